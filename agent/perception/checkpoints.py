"""Reading and writing torch checkpoints as weights plus plain data, so that opening a model file runs no code.

Why: ``torch.load`` without ``weights_only=True`` unpickles arbitrary objects, and a crafted ``.pt`` (a download,
a file left next to an ONNX model) runs whatever code its pickle names. Every checkpoint this project reads goes
through ``load_checkpoint``, which lets torch rebuild only tensors and plain containers; every checkpoint it writes
goes through ``plain`` first, so what is written can always be read back that way.
"""

from __future__ import annotations

import pickle
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch


def plain(value: Any) -> Any:
    """``value`` as plain data torch's weights-only loader accepts: dicts with str or int keys, lists, str, int, float,
    bool, None and tensors. Paths become str, tuples lists, NumPy scalars and arrays Python numbers and lists;
    anything else is refused (``TypeError`` naming its type), never pickled."""
    if value is None or isinstance(value, bool | int | float | str | torch.Tensor):
        return value
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Mapping):
        return {k if isinstance(k, int | str) else str(k): plain(v) for k, v in value.items()}  # int: optimiser state
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    raise TypeError(f"cannot store a {type(value).__name__} in a checkpoint; store plain data (str, numbers, lists).")


def save_checkpoint(path: str | Path, content: Mapping[str, Any]) -> Path:
    """Write ``content`` (a ``state_dict`` and metadata) atomically: ``<path>.partial``, then a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    try:
        torch.save(plain(content), tmp)
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(path: str | Path, what: str = "model") -> dict[str, Any]:
    """The dict a checkpoint holds, loaded with ``weights_only=True``; ``what`` ("PilotNet", "detector", ...) names
    the role in the one-sentence errors, which also name the file: missing, not a torch file, holding code or
    other objects than weights and plain data, or without a ``state_dict``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} checkpoint {path} not found; check the path.")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        blocked = _blocked_global(str(exc))
        if blocked:
            raise ValueError(f"{path} is not a {what} checkpoint this project loads: it asks to run or build "
                             f"{blocked}, and checkpoints may hold only weights and plain data.") from None
        raise ValueError(f"{path} is not a {what} checkpoint (not a torch file, or corrupt); check the path.") from None
    except (RuntimeError, EOFError, OSError, ValueError, TypeError, AttributeError, KeyError, IndexError):
        raise ValueError(f"{path} is not a {what} checkpoint (truncated, corrupt or not a torch file); "
                         "check the path or train it again.") from None
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt:
        raise ValueError(f"{path} is not a {what} checkpoint (no state_dict); train one with train.py.")
    return ckpt


def _blocked_global(message: str) -> str:
    """The Python object a refused pickle named (torch says "unsupported GLOBAL posix.system ..."), or ""."""
    words = message.split()
    for i, word in enumerate(words[:-1]):
        if word.lower() == "global":
            return words[i + 1].rstrip(".,:")
    return ""


def numpy_forward(model: torch.nn.Module):  # -> Callable[[np.ndarray], np.ndarray]
    """A loaded model as a NumPy function (no gradients): what the ONNX session of its export is, for torch."""
    def run(x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return model(torch.from_numpy(x)).numpy()

    return run
