"""Train or export models from a clone: the same as ``towndrive train`` and ``towndrive export`` (see ``--help``)."""

from towndrive.train_cli import main

if __name__ == "__main__":
    raise SystemExit(main())
