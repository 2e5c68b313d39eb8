"""Train the project's models and export them: ``towndrive train pilotnet|detector|rl`` and ``towndrive export``.

Each subcommand lives in its own module under ``towndrive.agent`` and provides ``add_arguments(parser)`` and
``run(args) -> int``; this module only dispatches, importing only the module of the subcommand asked for.
"""

from __future__ import annotations

import argparse
import sys

from towndrive.cli import HelpFormatter
from towndrive.extras import import_for

# subcommand -> (module with add_arguments(parser) and run(args), what it does)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "pilotnet": ("towndrive.agent.training.pilotnet_training", "behavioural cloning of PilotNet on recorded episodes"),
    "detector": ("towndrive.agent.training.detector_training", "the detector and pedestrian refiner: data, training, export"),
    "rl": ("towndrive.agent.training.rl_training", "the PPO baseline on ground-truth features"),
    "export": ("towndrive.agent.deploy.export_profile", "a deployment profile's models: ONNX, int8, TensorRT scripts"),
}
# where a subcommand's flags live when its module is heavy to import (torch): parsed first, run module imported after
ARGUMENTS = {"pilotnet": "towndrive.agent.training.pilotnet_args"}


def build_parser(command: str | None = None, prog: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s module is imported (the others' heavy imports wait until they are asked for)."""
    parser = argparse.ArgumentParser(prog=prog, description=__doc__, formatter_class=HelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True, metavar="{" + ",".join(SUBCOMMANDS) + "}")
    for name, (module_name, summary) in SUBCOMMANDS.items():
        if name != command:
            sub.add_parser(name, help=summary)
            continue
        what = f"towndrive train {name}" if name != "export" else "towndrive export"
        light = import_for(ARGUMENTS.get(name, module_name), what)
        p = sub.add_parser(name, help=summary, description=light.__doc__ if name not in ARGUMENTS else summary,
                           formatter_class=HelpFormatter)
        light.add_arguments(p)
        p.set_defaults(run=lambda args, module_name=module_name, what=what: import_for(module_name, what).run(args))
    return parser


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = argv[0] if argv and argv[0] in SUBCOMMANDS else None
    args = build_parser(command, prog).parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except KeyboardInterrupt:
        print("Interrupted; the last finished checkpoint is kept.", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
