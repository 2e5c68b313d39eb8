"""Drive, record, evaluate or run scenarios from a clone: the same as ``towndrive drive`` (see ``--help``)."""

from towndrive.drive_cli import main

if __name__ == "__main__":
    raise SystemExit(main())
