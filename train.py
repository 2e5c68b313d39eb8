"""Train the project's models and export them: ``python train.py pilotnet|detector|rl|export ... --help``.

Each subcommand lives in its own module under ``agent/`` and provides ``add_arguments(parser)``
and ``run(args) -> int``; this file only dispatches, so the modules stay importable and testable.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# subcommand -> module with add_arguments(parser) and run(args)
SUBCOMMANDS: dict[str, str] = {
    "pilotnet": "agent.training.pilotnet_training",
    "detector": "agent.training.detector_training",
    "rl": "agent.training.rl_training",
    "export": "agent.deploy.export_profile",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True, metavar="{" + ",".join(SUBCOMMANDS) + "}")
    for name, module_name in SUBCOMMANDS.items():
        module = importlib.import_module(module_name)
        summary = (module.__doc__ or name).strip().splitlines()[0]
        p = sub.add_parser(name, help=summary, description=module.__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(p)
        p.set_defaults(run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except KeyboardInterrupt:
        print("Interrupted; the last finished checkpoint is kept.", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
