"""Where training writes: the run folder by default; the shipped models only when the user asks.

Why: the demo and the evaluation drive with the shipped models. A user who tries a training command (one epoch
to see it work) must not silently replace them; ``--replace-shipped`` does, and says which files it overwrote.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from towndrive.agent.shipped import MODELS_DIR


def add_replace_shipped(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--replace-shipped", action="store_true",
                   help=f"also copy the result over the shipped {what} in {MODELS_DIR} (the demo and evaluation use it)")


def replace_shipped(files: list[Path], names: list[str] | None = None) -> list[Path]:
    """Copy each of ``files`` over the shipped model of the same name (or ``names``); returns what was replaced."""
    replaced = []
    for k, src in enumerate(files):
        dst = MODELS_DIR / (names[k] if names else Path(src).name)
        if Path(src).resolve() == dst.resolve():
            continue
        shutil.copy2(src, dst)
        replaced.append(dst)
        print(f"Replaced the shipped {dst} with {src}.")
    return replaced
