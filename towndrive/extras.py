"""Which optional extra brings which library: a missing one is one sentence naming what to install.

The environment alone needs none of torch, ONNX or stable-baselines3; the drivers and tools that do say so.
"""

from __future__ import annotations

import importlib
from types import ModuleType

EXTRA_OF = {  # top-level module -> the extra that installs it
    "torch": "agent",
    "onnxruntime": "agent",
    "onnx": "train",
    "stable_baselines3": "rl",
    "serial": "deploy",
    "motmetrics": "eval",
    "ray": "cluster",
    "pyarrow": "dataset",
    "pandas": "dataset",
    "av": "dataset",
    "minari": "minari",
}


class MissingExtra(ImportError):
    """An optional library is not installed (the message names the extra)."""


def explain(exc: ImportError, what: str) -> ImportError:
    """``exc`` as one sentence naming the extra, when it is about a library an extra installs; else ``exc``."""
    name = (getattr(exc, "name", None) or "").split(".")[0]
    extra = EXTRA_OF.get(name)
    if extra is None:
        return exc
    return MissingExtra(f"{what} needs {name}, which is not installed: pip install 'towndrive[{extra}]'.")


def import_for(module: str, what: str) -> ModuleType:
    """Import ``module`` for ``what``; a missing optional library becomes ``MissingExtra``."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise explain(exc, what) from None
