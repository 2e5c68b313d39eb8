"""Evaluation on 1 and on N worker processes, in the same run: wall times, speed-up, and whether the reports match.

Why: ``--workers`` (envs/parallel.py) is only worth its processes if it is faster and gives the serial run's
report. This runs the same routes (``--episodes`` seeds from 500, towns 100-104, every weather, traffic) once
serially and once on ``--workers`` processes, compares metrics.json and table.md byte for byte, and prints the
wall times with the machine's load average (on a shared machine the speed-up says as much about the neighbours
as about the code).

  python bench/bench_scale.py                                   # the agent, 8 routes of 30 s, 1 and 2 workers
  python bench/bench_scale.py --driver autopilot --camera --seconds 60
  python bench/bench_scale.py --ray                             # also through a local Ray cluster (towndrive[cluster])
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from towndrive.agent.drivers import make_driver  # noqa: E402
from towndrive.envs.drive_env import DriveConfig  # noqa: E402
from towndrive.envs.evaluation import evaluate  # noqa: E402
from towndrive.envs.parallel import DriverSpec, available_cores, parse_workers  # noqa: E402
from towndrive.sim.render import LIGHTING_PRESETS  # noqa: E402


def episode_options(weathers: list[str], k: int) -> dict:
    return {"town_seed": 100 + k % 5, "weather": weathers[k % len(weathers)]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--driver", default="agent", help="driver name (agent, pilotnet, autopilot, rl)")
    ap.add_argument("--episodes", type=int, default=8, help="routes")
    ap.add_argument("--seconds", type=float, default=30.0, help="time limit per route, simulated seconds")
    ap.add_argument("--workers", default="2", help="the parallel run's workers ('auto': the available cores)")
    ap.add_argument("--camera", action="store_true",
                    help="render the camera for a privileged driver too (it does not need it; a camera-only driver "
                         "always has it)")
    ap.add_argument("--ray", action="store_true",
                    help="also run the routes as Ray tasks on a local cluster of --workers CPUs (towndrive[cluster])")
    ap.add_argument("--out", type=Path, default=None, help="keep both reports here (default: a temporary folder)")
    args = ap.parse_args(argv)
    workers = parse_workers(args.workers)
    spec = DriverSpec.of(make_driver, args.driver)
    privileged = spec.build().privileged
    config = DriveConfig(max_time_s=args.seconds)
    if privileged and not args.camera:
        config = replace(config, render_camera=False)
    options = functools.partial(episode_options, sorted(LIGHTING_PRESETS))
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        runs = {"1 worker": (1, None), f"{workers} workers": (workers, None)}
        if args.ray:
            runs[f"Ray, {workers} CPUs"] = (workers, "local")
        walls, loads, same = {}, {}, {}
        for label, (n, ray) in runs.items():
            folder = out / label.replace(" ", "_").replace(",", "")
            load0 = os.getloadavg()[0]
            t0 = time.perf_counter()
            evaluate(spec, config, args.episodes, 500, folder, video=False, options=options, plots=False, workers=n,
                     ray=ray)
            walls[label] = time.perf_counter() - t0
            loads[label] = [round(load0, 2), round(os.getloadavg()[0], 2)]
            serial = out / "1_worker"
            same[label] = all((serial / f).read_bytes() == (folder / f).read_bytes() for f in ("metrics.json", "table.md"))
        mean = json.loads((out / "1_worker" / "metrics.json").read_text())["mean"]
    serial_s = walls["1 worker"]
    result = {
        "driver": args.driver, "episodes": args.episodes, "seconds_per_episode": args.seconds,
        "camera": config.render_camera, "cores_available": available_cores(), "cpu_count": os.cpu_count(),
        "wall_s": {k: round(w, 1) for k, w in walls.items()},
        "speed_up": {k: round(serial_s / w, 2) for k, w in walls.items()},
        "episodes_per_hour": {k: round(3600 * args.episodes / w, 1) for k, w in walls.items()},
        "load_average_1min_before_after": loads,
        "reports_identical_to_serial": same, "driving_score": mean["driving_score"],
    }
    print(json.dumps(result, indent=2))
    print(f"{args.driver}, {args.episodes} routes of {args.seconds:g} s: "
          + "; ".join(f"{k} {w:.1f} s (x{serial_s / w:.2f}, report {'identical' if same[k] else 'DIFFERENT'})"
                      for k, w in walls.items())
          + f"; load average (1 min) {loads['1 worker'][0]:.1f} at the start, on {available_cores()} cores.")
    return 0 if all(same.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
