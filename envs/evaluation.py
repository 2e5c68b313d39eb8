"""Closed-loop evaluation of a driver on a suite of seeded routes, with a safety driver.

Writes ``metrics.json`` (per episode and ``mean``), ``table.md``, plots (each route's trajectory on the
map; speed and steering over time) and ``video.mp4`` of the first episode (camera beside the top-down
map, with a HUD). The metrics and the intervention rule are documented in ``envs.metrics``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from tqdm import tqdm

from envs.drive_env import DriveConfig, DriveEnv
from envs.metrics import EpisodeTrace, aggregate, episode_metrics, markdown_table, needs_intervention
from envs.standing import STANDING_SPEED_MPS, standing_reason

if TYPE_CHECKING:
    from agent.drivers import Driver

LIGHT_BGR = {"green": (60, 200, 60), "yellow": (40, 210, 240), "red": (50, 50, 230)}


def video_writer(path: Path, fps: int) -> Any:
    """An MP4 writer (H.264) for RGB frames; callers close it."""
    import imageio.v2 as imageio

    return imageio.get_writer(path, fps=fps, codec="libx264", quality=7, macro_block_size=8)


def draw_hud(image: np.ndarray, info: dict[str, Any], driver: str, extra: str = "") -> np.ndarray:
    """Speed, command, next light, route completion and infractions over an RGB frame (returns a copy)."""
    img = image.copy()
    lines = [f"{driver}  {info['ego']['speed_mps'] * 3.6:5.1f} km/h  cmd {info['command']}",
             f"route {100 * info['route']['completion']:5.1f}%  t {info['time_s']:6.1f}s {extra}"]
    light = info.get("next_light")
    if light:
        lines.append(f"light {light['state']} in {light['distance_m']:.0f} m")
    counts = info.get("infraction_counts") or {}
    if counts:
        lines.append(" ".join(f"{k}:{v}" for k, v in sorted(counts.items())))
    for k, text in enumerate(lines):
        y = 14 + 14 * k
        cv2.putText(img, text, (5, y), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(img, text, (5, y), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (255, 255, 255), 1, cv2.LINE_AA)
    if light:
        bgr = LIGHT_BGR[light["state"]]
        cv2.circle(img, (img.shape[1] - 12, 12), 7, bgr[::-1], -1, cv2.LINE_AA)
    return img


def video_frame(env: DriveEnv, driver: Driver, info: dict[str, Any], extra: str = "") -> np.ndarray:
    """The HUD picture (camera beside the map); a driver with an ``overlay()`` (the agent) gets its own
    perception overlay on top, so its videos show what it saw and why it acted."""
    hud = draw_hud(env.composite(), info, driver.name, extra)
    overlay = getattr(driver, "overlay", None)
    picture = overlay() if callable(overlay) else None
    if picture is None:
        return hud
    width = picture.shape[1]
    below = np.zeros((hud.shape[0], width, 3), np.uint8)
    below[:, :min(width, hud.shape[1])] = hud[:, :width]
    return np.concatenate([picture, below], axis=0)


def run_episode(env: DriveEnv, driver: Driver, seed: int, video: Any = None, progress: Any = None,
                options: dict[str, Any] | None = None) -> EpisodeTrace:
    """One evaluation episode; the safety driver intervenes by ``envs.metrics.needs_intervention``."""
    obs, info = env.reset(seed=seed, options=options)
    driver.reset(env)
    world = env.world
    assert world is not None
    trace = EpisodeTrace(seed, world.route_total_m, world.config.dt_s, town_seed=world.town.seed, weather=env.weather)
    done = False
    while not done:
        action = np.asarray(driver.act(obs), np.float32)
        obs, _, terminated, truncated, info = env.step(action)
        stands = info["ego"]["speed_mps"] < STANDING_SPEED_MPS
        trace.add_step(info, action, standing_clear=stands and standing_reason(world) is None)
        if needs_intervention(info) and not world.route_done:
            trace.interventions.append(info["time_s"])
            world.put_back_on_route()
            restart = getattr(driver, "on_intervention", None)  # a driver with state re-engages afresh
            if restart is not None:
                restart()
        if video is not None:
            video.append_data(video_frame(env, driver, info))
        if progress is not None:
            progress.update(1)
        done = terminated or truncated
    return trace


def plot_traces(env: DriveEnv, traces: list[EpisodeTrace], out: Path) -> list[str]:
    """One trajectory-on-map PNG per episode and one speed/steering-over-time PNG per episode."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sim.topdown import TopDownMap

    assert env.world is not None
    out.mkdir(parents=True, exist_ok=True)
    topdown = TopDownMap(env.world.town, pixels_per_m=1.5)
    background = topdown.render()
    written = []
    for tr in traces:
        px = topdown.to_px(np.stack([tr.x, tr.y], axis=1))
        fig, ax = plt.subplots(figsize=(5, 5), dpi=100)
        ax.imshow(background)
        ax.plot(px[:, 0], px[:, 1], color="tab:blue", lw=2, label="driven")
        ax.scatter(px[:1, 0], px[:1, 1], c="lime", s=30, zorder=3, label="start")
        for inf in tr.infractions:
            p = topdown.to_px(np.array([[inf["x"], inf["y"]]]))[0]
            ax.scatter(p[0], p[1], c="red", marker="x", s=50, zorder=4)
        ax.set_title(f"seed {tr.seed}: trajectory (red x: infractions)")
        ax.axis("off")
        ax.legend(loc="lower right", fontsize=7)
        name = f"trajectory_seed{tr.seed}.png"
        fig.savefig(out / name, bbox_inches="tight")
        plt.close(fig)
        written.append(name)
        t = np.arange(len(tr.speed)) * tr.dt_s
        fig, (a1, a2) = plt.subplots(2, 1, figsize=(7, 4), dpi=100, sharex=True)
        a1.plot(t, tr.speed, color="tab:blue")
        a1.set_ylabel("speed m/s")
        a2.plot(t, tr.steer, color="tab:orange")
        a2.set_ylabel("steer [-1, 1]")
        a2.set_xlabel("time s")
        for ti in tr.interventions:
            a1.axvline(ti, color="red", lw=0.8)
        fig.suptitle(f"seed {tr.seed}: speed and steering (red: interventions)")
        name = f"speed_steer_seed{tr.seed}.png"
        fig.savefig(out / name, bbox_inches="tight")
        plt.close(fig)
        written.append(name)
    return written


