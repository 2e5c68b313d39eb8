"""Closed-loop evaluation of a driver on a suite of seeded routes, with a safety driver.

Writes ``metrics.json`` (per episode and ``mean``, with every infraction and take-over as an event),
``table.md`` (the events listed under each episode), a few seconds of video around each event in
``clips/``, plots (each route's trajectory on its town's map; speed and steering over time) and ``video.mp4``
of the first episode (camera beside the top-down map, with a HUD). Each episode is a work item
(``EvalEpisode``) that writes its own clips, plots and video, so episodes can run on several processes
(``envs.parallel``) and give the serial run's report. The metrics, the intervention rule and
the Leaderboard rules one can switch on are documented in ``envs.metrics``; every episode's infractions
are also recomputed by ``envs.audit`` and the comparison is reported.
"""

from __future__ import annotations

import json
import math
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from tqdm import tqdm

from towndrive.envs.audit import AuditTrace, audit_episode
from towndrive.envs.drive_env import DriveConfig, DriveEnv
from towndrive.envs.metrics import (
    BLOCKED_SPEED_MPS,
    INTERVENTION_INFRACTIONS,
    MIN_SPEED_RADIUS_M,
    EpisodeTrace,
    EvaluationRules,
    aggregate,
    episode_metrics,
    failed_episode_metrics,
    markdown_table,
    needs_intervention,
)
from towndrive.envs.parallel import DriverSpec, Interrupted, RunSummary, Worker, run_items
from towndrive.envs.standing import STANDING_SPEED_MPS, standing_reason

if TYPE_CHECKING:
    from towndrive.agent.drivers import Driver
    from towndrive.sim.world import World

LIGHT_BGR = {"green": (60, 200, 60), "yellow": (40, 210, 240), "red": (50, 50, 230)}


def video_writer(path: Path, fps: int) -> Any:
    """An MP4 writer (H.264) for RGB frames; callers close it."""
    import imageio.v2 as imageio

    return imageio.get_writer(path, fps=fps, codec="libx264", quality=7, macro_block_size=8)


def draw_hud(image: np.ndarray, info: dict[str, Any], driver: str, extra: str = "") -> np.ndarray:
    """Speed, command, next light, route completion and infractions over an RGB frame (returns a copy)."""
    img = image.copy()
    lines = [f"{driver} | {info['ego']['speed_mps'] * 3.6:.1f} km/h | command {info['command']}",
             f"route {100 * info['route']['completion']:.1f} % | t {info['time_s']:.1f} s {extra}".rstrip()]
    light = info.get("next_light")
    if light:
        lines.append(f"light {light['state']} in {light['distance_m']:.0f} m")
    counts = info.get("infraction_counts") or {}
    if counts:
        lines.append(" ".join(f"{k}:{v}" for k, v in sorted(counts.items())))
    for k, text in enumerate(lines):
        _label(img, text, 5, 15 + 15 * k, 0.38)
    if light:
        bgr = LIGHT_BGR[light["state"]]
        cv2.circle(img, (img.shape[1] - 12, 12), 7, bgr[::-1], -1, cv2.LINE_AA)
    return img


def _label(img: np.ndarray, text: str, x: int, y: int, scale: float = 0.4) -> None:
    """White text with a dark outline, readable on any background. The outline is the thin text drawn at the eight
    neighbouring offsets: OpenCV's advance grows with the stroke's thickness, so a thick dark copy drifts right."""
    for dx, dy in ((-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)):
        cv2.putText(img, text, (x + dx, y + dy), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)


