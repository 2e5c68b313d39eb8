"""Export a torch model to ONNX and prove that ONNX Runtime computes the same thing.

Shared by every model the project ships (PilotNet, the detector): the export is only accepted when
ONNX Runtime's outputs equal torch's within a tolerance on the given example inputs.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch


def onnx_session(path: str | Path, threads: int = 0):  # -> onnxruntime.InferenceSession
    """A CPU ONNX Runtime session; ``threads`` 0 lets ONNX Runtime choose.

    With more than one thread the pool's workers do not spin-wait after a run: the detector and the
    pedestrian refiner run one after the other, each with its own pool, and on a 2-core machine the
    detector's spinning workers held the cores the refiner needed (the refiner took 20 ms instead of 4).
    """
    import onnxruntime as ort

    if not Path(path).is_file():
        raise FileNotFoundError(f"ONNX model {path} not found; export it with train.py first.")
    options = ort.SessionOptions()
    if threads:
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
    if threads != 1:
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])


def export_onnx(model: torch.nn.Module, example_inputs: Sequence[torch.Tensor], path: str | Path,
                input_names: Sequence[str], output_names: Sequence[str], tolerance: float = 1e-4,
                opset: int = 17) -> float:
    """Write ``model`` to ``path`` with a dynamic batch axis; return the largest |onnx - torch| difference.

    Raises ``ValueError`` if the difference exceeds ``tolerance`` (the file is then removed).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model = model.eval()
    dynamic = {name: {0: "batch"} for name in (*input_names, *output_names)}
    with torch.no_grad(), warnings.catch_warnings():
        # The TorchScript exporter is deprecated in favour of dynamo's, which needs onnxscript; it still works.
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(model, tuple(example_inputs), str(path), input_names=list(input_names),
                          output_names=list(output_names), dynamic_axes=dynamic, opset_version=opset,
                          dynamo=False)
        expected = model(*example_inputs)
    expected_list = [expected] if isinstance(expected, torch.Tensor) else list(expected)
    session = onnx_session(path)
    got = session.run(list(output_names), {n: t.numpy() for n, t in zip(input_names, example_inputs, strict=True)})
    diff = max(float(np.max(np.abs(g - e.numpy()))) for g, e in zip(got, expected_list, strict=True))
    if not diff <= tolerance:
        path.unlink(missing_ok=True)
        raise ValueError(f"ONNX export of {path.name} differs from torch by {diff:.2e} (> {tolerance:.0e}); not written.")
    return diff
