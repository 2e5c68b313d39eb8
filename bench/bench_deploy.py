"""Deployment profiles on this CPU: per-stage latency with torch vs ONNX Runtime, and detector frame skipping.

    python bench/bench_deploy.py                                  # cpu profile, 3 drives x 300 frames
    python bench/bench_deploy.py --pilotnet out/pilotnet/bc.pt    # until data/models/pilotnet.pt ships

Frames: drives of the autopilot in dense traffic (``bench/eval_tracking.py``'s recording: seeds 11, 12, 13,
ground-truth boxes with the simulator's ids). The perception loop of the agent runs over them in order, as
it would while driving: PilotNet, the detector, SORT, lanes, stop line, each timed per frame (one thread
each; OpenCV one thread) in CPU time of the calling thread, which other programs on a shared machine do not
inflate; the wall-clock FPS of the same loop is printed beside it. Stereo is off in the cpu profile and is
not timed here (bench_perception: SGBM).

1. Per stage p50/p95 for the cpu profile with each backend that runs here: torch fp32, ONNX Runtime fp32
   (the profile's choice), ONNX Runtime fp16 (runs, but x86 CPUs have no fast fp16 arithmetic) and ONNX
   Runtime int8 (the QDQ files of ``train.py export``, calibrated on recorded frames).
2. Detector every k frames (SORT predicts in between, seed 000's skipping): loop FPS, and tracking MOTA /
   IDF1 / identity switches of the trained detector + SORT against the simulator's ids (motmetrics,
   ``eval_tracking.evaluate``, objects under 25 visible pixels are ignore regions).
3. The whole agent driver (``agent.deploy.profiled_agent.ProfiledAgent``) replayed on a recorded episode, per backend,
   detector precision and skipping, its stages one after another on the calling thread (``stage_threads=1``).

The fp16 and int8 files come from ``python train.py export --profile cpu`` (``--export-dir`` elsewhere).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.eval_tracking import evaluate, record  # noqa: E402
from bench.timing import latency_of  # noqa: E402
from towndrive.agent.deploy.backends import open_detector, open_pilotnet  # noqa: E402
from towndrive.agent.deploy.profiles import load_profile, profile_from_dict  # noqa: E402
from towndrive.agent.perception.lanes import LaneDetector  # noqa: E402
from towndrive.agent.perception.stop_line import StopLineDetector  # noqa: E402
from towndrive.agent.perception.tracking import Sort, SortConfig  # noqa: E402

STAGES = ("pilotnet", "detector", "tracking", "lanes", "stop_line")
MOVERS = ("car", "truck", "pedestrian")


def variant(base_name: str, backend: str, precision: str, pilotnet: Path | None, export_dir: str | None,
            detector_precision: str | None = None) -> object:
    """The base profile with both models on ``backend``/``precision`` (the detector on ``detector_precision``
    if given), and another PilotNet checkpoint if given."""
    base = load_profile(base_name)
    models = {}
    for name, spec in base.models.items():
        checkpoint = str(pilotnet) if name == "pilotnet" and pilotnet else spec.checkpoint
        p = detector_precision if name == "detector" and detector_precision else precision
        models[name] = {"checkpoint": checkpoint, "backend": backend, "precision": p}
    data = {"name": base.name, "models": models, "export_dir": export_dir or base.export_dir}
    return profile_from_dict(data, f"{base.source_file} ({backend} {precision})")


def interleaved(configs: list[tuple[object, int]], sequences: list) -> list[dict[str, list[float]]]:
    """``run_loop`` for each (profile, every), taking turns drive by drive, so that a slow spell of the shared
    machine falls on every configuration alike rather than on whichever ran then."""
    out: list[dict[str, list[float]]] = [{} for _ in configs]
    for seq in sequences:
        for acc, (profile, every) in zip(out, configs, strict=True):
            for stage, values in run_loop(profile, [seq], every).items():
                acc.setdefault(stage, []).extend(values)
    return out


def run_loop(profile: object, sequences: list, every: int, clock: Callable[[], float] = time.thread_time
             ) -> dict[str, list[float]]:
    """The perception loop over every drive in order; per-stage seconds per frame by ``clock``, and the loop's
    wall time per frame as ``wall``.

    The default clock is this thread's CPU time: every model runs on one thread in the calling thread (ONNX
    Runtime with one intra-op thread, torch with one thread, OpenCV with one), so it counts all their work
    but not the time other programs on this shared 2-core machine hold the CPU.
    """
    pilot = open_pilotnet(profile)
    det = open_detector(profile)
    cam_lanes = LaneDetector()
    stop = StopLineDetector()
    times: dict[str, list[float]] = {s: [] for s in (*STAGES, "total", "wall")}
    for seq in sequences:
        sort = Sort(SortConfig())
        cam_lanes.reset()
        stop.reset()
        for k, (_, _, image) in enumerate(seq):
            w0 = time.perf_counter()
            t0 = clock()
            pilot.steer(image, 0)
            t1 = clock()
            if k % every == 0:
                dets = [d for d in det(image) if d.name in MOVERS]
                t2 = clock()
                sort.update(np.array([d.box for d in dets], float).reshape(-1, 4), np.array([d.cls for d in dets], int))
            else:
                t2 = clock()
                sort.predict()
            t3 = clock()
            lanes = cam_lanes.detect(image)
            t4 = clock()
            stop.detect(image, lanes)
            t5 = clock()
            for stage, dt in zip(STAGES, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4), strict=True):
                times[stage].append(dt)
            times["total"].append(t5 - t0)
            times["wall"].append(time.perf_counter() - w0)
    return times


def agent_section(args: argparse.Namespace, report: dict) -> None:
    """The whole ``agent`` driver (agent.deploy.profiled_agent.ProfiledAgent) replayed on a recorded episode, per backend."""
    try:
        from towndrive.agent.deploy.camera_sources import EpisodeSource
        from towndrive.agent.deploy.profiled_agent import ProfiledAgent, budget_report, frame_env
    except ImportError as exc:
        print(f"\nthe agent driver: not available ({exc}); skipped")
        return
    if not args.episode.is_file():
        print(f"\nthe agent driver: no recorded episode {args.episode}; skipped")
        return
    print(f"\n### The agent driver on {args.episode} ({args.agent_frames} frames; stages in wall-clock ms p50 / p95, "
          "whole step also in CPU time)\n")
    stages = ("pilotnet", "detector", "tracking", "lanes", "stop_line", "distance", "control", "adas", "total")
    print("| profile | " + " | ".join(stages) + " | CPU ms per step (mean) | FPS (CPU time) |")
    print("|---" * (len(stages) + 3) + "|")
    report["agent"] = {}
    from dataclasses import replace

    with EpisodeSource(args.episode) as source:
        frames = [f for f, _ in zip(source, range(args.agent_frames), strict=False)]
        dt = source.dt
    runs = []
    for backend, precision, det_precision, every in (("torch", "fp32", "fp32", 1), ("onnxruntime", "fp32", "fp32", 1),
                                                     ("onnxruntime", "fp32", "int8", 1), ("onnxruntime", "fp32", "fp32", 3),
                                                     ("onnxruntime", "fp32", "int8", 3)):
        profile = variant(args.profile, backend, precision, args.pilotnet, args.export_dir, det_precision)
        profile = replace(profile, modules={**profile.modules, "detector": replace(profile.modules["detector"], every=every)})
        # serial stages (stage_threads=1): every stage on the calling thread, so that its CPU time counts all of
        # them; the agent's default may move the detector and lanes to a worker thread, which thread_time misses
        agent = ProfiledAgent(profile, stage_threads=1)
        agent.reset(frame_env(profile.camera_config(), dt, False))
        runs.append((f"{backend}, detector {det_precision} every {every}", profile, agent, []))
    for start in range(0, len(frames), 50):  # taking turns, 50 frames each (see interleaved)
        for _, _, agent, cpu in runs:
            for frame in frames[start:start + 50]:
                obs = {"image": frame.image, "speed": np.array([frame.speed_mps], np.float32), "command": frame.command}
                c0 = time.thread_time()
                agent.act(obs)
                cpu.append(time.thread_time() - c0)
    for name, profile, agent, cpu in runs:
        lat = budget_report(agent.timings, profile.budgets_ms)
        cpu_ms = 1000.0 * float(np.mean(cpu))
        cells = [f"{lat[s]['p50_ms']:.2f} / {lat[s]['p95_ms']:.2f}" if s in lat else "-" for s in stages]
        print(f"| {name} | " + " | ".join(cells) + f" | {cpu_ms:.2f} | {1000.0 / cpu_ms:.0f} |")
        report["agent"][name] = {"latency": lat, "cpu_ms_mean": cpu_ms}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--profile", default="cpu")
    ap.add_argument("--pilotnet", type=Path, default=None, help="PilotNet checkpoint instead of the profile's")
    ap.add_argument("--export-dir", default=None, help="where train.py export wrote the fp16 files (default: profile's)")
    ap.add_argument("--episodes", type=int, default=3)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--skips", default="1,2,3,5,10")
    ap.add_argument("--json", type=Path, default=Path("out/bench_deploy.json"))
    ap.add_argument("--episode", type=Path, default=Path("data/episodes/autopilot/episode_00000.h5"),
                    help="recorded episode the whole agent is replayed on")
    ap.add_argument("--agent-frames", type=int, default=400)
    ap.add_argument("--agent-only", action="store_true", help="only the agent driver's section")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    if args.agent_only:
        agent_section(args, {})
        return
    t0 = time.perf_counter()
    sequences = record(args.episodes, args.frames, args.seed)
    n = sum(len(s) for s in sequences)
    print(f"recorded {len(sequences)} drives, {n} frames at 320x160 in {time.perf_counter() - t0:.0f} s")
    report: dict[str, object] = {"frames": n, "profile": args.profile, "stages": {}, "skipping": []}

    print("\n### Per stage, detector every frame (ms of CPU time on one core, p50 / p95)\n")
    print("| backend | " + " | ".join(STAGES) + " | whole loop | FPS (CPU time) | FPS (wall clock) |")
    print("|---" * (len(STAGES) + 4) + "|")
    runnable = []
    for backend, precision in (("torch", "fp32"), ("onnxruntime", "fp32"), ("onnxruntime", "fp16"), ("onnxruntime", "int8")):
        profile = variant(args.profile, backend, precision, args.pilotnet, args.export_dir)
        try:
            open_pilotnet(profile), open_detector(profile)
        except FileNotFoundError as exc:
            print(f"| {backend} {precision} | skipped: {exc} |")
            continue
        runnable.append((backend, precision, profile))
    results = interleaved([(p, 1) for _, _, p in runnable], sequences)
    for (backend, precision, _), times in zip(runnable, results, strict=True):
        lat = {s: latency_of(v) for s, v in times.items()}
        fps = 1000.0 / lat["total"].mean_ms
        cells = [f"{lat[s].p50_ms:.2f} / {lat[s].p95_ms:.2f}" for s in (*STAGES, "total")]
        print(f"| {backend} {precision} | " + " | ".join(cells) + f" | {fps:.0f} | {1000.0 / lat['wall'].mean_ms:.0f} |")
        report["stages"][f"{backend} {precision}"] = {s: {"p50_ms": v.p50_ms, "p95_ms": v.p95_ms, "mean_ms": v.mean_ms}
                                                      for s, v in lat.items()}

    print("\n### Detector every k frames (ONNX Runtime fp32): loop speed and tracking quality\n")
    import motmetrics as mm

    profile = variant(args.profile, "onnxruntime", "fp32", args.pilotnet, args.export_dir)
    det = open_detector(profile)

    def boxes_of(image: np.ndarray) -> np.ndarray:
        return np.array([d.box for d in det(image) if d.name in MOVERS], float).reshape(-1, 4)

    cache = {(e, k): boxes_of(img) for e, s in enumerate(sequences) for k, (_, _, img) in enumerate(s)}
    mh = mm.metrics.create()
    print("| detector every | detector CPU ms per frame (mean) | loop CPU ms (mean / p95) | FPS (CPU time) | "
          "FPS (wall clock) | MOTA | IDF1 | ID switches |")
    print("|---|---|---|---|---|---|---|---|")
    skips = [int(k) for k in args.skips.split(",")]
    for every, times in zip(skips, interleaved([(profile, k) for k in skips], sequences), strict=True):
        total = latency_of(times["total"])
        acc, _, _ = evaluate(sequences, lambda e, k, item: cache[(e, k)], every, SortConfig(), "")
        m = mh.compute(acc, metrics=["mota", "idf1", "num_switches"], name="x")
        mota, idf1, sw = float(m["mota"].iloc[0]), float(m["idf1"].iloc[0]), int(m["num_switches"].iloc[0])
        det_ms = 1000.0 * float(np.mean(times["detector"]))
        wall_fps = 1.0 / float(np.mean(times["wall"]))
        print(f"| {every} | {det_ms:.2f} | {total.mean_ms:.2f} / {total.p95_ms:.2f} | {1000.0 / total.mean_ms:.0f} | "
              f"{wall_fps:.0f} | {mota:.3f} | {idf1:.3f} | {sw} |")
        report["skipping"].append({"every": every, "detector_ms_mean": det_ms, "loop_ms_mean": total.mean_ms,
                                   "loop_ms_p95": total.p95_ms, "fps": 1000.0 / total.mean_ms, "fps_wall": wall_fps,
                                   "mota": mota,
                                   "idf1": idf1, "id_switches": sw})
    agent_section(args, report)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2))
    print(f"\nfigures: {args.json}")


if __name__ == "__main__":
    main()