def evaluate(driver: Driver, config: DriveConfig, episodes: int, seed: int, out: Path, video: bool = True,
             options: Callable[[int], dict[str, Any]] | None = None) -> dict:
    """Run the suite, write every report file into ``out``, and return the metrics dict.

    ``options(k)`` gives the k-th episode's reset options (e.g. its town and weather)."""
    config = replace(config, terminate_on_infraction=False, terminate_on_route_deviation=False)
    env = DriveEnv(config, render_mode="rgb_array")
    out.mkdir(parents=True, exist_ok=True)
    traces, per_episode = [], []
    steps_hint = int(config.max_time_s / config.world.dt_s) * episodes
    writer = None
    try:
        with tqdm(total=steps_hint, desc=f"evaluating {driver.name}", unit="step", mininterval=2.0) as bar:
            for k in range(episodes):
                if video and k == 0:
                    writer = video_writer(out / "video.mp4", env.metadata["render_fps"])
                trace = run_episode(env, driver, seed + k, writer, bar, options(k) if options else None)
                if writer is not None:
                    writer.close()
                    writer = None
                traces.append(trace)
                per_episode.append(episode_metrics(trace))
                adas = getattr(driver, "adas_summary", None)  # ADAS warnings (the agent): counts and events
                if callable(adas):
                    per_episode[-1]["adas"] = adas()
        plots = plot_traces(env, traces, out / "plots")
    finally:
        if writer is not None:
            writer.close()
        env.close()
    mean = aggregate(per_episode)
    if any("adas" in e for e in per_episode):
        mean["adas_warnings"] = {k: sum(e["adas"]["counts"][k] for e in per_episode if "adas" in e)
                                 for k in per_episode[0]["adas"]["counts"]}
    metrics = {"driver": driver.name, "privileged": driver.privileged, "town_seed": config.town_seed,
               "weather": config.weather, "seeds": [seed, seed + episodes - 1], "episodes": per_episode,
               "mean": mean, "plots": plots, "video": "video.mp4" if video else None}
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    (out / "table.md").write_text(markdown_table(driver.name, per_episode, mean))
    return metrics
