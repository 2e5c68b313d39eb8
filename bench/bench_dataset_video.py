"""Camera frames as MP4 (the LeRobot export) against gzip HDF5 (the episode files): size and decode cost per frame.

Why: the export's point is smaller files that other tools read; this says how much smaller, what a frame costs to
decode each way, and how far the video's frames are from the originals. It records one autopilot episode (default
300 frames at 320x160), then encodes its frames at a few H.264 settings.

    python bench/bench_dataset_video.py                  # --frames 300 --width 320 --height 160
"""

from __future__ import annotations

import argparse
import random
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from towndrive.data.episodes import list_episodes, read_episode  # noqa: E402
from towndrive.data.video import Mp4Writer, VideoSettings, read_frames  # noqa: E402


def _ms_per_frame(fn, frames: int, repeats: int = 3) -> float:  # type: ignore[no-untyped-def]
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, (time.perf_counter() - start) / frames * 1000)
    return best


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=160)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    import drive

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "ep"
        seconds = args.frames * 0.05
        assert drive.main(["--driver", "autopilot", "--record", str(folder), "--episodes", "1", "--seed", str(args.seed),
                           "--seconds", f"{seconds}", "--traffic", "0.5", "--width", str(args.width),
                           "--height", str(args.height)]) == 0
        path = list_episodes(folder)[0]
        frames = read_episode(path).frames
        n = len(frames)
        with h5py.File(path, "r") as f:
            h5_bytes = f["frames"].id.get_storage_size()

        def h5_sequential() -> None:
            with h5py.File(path, "r") as f:
                ds = f["frames"]
                for t in range(n):
                    ds[t]

        order = list(range(n))
        random.Random(0).shuffle(order)
        picks = order[:30]

        def h5_random() -> None:
            with h5py.File(path, "r") as f:
                for t in picks:
                    f["frames"][t]

        print(f"{n} frames at {args.width}x{args.height} (autopilot, seed {args.seed})\n")
        print("| storage | bytes | KiB | x smaller than gzip HDF5 | decode all, ms/frame | one random frame, ms "
              "| mean abs error | PSNR dB |")
        print("|---|---|---|---|---|---|---|---|")
        print(f"| gzip HDF5 (episode `frames`) | {h5_bytes} | {h5_bytes / 1024:.0f} | 1.0 | "
              f"{_ms_per_frame(h5_sequential, n):.2f} | {_ms_per_frame(h5_random, len(picks)):.2f} | 0 | inf |")
        for settings in (VideoSettings(), VideoSettings(gop_frames=2), VideoSettings(crf=23), VideoSettings(crf=30)):
            mp4 = Path(tmp) / f"crf{settings.crf}_g{settings.gop_frames}.mp4"
            writer = Mp4Writer(mp4, 20, args.width, args.height, settings)
            for frame in frames:
                writer.add(frame)
            writer.close()
            size = mp4.stat().st_size
            decoded = read_frames(mp4)
            error = decoded.astype(np.float64) - frames
            psnr = 10 * np.log10(255**2 / np.mean(error**2))
            random_ms = _ms_per_frame(lambda mp4=mp4: [read_frames(mp4, t, 1) for t in picks], len(picks))
            print(f"| MP4 H.264 crf {settings.crf}, keyframe every {settings.gop_frames} | {size} | {size / 1024:.0f} | "
                  f"{h5_bytes / size:.1f} | {_ms_per_frame(lambda mp4=mp4: read_frames(mp4), n):.2f} | {random_ms:.2f} | "
                  f"{np.abs(error).mean():.2f} | {psnr:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
