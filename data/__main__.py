"""Dataset tools: ``python -m data summary DIR [--png PATH] [--json]``, ``import-udacity SRC DST``,
``export-udacity SRC DST``, ``export-lerobot SRC DST``, ``import-lerobot SRC DST``, ``export-minari SRC NAME``.
Errors print one sentence to stderr and exit with status 2 (a missing optional extra included)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path


def main(argv: list[str] | None = None, prog: str = "towndrive data") -> int:
    parser = argparse.ArgumentParser(prog=prog, description="Inspect and convert recorded episodes.")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("summary", help="episodes, frames, hours, drivers, commands and steering of a dataset folder")
    p.add_argument("folder", type=Path, help="the folder of episodes")
    p.add_argument("--png", type=Path, help="also write the steering histogram to this PNG")
    p.add_argument("--json", action="store_true", help="print the summary as JSON instead of a table")
    p.add_argument("--quick", action="store_true", help="skip decoding the frames (a damaged frame then passes)")
    p.add_argument("--delete-partial", action="store_true",
                   help="delete the .partial leftovers of killed writers (only when nothing is writing into the folder)")
    p = sub.add_parser("import-udacity", help="convert a Udacity simulator recording (driving_log.csv + IMG/) to episodes")
    p.add_argument("src", type=Path, help="folder holding driving_log.csv and IMG/")
    p.add_argument("dst", type=Path, help="dataset folder to add episodes to")
    p.add_argument("--dt", type=float, default=0.05, help="seconds per step to record in the episodes (default 0.05)")
    p = sub.add_parser("export-udacity", help="write episodes as a Udacity recording (driving_log.csv + IMG/)")
    p.add_argument("src", type=Path, help="dataset folder or one episode_*.h5 file")
    p.add_argument("dst", type=Path, help="empty output folder")
    p = sub.add_parser("export-lerobot", help="write episodes as a LeRobotDataset v3 folder (parquet + MP4 video)")
    p.add_argument("src", type=Path, help="dataset folder or one episode_*.h5 file")
    p.add_argument("dst", type=Path, help="new or empty output folder")
    p.add_argument("--crf", type=int, default=18, help="H.264 quality: lower is larger and closer to the frames")
    p.add_argument("--gop", type=int, default=10, help="a keyframe at least every this many frames")
    p = sub.add_parser("import-lerobot", help="convert a LeRobotDataset v3 folder (camera, steering, throttle) to episodes")
    p.add_argument("src", type=Path, help="LeRobot dataset folder (holding meta/info.json)")
    p.add_argument("dst", type=Path, help="new or empty dataset folder")
    p.add_argument("--camera", help="the video feature to import (default observation.images.front, or the only one)")
    p = sub.add_parser("export-minari", help="write episodes as a Minari dataset (pip install 'towndrive[minari]')")
    p.add_argument("src", type=Path, help="dataset folder or one episode_*.h5 file")
    p.add_argument("name", help="Minari dataset id, e.g. towndrive/autopilot-v0 (stored under MINARI_DATASETS_PATH)")
    args = parser.parse_args(argv)
    from towndrive.data.stopping import Stopped, StopSignals, describe_os_error
    from towndrive.extras import MissingExtra

    signals = StopSignals()
    if args.command != "summary":  # writers stop between frames; summary writes nothing, so Ctrl-C stops it at once
        signals.__enter__()
    try:
        if args.command == "summary":
            from towndrive.data.summary import format_summary, summarize, write_histogram_png

            summary = summarize(args.folder, progress=True, check_frames=not args.quick)
            print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
            if args.delete_partial and summary["partial"]:
                for name in summary["partial"]:
                    (args.folder / name).unlink(missing_ok=True)
                print(f"deleted {len(summary['partial'])} .partial file(s) from {args.folder}", file=sys.stderr)
            if args.png:
                print(f"histogram written to {write_histogram_png(summary, args.png)}", file=sys.stderr)
        elif args.command == "import-udacity":
            from towndrive.data.udacity import import_udacity

            if args.dt <= 0:
                raise ValueError(f"--dt must be positive, got {args.dt}.")
            paths = import_udacity(args.src, args.dst, dt_s=args.dt, progress=True, stop=signals.check)
            print(f"imported {len(paths)} episode(s) into {args.dst}: {', '.join(p.name for p in paths)}")
        elif args.command == "export-udacity":
            from towndrive.data.udacity import export_udacity

            frames = export_udacity(args.src, args.dst, progress=True, stop=signals.check)
            print(f"exported {frames} frame(s) to {args.dst}")
        elif args.command == "export-lerobot":
            from towndrive.data.lerobot import LeRobotSettings, export_lerobot
            from towndrive.data.video import VideoSettings

            if args.crf < 0 or args.gop < 1:
                raise ValueError(f"--crf must be 0 or more and --gop 1 or more, got {args.crf} and {args.gop}.")
            done = export_lerobot(args.src, args.dst, LeRobotSettings(video=VideoSettings(crf=args.crf, gop_frames=args.gop)),
                                  progress=True, stop=signals.check)
            videos = ", ".join(f"{k} {v / 2**10:.0f} KiB" for k, v in done["video_bytes"].items())
            print(f"exported {done['episodes']} episode(s), {done['frames']} frame(s) at {done['fps']} fps to "
                  f"{args.dst} ({videos})")
        elif args.command == "import-lerobot":
            from towndrive.data.lerobot import import_lerobot

            paths = import_lerobot(args.src, args.dst, camera=args.camera, progress=True, stop=signals.check)
            print(f"imported {len(paths)} episode(s) into {args.dst}")
        elif args.command == "export-minari":
            from towndrive.data.minari_export import export_minari

            where = export_minari(args.src, args.name, progress=True, stop=signals.check)
            print(f"exported to Minari dataset {args.name} at {where}; load it with minari.load_dataset({args.name!r})")
    except BrokenPipeError:  # output piped into head & co.: stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except (ValueError, FileNotFoundError, PermissionError, IsADirectoryError, NotADirectoryError, MissingExtra) as exc:
        print(f"error: {exc}", file=sys.stderr)  # EpisodeError, UdacityError, LeRobotError are ValueErrors
        return 2
    except OSError as exc:  # a full disk, an I/O error: what this command wrote is removed again
        where = f" writing {exc.filename}" if exc.filename else ""
        print(f"error: {args.command} stopped because {describe_os_error(exc)}{where}; nothing of this "
              f"{args.command} was kept (all or nothing), so free some space and run it again.", file=sys.stderr)
        return 1
    except Stopped as exc:
        print(f"{args.command} stopped by {exc.name}; nothing of this {args.command} was kept (all or nothing).",
              file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("interrupted; nothing half-written was kept.", file=sys.stderr)
        return 130
    finally:
        signals.restore()
    return 0


if __name__ == "__main__":
    sys.exit(main())
