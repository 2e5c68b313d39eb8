"""Dataset tools: ``python -m data summary DIR [--png PATH] [--json]``, ``python -m data import-udacity SRC DST``,
``python -m data export-udacity SRC DST``. Errors print one sentence to stderr and exit with status 2."""

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
    args = parser.parse_args(argv)
    from towndrive.data.stopping import Stopped, StopSignals, describe_os_error

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
    except BrokenPipeError:  # output piped into head & co.: stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except (ValueError, FileNotFoundError, PermissionError, IsADirectoryError, NotADirectoryError) as exc:
        print(f"error: {exc}", file=sys.stderr)  # EpisodeError and UdacityError are ValueErrors
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
