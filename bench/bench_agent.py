"""The full agent's closed loop: render + perception + control, frames per second, and per-stage p50/p95.

    python bench/bench_agent.py                       # 600 frames, town 0 with traffic, detector every frame
    python bench/bench_agent.py --detect-every 2      # detector on every other frame (SORT predicts between)
    python bench/bench_agent.py --stereo              # distances by stereo matching (renders the pair too)
    python bench/bench_agent.py --no-blind-spot       # without the look in the mirror cameras (no mirror renders)
    python bench/bench_agent.py --threads 1           # a frame's stages one after another on one thread
    python bench/bench_agent.py --threads 2           # ... always on two threads (default 0: the faster)
    python bench/bench_agent.py --pipeline            # perception of frame t while the simulator renders t+1
    python bench/bench_agent.py --town-style downtown   # a downtown town, its road priors
    python bench/bench_agent.py --no-signs            # the six-class detector (no road-sign classes)

The agent drives (closed loop, its own actions), in the default town with its default traffic, at 320x160.
"Whole loop" is ``env.step`` (simulation and rendering) plus ``driver.act`` (every perception stage and
the controller) per frame. Its wall-clock frames per second is the headline figure; its **CPU time** is that of
the whole process (every thread: the agent runs a frame's independent stages on two threads, see
``AgentConfig.stage_threads``), which other jobs on a shared machine do not inflate. The stage rows are the
driver's own timings (``AgentDriver.timings``), each stage in CPU time of the thread that ran it; "wait" is the
calling thread waiting for the worker's stages. ONNX Runtime and OpenCV run one thread each per call.
``--pin`` pins the process to one core (with ``--threads 1``: the honest figure for one core of a small board).
The first line names the machine (CPU, vector extensions) and the load average.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.timing import latency_of, machine_line  # noqa: E402
from towndrive.agent.agent_driver import STAGES  # noqa: E402
from towndrive.agent.decision.blind_spot import BlindSpotConfig  # noqa: E402
from towndrive.agent.drivers import make_driver  # noqa: E402
from towndrive.drive_cli import agent_variant  # noqa: E402
from towndrive.envs.drive_env import DriveConfig, DriveEnv  # noqa: E402
from towndrive.sim.render import CameraConfig  # noqa: E402
from towndrive.sim.town import TownConfig  # noqa: E402
from towndrive.sim.town_style import STYLES  # noqa: E402
from towndrive.sim.world import WorldConfig  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--weather", default="noon")
    ap.add_argument("--detect-every", type=int, default=1)
    ap.add_argument("--stereo", action="store_true", help="distances from the stereo pair (renders it: slower)")
    ap.add_argument("--pin", action="store_true", help="pin the process to one CPU core")
    ap.add_argument("--model", type=Path, default=None, help="PilotNet model (default data/models/pilotnet.pt)")
    ap.add_argument("--threads", type=int, default=0, choices=(0, 1, 2),
                    help="threads for a frame's independent stages: 1 one after another, 2 two cores, 0 (default) the "
                         "faster of the two, timed now and then; the actions are the same")
    ap.add_argument("--pipeline", action="store_true",
                    help="perceive frame t while the simulator renders frame t+1 (one frame of latency)")
    ap.add_argument("--town-style", default="classic", choices=sorted(STYLES),
                    help="the kind of town (the agent gets that style's road priors)")
    ap.add_argument("--signs", action=argparse.BooleanOptionalAction, default=None,
                    help="the detector with the road-sign classes and the sign reader (the default); --no-signs: the "
                         "six-class detector (as drive --no-signs)")
    ap.add_argument("--no-blind-spot", action="store_true",
                    help="without the mirror-camera look before lane changes (agent.decision.blind_spot; on by default)")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    if args.pin and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    config = DriveConfig(world=WorldConfig(town=TownConfig.of_style(args.town_style)),
                         camera=CameraConfig(stereo=args.stereo), observe_stereo=args.stereo, weather=args.weather,
                         terminate_on_infraction=False, terminate_on_route_deviation=False)
    kwargs: dict = {"detect_every": args.detect_every, "distance": "stereo" if args.stereo else "geometry",
                    "clock": "cpu", "stage_threads": args.threads, "pipeline": args.pipeline}
    if args.model is not None:
        kwargs["model"] = args.model
    kwargs.update(agent_variant(args.town_style, "style", args.signs))
    if args.no_blind_spot:
        kwargs["blind_spot"] = BlindSpotConfig(enabled=False)
    driver = make_driver("agent", **kwargs)
    env = DriveEnv(config, render_mode="rgb_array")
    obs, _ = env.reset(seed=args.seed)
    driver.reset(env)
    step_s, act_s, loop_s, cpu_s, cpu_step_s, cpu_act_s = [], [], [], [], [], []
    for k in range(args.warmup + args.frames):
        t0, c0 = time.perf_counter(), time.process_time()
        action = driver.act(obs)
        t1, c1 = time.perf_counter(), time.process_time()
        obs, _, terminated, truncated, _ = env.step(action)
        t2, c2 = time.perf_counter(), time.process_time()
        if k >= args.warmup:
            act_s.append(t1 - t0)
            step_s.append(t2 - t1)
            loop_s.append(t2 - t0)
            cpu_s.append(c2 - c0)
            cpu_step_s.append(c2 - c1)
            cpu_act_s.append(c1 - c0)
        if terminated or truncated:
            obs, _ = env.reset(seed=args.seed + k + 1)
            driver.reset(env)
    env.close()
    timings = driver.timings[-args.frames:] if len(driver.timings) >= args.frames else driver.timings
    cam = config.camera
    loop = latency_of(loop_s)
    print(machine_line())
    town = "" if args.town_style == "classic" else f"{args.town_style} town, its road priors, "
    print(f"Agent closed loop at {cam.width}x{cam.height}, {args.frames} frames, seed {args.seed}, {args.weather}, {town}"
          f"{'the six-class detector, ' if args.signs is False else 'the sign detector, '}"
          f"detector every {args.detect_every} frame(s), distances by {'stereo' if args.stereo else 'box geometry'}, "
          f"stage threads {args.threads or 'the faster of 1 and 2'}{', pipelined' if args.pipeline else ''}")
    cpu = latency_of(cpu_s)
    print(f"whole loop, wall clock: {len(loop_s) / sum(loop_s):.1f} frames/s (mean), p50 {loop.p50_ms:.1f} ms, "
          f"p95 {loop.p95_ms:.1f} ms; load average {os.getloadavg()[0]:.1f}")
    print(f"whole loop, CPU time (all threads): {len(cpu_s) / sum(cpu_s):.1f} frames/s (mean), p50 {cpu.p50_ms:.1f} ms, "
          f"p95 {cpu.p95_ms:.1f} ms (env.step {latency_of(cpu_step_s).p50_ms:.1f} ms, "
          f"driver.act {latency_of(cpu_act_s).p50_ms:.1f} ms at p50)")
    print("")
    print("| stage (CPU time of its thread) | p50 ms | p95 ms | mean ms |")
    print("|---|---|---|---|")
    rows = [("env.step (simulation + rendering)", latency_of(cpu_step_s)), ("driver.act (all below)", latency_of(cpu_act_s))]
    stages = [s for s in STAGES if any(s in t for t in timings)]
    for stage in stages:
        samples = [t[stage] / 1000.0 for t in timings if stage in t]
        if stage == "detector" and args.detect_every > 1:  # only the frames it ran on
            samples = [s for s in samples if s > 0] or samples
            stage = f"detector (every {args.detect_every})"
        rows.append((f"  {stage}", latency_of(samples)))
    rows.append(("whole loop", cpu))
    for name, lat in rows:
        print(f"| {name} | {lat.p50_ms:.2f} | {lat.p95_ms:.2f} | {lat.mean_ms:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