def truth_panel(info: dict[str, Any], driver: str, width: int, height: int, extra: str = "") -> np.ndarray:
    """The simulator's ground truth as text: speed, command, route, time, the next light and infractions."""
    img = np.full((height, width, 3), 24, np.uint8)
    light = info.get("next_light")
    counts = info.get("infraction_counts") or {}
    lines = ["ground truth (simulator)",
             f"driver: {driver}",
             f"speed: {info['ego']['speed_mps'] * 3.6:.1f} km/h",
             f"route command: {info['command']}",
             f"route: {100 * info['route']['completion']:.1f} % done   time: {info['time_s']:.1f} s",
             f"next light: {light['state']}, {light['distance_m']:.0f} m ahead" if light else "next light: none ahead",
             "infractions: " + (", ".join(f"{k} {v}" for k, v in sorted(counts.items())) if counts else "none")]
    if extra:
        lines.append(extra)
    step = max(14, (height - 12) // len(lines))
    for k, text in enumerate(lines):
        _label(img, text, 8, 16 + step * k, 0.45 if k == 0 else 0.4)
    return img


def video_frame(env: DriveEnv, driver: Driver, info: dict[str, Any], extra: str = "") -> np.ndarray:
    """The HUD picture (camera beside the map); a driver with an ``overlay()`` (the agent) gets its own
    perception overlay on top, labelled as such, above the map and the ground truth, so its videos show what it
    saw and why it acted next to what was really there."""
    overlay = getattr(driver, "overlay", None)
    picture = overlay() if callable(overlay) else None
    if picture is None:
        return draw_hud(env.composite(), info, driver.name, extra)
    picture = picture.copy()
    _label(picture, "camera + perception", 6, picture.shape[0] - 8, 0.35)  # left of the steering bar
    side = picture.shape[0] // 2  # the overlay is the camera frame at twice its size: the bottom row is one frame high
    width = picture.shape[1]
    tile = env.map_view(side)  # the top-down map around the car
    _label(tile, "map (ground truth)", 4, side - 6, 0.35)
    row = np.concatenate([tile, truth_panel(info, driver.name, max(width - side, 1), side, extra)], axis=1)
    return np.concatenate([picture, row[:, :width]], axis=0)


class ClipWriter:
    """Short clips around events: the last ``before_s`` of video frames are kept, and an event's clip is
    written once ``after_s`` more have been seen (or when the episode ends)."""

    def __init__(self, folder: Path, fps: int, before_s: float = 3.0, after_s: float = 2.0) -> None:
        self.folder, self.fps = folder, fps
        self.before = deque(maxlen=max(1, int(round(before_s * fps))))
        self.after_steps = int(round(after_s * fps))
        self.pending: list[tuple[str, list[np.ndarray], int]] = []

    def add(self, frame: np.ndarray) -> None:
        self.before.append(frame)
        still = []
        for name, frames, left in self.pending:
            frames.append(frame)
            if left <= 1:
                self._write(name, frames)
            else:
                still.append((name, frames, left - 1))
        self.pending = still

    def event(self, name: str) -> str:
        """Start a clip for an event seen in the frame just added; returns its file name."""
        self.pending.append((name, list(self.before), self.after_steps))
        return name

    def flush(self) -> None:
        for name, frames, _ in self.pending:
            self._write(name, frames)
        self.pending = []

    def _write(self, name: str, frames: list[np.ndarray]) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        writer = video_writer(self.folder / name, self.fps)
        try:
            for frame in frames:
                writer.append_data(frame)
        finally:
            writer.close()


@dataclass
class _RuleState:
    """What the Leaderboard rules of ``EvaluationRules`` count as the episode goes on."""

    still_s: float = 0.0  # seconds without moving (agent blocked)
    hold_s: float = 0.0  # seconds standing with nothing in the path (hold timeout)
    section_end_m: float = 0.0  # where the current minimum-speed section ends, in route metres
    ego_speed_sum: float = 0.0
    traffic_speed_sum: float = 0.0
    traffic_steps: int = 0


def _min_speed_event(state: _RuleState, info: dict[str, Any]) -> dict[str, Any] | None:
    """Close a minimum-speed section: an event when the car was slower than the traffic around it."""
    event = None
    if state.traffic_steps and state.traffic_speed_sum > 0:
        ratio = (state.ego_speed_sum / state.traffic_steps) / (state.traffic_speed_sum / state.traffic_steps)
        if ratio < 1.0:
            event = {"kind": "min_speed", "time_s": info["time_s"], "x": info["ego"]["x"], "y": info["ego"]["y"],
                     "other_id": 0, "penalty": round(0.7 + 0.3 * ratio, 6),
                     "why": f"mean speed {100 * ratio:.1f}% of the surrounding traffic's"}
    state.ego_speed_sum = state.traffic_speed_sum = 0.0
    state.traffic_steps = 0
    return event


def _traffic_speed(world: World) -> float | None:
    """The mean speed of the vehicles within ``MIN_SPEED_RADIUS_M`` of the ego (None when there are none)."""
    speeds = [v.speed for v in world.npcs if math.hypot(*(v.position - world.ego.position)) < MIN_SPEED_RADIUS_M]
    return float(np.mean(speeds)) if speeds else None


def run_episode(env: DriveEnv, driver: Driver, seed: int, video: Any = None, progress: Any = None,
                options: dict[str, Any] | None = None, rules: EvaluationRules | None = None,
                clips: ClipWriter | None = None, audit: bool = False, until_s: float | None = None) -> EpisodeTrace:
    """One evaluation episode; the safety driver intervenes by ``envs.metrics.needs_intervention``.

    ``rules``: the take-over cost and Leaderboard rules; ``clips``: write a clip around every event;
    ``audit``: recompute the infractions independently (``envs.audit``); ``until_s``: stop at this time
    (a replay of the episode up to a moment)."""
    rules = rules or EvaluationRules()
    obs, info = env.reset(seed=seed, options=options)
    driver.reset(env)
    world = env.world
    assert world is not None
    trace = EpisodeTrace(seed, world.route_total_m, world.config.dt_s, town_seed=world.town.seed, weather=env.weather,
                         takeover_penalty=rules.takeover_penalty, town_style=world.town.config.style)
    truth = AuditTrace() if audit else None
    state = _RuleState(section_end_m=world.route_progress_m + rules.min_speed_section_m)
    dt = world.config.dt_s
    carried = False
    done = False
    while not done:
        action = np.asarray(driver.act(obs), np.float32)
        obs, _, terminated, truncated, info = env.step(action)
        speed = info["ego"]["speed_mps"]
        clear = speed < STANDING_SPEED_MPS and standing_reason(world) is None
        extra = _rule_events(rules, state, world, info, clear, dt)
        info["infractions"] = info["infractions"] + extra
        trace.add_step(info, action, standing_clear=clear)
        if truth is not None:
            truth.record(world, carried)
            carried = False
        takeover = needs_intervention(info) and not world.route_done
        reason = str(getattr(driver, "reason", "") or "") if info["infractions"] or takeover else ""
        new_events = [{**inf, **({"reason": reason} if reason else {})} for inf in info["infractions"]]
        if takeover:
            trace.interventions.append(info["time_s"])
            new_events.append(_takeover_event(info, reason))
            world.put_back_on_route()
            obs = env.observe()  # the driver re-engages on a frame of where the car now stands
            carried = True
            restart = getattr(driver, "on_intervention", None)  # a driver with state re-engages afresh
            if restart is not None:
                restart()
        frame = video_frame(env, driver, info) if (video is not None or clips is not None) else None
        if video is not None:
            video.append_data(frame)
        if clips is not None and frame is not None:
            clips.add(frame)
            for ev in new_events:
                ev["clip"] = clips.event(f"seed{seed}_{ev['time_s']:07.2f}s_{ev['kind']}.mp4")
        trace.events += new_events
        if progress is not None:
            progress.update(1)
        blocked = any(ev["kind"] == "agent_blocked" for ev in extra)
        done = terminated or truncated or blocked or (until_s is not None and info["time_s"] >= until_s - 1e-9)
    if rules.min_speed:
        last = _min_speed_event(state, info)
        if last is not None:
            trace.infractions.append(last)
            trace.events.append(last)
    if clips is not None:
        clips.flush()
    if truth is not None:
        trace.audit = audit_episode(world.town, truth, trace.infractions)
    return trace


def _takeover_event(info: dict[str, Any], reason: str) -> dict[str, Any]:
    offset = info["lane_band_offset_m"]
    kinds = [inf["kind"] for inf in info["infractions"] if inf["kind"] in INTERVENTION_INFRACTIONS]
    why = ", ".join(kinds) if kinds else (f"{offset:.2f} m outside its lanes" if math.isfinite(offset) else "off road")
    return {"kind": "takeover", "time_s": info["time_s"], "x": info["ego"]["x"], "y": info["ego"]["y"],
            "speed_mps": info["ego"]["speed_mps"], "why": why, **({"reason": reason} if reason else {})}


def _rule_events(rules: EvaluationRules, state: _RuleState, world: World, info: dict[str, Any], clear: bool,
                 dt: float) -> list[dict[str, Any]]:
    """This step's events from the Leaderboard rules that are switched on."""
    out: list[dict[str, Any]] = []
    here = {"time_s": info["time_s"], "x": info["ego"]["x"], "y": info["ego"]["y"], "other_id": 0,
            "speed_mps": info["ego"]["speed_mps"]}
    speed = info["ego"]["speed_mps"]
    if rules.blocked_limit_s is not None:
        state.still_s = state.still_s + dt if speed < BLOCKED_SPEED_MPS else 0.0
        if state.still_s >= rules.blocked_limit_s - 1e-9:
            out.append({**here, "kind": "agent_blocked", "why": f"not moving for {state.still_s:.0f} s: the route ends"})
    if rules.hold_timeout_s is not None:
        state.hold_s = state.hold_s + dt if clear else 0.0
        if state.hold_s >= rules.hold_timeout_s - 1e-9:
            out.append({**here, "kind": "hold_timeout", "why": f"stood {state.hold_s:.0f} s with nothing in the path"})
            state.hold_s = 0.0
    if rules.min_speed:
        traffic = _traffic_speed(world)
        if traffic is not None:
            state.ego_speed_sum += speed
            state.traffic_speed_sum += traffic
            state.traffic_steps += 1
        if info["route"]["progress_m"] >= state.section_end_m:
            state.section_end_m += rules.min_speed_section_m
            event = _min_speed_event(state, info)
            if event is not None:
                out.append(event)
    return out


_MAP_CACHE: dict[int, tuple[Any, Any, np.ndarray]] = {}  # id(town) -> (town, TopDownMap, its picture): the last one


def plot_trace(town: Any, tr: EpisodeTrace, out: Path) -> list[str]:
    """The episode's trajectory on its own town's map and its speed and steering over time: two PNGs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from towndrive.sim.topdown import TopDownMap

    cached = _MAP_CACHE.get(id(town))
    if cached is None or cached[0] is not town:
        topdown = TopDownMap(town, pixels_per_m=1.5)
        _MAP_CACHE.clear()
        cached = _MAP_CACHE[id(town)] = (town, topdown, topdown.render())
    _, topdown, background = cached
    out.mkdir(parents=True, exist_ok=True)
    written = []
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


@dataclass(frozen=True)
class EvalEpisode:
    """One evaluation episode as a work item (``envs.parallel``): everything it needs, so that it gives the same
    result in any process. ``video``: write ``out/video.mp4`` (the run's first episode)."""

    index: int
    seed: int
    config: DriveConfig
    out: Path
    options: dict[str, Any] | None = None
    rules: EvaluationRules = EvaluationRules()
    until_s: float | None = None
    video: bool = False
    clips: bool = True
    audit: bool = True
    plots: bool = True

    def run(self, worker: Worker, progress: Any = None) -> dict[str, Any]:
        """Run it on ``worker``'s env and driver: ``{"metrics", "plots", "driver", "privileged"}``."""
        env, driver = worker.env(self.config), worker.driver
        worker.start_episode(self.index)
        fps = env.metadata["render_fps"]
        clip_writer = ClipWriter(self.out / "clips", fps) if self.clips else None
        writer = video_writer(self.out / "video.mp4", fps) if self.video else None
        try:
            trace = run_episode(env, driver, self.seed, writer, progress, self.options, self.rules, clip_writer,
                                self.audit, self.until_s)
        finally:
            if writer is not None:
                writer.close()
        metrics = episode_metrics(trace)
        adas = getattr(driver, "adas_summary", None)  # ADAS warnings (the agent): counts and events
        if callable(adas):
            metrics["adas"] = adas()
        assert env.world is not None
        plots = plot_trace(env.world.town, trace, self.out / "plots") if self.plots else []
        return {"metrics": metrics, "plots": plots, "driver": driver.name, "privileged": driver.privileged}

    def failed(self, error: str) -> dict[str, Any]:
        options = self.options or {}
        metrics = failed_episode_metrics(self.seed, options.get("town_seed", self.config.town_seed),
                                         options.get("weather", self.config.weather), error)
        return {"metrics": metrics, "plots": [], "driver": None, "privileged": None}


def evaluate(driver: Driver | DriverSpec, config: DriveConfig, episodes: int, seed: int, out: Path,
             video: bool = True, options: Callable[[int], dict[str, Any]] | None = None,
             rules: EvaluationRules | None = None, clips: bool = True, audit: bool = True, plots: bool = True,
             until_s: float | None = None, workers: int = 1, summary: RunSummary | None = None,
             should_stop: Callable[[], bool] | None = None, ray: str | None = None) -> dict:
    """Run the suite, write every report file into ``out``, and return the metrics dict.

    ``options(k)`` gives the k-th episode's reset options (e.g. its town and weather); ``rules`` the take-over
    cost and the Leaderboard rules in force; ``clips`` writes a clip around every infraction and take-over
    into ``out/clips``; ``audit`` recomputes every infraction independently (``envs.audit``) and reports the
    comparison; ``plots`` writes the trajectory and speed plots; ``until_s`` stops each episode at that time.

    ``workers`` > 1 runs the episodes on that many processes (``envs.parallel``; ``driver`` must then be a
    ``DriverSpec``), ``ray`` (an address, or ``"local"``) as Ray tasks; the report is the serial run's. An episode
    whose worker died twice, or whose driver raised there, is reported failed with its error and counted as zero.
    On Ctrl-C the finished episodes' report is written (``interrupted`` says how many of how many) and
    ``envs.parallel.Interrupted`` is raised."""
    config = replace(config, terminate_on_infraction=False, terminate_on_route_deviation=False)
    rules = rules or EvaluationRules()
    out.mkdir(parents=True, exist_ok=True)
    items = [EvalEpisode(k, seed + k, config, out, options(k) if options else None, rules, until_s, video and k == 0,
                         clips, audit, plots) for k in range(episodes)]
    if workers > 1 or ray is not None:
        if not isinstance(driver, DriverSpec):
            raise ValueError("evaluate(workers > 1) builds a driver in each worker: give a DriverSpec, not a driver.")
        name = driver.name
        try:
            results = run_items(items, driver, workers, f"evaluating {name} ({workers} workers)", should_stop,
                                summary, ray)
        except Interrupted as stop:
            done = [stop.results[k] for k in sorted(stop.results)]
            _write_report(done, name, None, config, seed, episodes, rules, out, video,
                          interrupted={"finished": len(done), "of": episodes})
            raise
        return _write_report(results, name, None, config, seed, episodes, rules, out, video)
    instance = driver.build() if isinstance(driver, DriverSpec) else driver
    worker = Worker(instance)
    results = []
    try:
        steps_hint = int(config.max_time_s / config.world.dt_s) * episodes
        with tqdm(total=steps_hint, desc=f"evaluating {instance.name}", unit="step", mininterval=2.0) as bar:
            for item in items:
                results.append(item.run(worker, bar))
    finally:
        worker.close()
    return _write_report(results, instance.name, instance.privileged, config, seed, episodes, rules, out, video)


def _write_report(results: list[dict[str, Any]], name: str, privileged: bool | None, config: DriveConfig, seed: int,
                  episodes: int, rules: EvaluationRules, out: Path, video: bool,
                  interrupted: dict[str, int] | None = None) -> dict:
    """metrics.json and table.md from the episodes' results, in episode order."""
    per_episode = [r["metrics"] for r in results]
    ran = [r for r in results if r["driver"] is not None]
    if ran:
        name, privileged = ran[0]["driver"], ran[0]["privileged"]
    mean = aggregate(per_episode) if per_episode else {}
    with_adas = [e for e in per_episode if "adas" in e]
    if with_adas:
        mean["adas_warnings"] = {k: sum(e["adas"]["counts"][k] for e in with_adas) for k in with_adas[0]["adas"]["counts"]}
    metrics = {"driver": name, "privileged": privileged, "town_seed": config.town_seed,
               "weather": config.weather, "seeds": [seed, seed + episodes - 1], "rules": asdict(rules),
               "episodes": per_episode, "mean": mean, "plots": [p for r in results for p in r["plots"]],
               "video": "video.mp4" if video else None,
               **({"interrupted": interrupted} if interrupted is not None else {})}
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    if per_episode:
        (out / "table.md").write_text(markdown_table(name, per_episode, mean))
    return metrics
