"""Drive-v0 throughput: env steps per second at 200x66 and 320x160 on the default town with traffic,
the bare ``getCameraImage`` cost of the same scene measured in the same run (so the simulation's own
overhead is a ratio), steps per second with no camera, and each town style against the classic town.

Run: ``python bench/bench_env.py`` (add ``--steps N`` for longer runs). Pins itself to one core
where the OS allows, as the targets are for one core. ``--render-processes 2``: the env shares each frame's
TinyRenderer work with a helper process (``DriveConfig.render_processes``) and the benchmark keeps every core.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import pybullet as p

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.timing import machine_line  # noqa: E402
from towndrive.agent.autopilot import Autopilot
from towndrive.envs.drive_env import DriveConfig, DriveEnv
from towndrive.sim.render import CameraConfig, _projection

TARGETS = {(200, 66): 150.0, (320, 160): 60.0}


def bare_camera_image_ms(env: DriveEnv, repeats: int) -> float:
    """The raw TinyRenderer call for the env's current scene and pose, nothing else (median ms)."""
    r = env.renderer
    assert r is not None and env.world is not None
    cam = env.config.camera
    ego = env.world.ego
    eye, forward = r.camera_position((float(ego.position[0]), float(ego.position[1]), float(ego.heading)), cam)
    view = p.computeViewMatrix(eye.tolist(), (eye + forward).tolist(), [0.0, 0.0, 1.0], **r._cid)
    proj = _projection(cam)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        p.getCameraImage(cam.width, cam.height, viewMatrix=view, projectionMatrix=proj, renderer=p.ER_TINY_RENDERER,
                         flags=p.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX, **r._cid)
        times.append(time.perf_counter() - t)
    return 1000 * statistics.median(times)


def run(config: DriveConfig, steps: int, seed: int) -> dict[str, float]:
    """Steps per second of ``config`` (with several render processes "bare render" is the main process's share)."""
    env = DriveEnv(config)
    driver = Autopilot()
    env.reset(seed=seed)
    driver.reset(env)
    step_times, bare = [], []
    done = 0
    while done < steps:
        assert env.world is not None
        action = driver.act({})
        t = time.perf_counter()
        _, _, term, trunc, _ = env.step(action)
        step_times.append(time.perf_counter() - t)
        done += 1
        if config.render_camera and done % 25 == 0:
            bare.append(bare_camera_image_ms(env, 3))
        if term or trunc:
            env.reset(seed=seed + done)
            driver.reset(env)
    env.close()
    step_ms = 1000 * statistics.median(step_times)
    out = {"steps_per_s": 1000.0 / step_ms, "step_ms_p50": step_ms,
           "step_ms_p95": 1000 * float(np.percentile(step_times, 95))}
    if bare:
        out["bare_render_ms"] = statistics.median(bare)
        out["overhead_fraction"] = max(0.0, 1.0 - out["bare_render_ms"] / step_ms)
    return out


def style_rows(steps: int, seed: int, processes: int = 1) -> bool:
    """Steps per second at 320x160 in each town style against the classic town, in the same run: one env per style,
    stepped in turn (one step each, round and round), so that a busy neighbour or a slower core weighs on every
    style alike. Issue 30's bar: the busiest style within 15 % of the classic town. Returns whether it is met."""
    from towndrive.sim.town import TownConfig
    from towndrive.sim.town_style import STYLES
    from towndrive.sim.world import WorldConfig

    envs, drivers, times, bare = {}, {}, {}, {}
    for name in STYLES:
        config = DriveConfig(world=WorldConfig(town=TownConfig.of_style(name)), camera=CameraConfig(width=320, height=160),
                             render_processes=processes)
        envs[name], drivers[name], times[name], bare[name] = DriveEnv(config), Autopilot(), [], []
        envs[name].reset(seed=seed)
        drivers[name].reset(envs[name])
    for k in range(steps):
        for name, env in envs.items():
            action = drivers[name].act({})
            t = time.perf_counter()
            _, _, term, trunc, _ = env.step(action)
            times[name].append(time.perf_counter() - t)
            if k % 25 == 0:
                bare[name].append(bare_camera_image_ms(env, 3))
            if term or trunc:
                env.reset(seed=seed + k + 1)
                drivers[name].reset(env)
    speed = {name: 1.0 / statistics.median(t) for name, t in times.items()}
    print(f"town styles at 320x160, town seed 0, {steps} steps each, the styles' envs stepped in turn")
    for name in STYLES:
        envs[name].close()
        print(f"{name:>10} {speed[name]:9.1f} steps/s  {speed[name] / speed['classic']:6.3f} x classic  "
              f"bare render {statistics.median(bare[name]):6.2f} ms  p95 {1000 * float(np.percentile(times[name], 95)):6.2f} ms")
    busiest = min(speed, key=lambda name: speed[name])
    slower = 1.0 - speed[busiest] / speed["classic"]
    ok = slower <= 0.15
    print(f"slowest style {busiest}: {100 * slower:.1f}% slower than classic (target <= 15%: {'met' if ok else 'NOT MET'})")
    return ok


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--styles-only", action="store_true", help="only the town styles against the classic town")
    ap.add_argument("--render-processes", type=int, default=1,
                    help="processes sharing each frame's rendering (DriveConfig.render_processes); >1 keeps all cores")
    args = ap.parse_args()
    n = args.render_processes
    if hasattr(os, "sched_setaffinity") and n == 1:
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    print(machine_line())
    if args.styles_only:
        return 0 if style_rows(args.steps, args.seed, n) else 1
    cores = "one core" if n == 1 else f"{n} render processes, all cores"
    print(f"Drive-v0 on the default town with traffic, {args.steps} steps each, {cores}")
    print(f"{'camera':>10} {'steps/s':>9} {'p50 ms':>8} {'p95 ms':>8} {'bare render ms':>15} {'sim overhead':>13}"
          f"  {'steps/s target':>20}  {'overhead <= 30%':>15}")
    ok = True
    for (w, h), target in TARGETS.items():
        res = run(DriveConfig(camera=CameraConfig(width=w, height=h), render_processes=n), args.steps, args.seed)
        speed_ok = res["steps_per_s"] >= target
        overhead_ok = res["overhead_fraction"] <= 0.30
        ok &= speed_ok and overhead_ok
        speed_word = f">={int(target)} {'met' if speed_ok else 'NOT MET'}"
        print(f"{f'{w}x{h}':>10} {res['steps_per_s']:9.1f} {res['step_ms_p50']:8.2f} {res['step_ms_p95']:8.2f} "
              f"{res['bare_render_ms']:15.2f} {100 * res['overhead_fraction']:12.1f}%  "
              f"{speed_word:>20}  {'met' if overhead_ok else 'NOT MET':>15}")
    res = run(DriveConfig(render_camera=False), args.steps * 3, args.seed)
    print(f"{'none':>10} {res['steps_per_s']:9.1f} {res['step_ms_p50']:8.2f} {res['step_ms_p95']:8.2f}")
    print("targets: >=150 steps/s at 200x66, >=60 at 320x160, simulation overhead <= 30% of the step")
    ok &= style_rows(args.steps, args.seed, n)
    print("all targets met" if ok else "some targets NOT met (see rows above)")
    print(f"load average at the end: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
