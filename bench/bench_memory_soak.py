"""Memory soak: resident memory after resets into 3 and into 30 different towns with the camera on.

Why: a long evaluation over many towns, and every parallel worker of a scale-out, pays for whatever a town
leaves behind when the next one replaces it. The renderer should free what a town built, so the figure
after 30 towns should be within 10 % of the figure after 3.

Run: ``python bench/bench_memory_soak.py [--towns 30] [--first 3] [--steps 5] [--camera-off]``.
Prints one line per town and the two figures; exits 1 when the growth is over 10 %.
"""

from __future__ import annotations

import argparse
import gc
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from towndrive.envs.drive_env import DriveConfig, DriveEnv  # noqa: E402


def rss_mb() -> float:
    """Resident set size of this process in MB (Linux /proc; ``resource`` gives only the peak)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--towns", type=int, default=30, help="how many different towns to reset into")
    ap.add_argument("--first", type=int, default=3, help="the early figure is taken after this many towns")
    ap.add_argument("--steps", type=int, default=5, help="steps driven in each town")
    ap.add_argument("--town-seed", type=int, default=1000, help="the first town (then +1 each)")
    ap.add_argument("--camera-off", action="store_true", help="DriveConfig(render_camera=False), for comparison")
    args = ap.parse_args(argv)
    if not 1 <= args.first < args.towns:
        ap.error(f"--first must be in [1, --towns); got {args.first} with --towns {args.towns}.")
    env = DriveEnv(DriveConfig(render_camera=not args.camera_off))
    figures: dict[int, float] = {}
    try:
        for k in range(args.towns):
            env.reset(seed=k, options={"town_seed": args.town_seed + k})
            for _ in range(args.steps):
                env.step(np.array([0.0, 0.3], np.float32))
            gc.collect()
            figures[k + 1] = rss_mb()
            print(f"town {k + 1:>3} (seed {args.town_seed + k}): RSS {figures[k + 1]:.0f} MB", flush=True)
    finally:
        env.close()
    early, late = figures[args.first], figures[args.towns]
    growth = late / early - 1.0
    print(f"RSS after {args.first} towns {early:.0f} MB, after {args.towns} towns {late:.0f} MB "
          f"({growth:+.1%}; target within 10 %)")
    return 0 if growth <= 0.10 else 1


if __name__ == "__main__":
    sys.exit(main())
