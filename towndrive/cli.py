"""The ``towndrive`` command: one entry point with a subcommand per job, each with the flags of its script.

Why a thin dispatcher: ``--help`` and argument errors must answer at once, so nothing heavy (torch, pybullet,
highway-env) is imported before a subcommand that needs it runs.
"""

from __future__ import annotations

import argparse
import sys


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Descriptions as written, and every option's default shown after its help."""


COMMANDS = {
    "drive": "drive a route and watch it (video, frames, summary): the demo by default",
    "record": "record episodes into a folder (human, autopilot or any driver)",
    "evaluate": "closed-loop evaluation with CARLA-style metrics",
    "scenario": "run a scenario of the suite by name, or 'all'",
    "train": "train a model: pilotnet, detector or rl",
    "export": "export a deployment profile's models (ONNX, TensorRT scripts)",
    "data": "inspect and convert recorded episodes (summary; Udacity, LeRobot and Minari)",
}


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = ["usage: towndrive COMMAND [options]   (towndrive COMMAND --help for its options)", "", "commands:"]
    lines += [f"  {name:<{width}}  {what}" for name, what in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(usage())
        return 0
    if args[0] in ("-V", "--version"):
        from towndrive import __version__

        print(f"towndrive {__version__}")
        return 0
    command, rest = args[0], args[1:]
    if command not in COMMANDS:
        print(f"towndrive: unknown command {command!r}; choose one of {', '.join(COMMANDS)}.", file=sys.stderr)
        return 2
    prog = f"towndrive {command}"
    if command in ("drive", "record", "evaluate", "scenario"):
        from towndrive.drive_cli import main as drive

        mode = {"drive": [], "evaluate": ["--evaluate"]}.get(command)
        if mode is None:  # record DIR / scenario NAME: the first argument is the mode's value
            if not rest or rest[0] in ("-h", "--help"):
                return drive(["--help"], prog=prog)
            mode, rest = [f"--{command}", rest[0]], rest[1:]
        return drive([*mode, *rest], prog=prog)
    if command in ("train", "export"):
        from towndrive.train_cli import main as train

        return train(rest if command == "train" else ["export", *rest], prog="towndrive" if command == "export" else prog)
    from towndrive.data.__main__ import main as data

    return data(rest, prog=prog)


def run() -> int:
    """The console command: ``main`` with a closed pipe (``towndrive --help | head``) ending quietly."""
    try:
        return main()
    except BrokenPipeError:
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # nothing more can be written there
        return 0


if __name__ == "__main__":
    raise SystemExit(run())
