"""PilotNet training throughput (samples/s): batches built in the training process or by DataLoader workers, and one
process or two under torchrun (DistributedDataParallel, gloo on the CPU).

Why: ``--loader-workers`` and torchrun (agent/training/loaders.py, devices.py) exist to keep a GPU fed and to use
several; on a CPU they compete with the training itself for the same cores. This measures what each setting gives
here: it records a few autopilot episodes (or takes ``--data``), trains PilotNet a few epochs with each setting and
reads the training samples per second of every epoch after the first from ``log.csv`` (the epoch's wall time on rank
0, validation excluded; under torchrun the samples of every rank). It prints the median of those epochs per setting
and the machine's load average (on a shared machine the figures say as much about the neighbours as about the code).

  python bench/bench_training.py                                  # 0 vs 2 loader workers, 1 vs 2 processes
  python bench/bench_training.py --only 3,4,5                     # some of the settings (numbered as listed)
  python bench/bench_training.py --data data/episodes/autopilot --samples 8192 --epochs 4
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# label -> (processes, loader workers per process, torch threads per process; 0: torch's default, one per core)
SETTINGS = {
    "1 process, default threads, 0 loader workers": (1, 0, 0),
    "1 process, default threads, 2 loader workers": (1, 2, 0),
    "1 process, 1 thread, 0 loader workers": (1, 0, 1),
    "1 process, 1 thread, 2 loader workers": (1, 2, 1),
    "2 processes (torchrun), 1 thread each, 0 loader workers": (2, 0, 1),
    "2 processes (torchrun), 1 thread each, 1 loader worker each": (2, 1, 1),
}


def record(folder: Path, episodes: int, seconds: float) -> None:
    cmd = [sys.executable, str(ROOT / "drive.py"), "--driver", "autopilot", "--record", str(folder), "--episodes",
           str(episodes), "--seconds", str(seconds), "--noise", "--seed", "1000", "--towns", "2", "--traffic", "0.5",
           "--workers", "2"]
    subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True)


def train(data: Path, out: Path, processes: int, workers: int, threads: int, args: argparse.Namespace) -> list[float]:
    """Train once; the samples per second of each epoch after the first."""
    flags = ["pilotnet", "--data", str(data), "--out", str(out), "--model", str(out / "m.pt"), "--epochs",
             str(args.epochs), "--samples-per-epoch", str(args.samples), "--batch", str(args.batch), "--seed", "0",
             "--device", "cpu", "--loader-workers", str(workers), "--threads", str(threads)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
           "MPLBACKEND": "Agg"}
    if processes > 1:
        env["OMP_NUM_THREADS"] = "1"
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(processes),
               str(ROOT / "train.py"), *flags]
    else:
        cmd = [sys.executable, str(ROOT / "train.py"), *flags]
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-2000:]}")
    with (out / "log.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    return [float(r["frames_per_s"]) for r in rows[1:]]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=None, help="episode folder (default: record a few into a temp folder)")
    ap.add_argument("--episodes", type=int, default=4, help="episodes to record when --data is not given")
    ap.add_argument("--seconds", type=float, default=20.0, help="length of each recorded episode")
    ap.add_argument("--epochs", type=int, default=3, help="epochs per setting; the first is not counted")
    ap.add_argument("--samples", type=int, default=4096, help="training samples per epoch (all processes together)")
    ap.add_argument("--batch", type=int, default=64, help="batch per process")
    ap.add_argument("--only", default="", help="comma-separated setting numbers to run (1-6; default: all)")
    args = ap.parse_args(argv)
    chosen = [label for k, label in enumerate(SETTINGS, 1) if not args.only or str(k) in args.only.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            data = Path(tmp) / "episodes"
            t0 = time.perf_counter()
            record(data, args.episodes, args.seconds)
            print(f"recorded {args.episodes} episodes of {args.seconds:g} s in {time.perf_counter() - t0:.0f} s",
                  file=sys.stderr)
        figures, loads = {}, {}
        for k, label in enumerate(chosen):
            processes, workers, threads = SETTINGS[label]
            load0 = os.getloadavg()[0]
            per_epoch = train(data, Path(tmp) / f"run{k}", processes, workers, threads, args)
            figures[label] = per_epoch
            loads[label] = [round(load0, 2), round(os.getloadavg()[0], 2)]
            print(f"{label}: {statistics.median(per_epoch):.0f} samples/s (epochs {', '.join(f'{v:.0f}' for v in per_epoch)})",
                  file=sys.stderr)
    base = statistics.median(figures[chosen[0]])
    result = {
        "samples_per_epoch": args.samples, "batch_per_process": args.batch, "epochs_counted": args.epochs - 1,
        "cpu_count": os.cpu_count(), "cores_available": len(os.sched_getaffinity(0)),
        "samples_per_s": {k: round(statistics.median(v)) for k, v in figures.items()},
        "relative_to_first": {k: round(statistics.median(v) / base, 2) for k, v in figures.items()},
        "load_average_1min_before_after": loads,
    }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
