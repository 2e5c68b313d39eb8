"""Write the car's networks to ONNX, each export proved against torch.

Why: a shipped ONNX file is only accepted when ONNX Runtime's outputs equal torch's within a tolerance on the
given example inputs, so what the car runs is what was trained. Training writes the files through here; the car
only reads them (``agent.perception.onnx_runtime``).
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from towndrive.agent.perception.detector import INPUT_HW, DecodedDetector, load_detector
from towndrive.agent.perception.onnx_runtime import onnx_session
from towndrive.agent.perception.ped_refiner import CROP_HW, load_refiner


def export_onnx(model: torch.nn.Module, example_inputs: Sequence[torch.Tensor], path: str | Path,
                input_names: Sequence[str], output_names: Sequence[str], tolerance: float = 1e-4,
                opset: int = 17, metadata: dict[str, str] | None = None) -> float:
    """Write ``model`` to ``path`` with a dynamic batch axis; return the largest |onnx - torch| difference.
    ``metadata``: key-value strings stored in the file's ``metadata_props`` (what a runtime needs besides the
    weights, so that it never has to open a second file).

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
    if metadata:
        import onnx

        proto = onnx.load(str(path))
        for key, value in metadata.items():
            entry = proto.metadata_props.add()
            entry.key, entry.value = key, value
        onnx.save(proto, str(path))
    expected_list = [expected] if isinstance(expected, torch.Tensor) else list(expected)
    session = onnx_session(path)
    got = session.run(list(output_names), {n: t.numpy() for n, t in zip(input_names, example_inputs, strict=True)})
    diff = max(float(np.max(np.abs(g - e.numpy()))) for g, e in zip(got, expected_list, strict=True))
    if not diff <= tolerance:
        path.unlink(missing_ok=True)
        raise ValueError(f"ONNX export of {path.name} differs from torch by {diff:.2e} (> {tolerance:.0e}); not written.")
    return diff


def export_detector(checkpoint: str | Path, out: str | Path, tolerance: float = 1e-4) -> float:
    """Write the decoded detector to ONNX; returns ONNX Runtime's largest difference from torch."""
    model = DecodedDetector(load_detector(checkpoint)).eval()
    gen = torch.Generator().manual_seed(0)
    example = torch.rand(2, 3, *INPUT_HW, generator=gen)
    return export_onnx(model, [example], out, ["image"], ["detections"], tolerance=tolerance)


def export_refiner(checkpoint: str | Path, out: str | Path, tolerance: float = 1e-4) -> float:
    """Write the refiner to ONNX (config in the metadata); returns ONNX Runtime's largest difference from torch."""
    import onnx

    model = load_refiner(checkpoint)
    gen = torch.Generator().manual_seed(0)
    example = torch.rand(3, 4, *CROP_HW, generator=gen) - 0.5
    diff = export_onnx(model, [example], out, ["crops"], ["refined"], tolerance=tolerance)
    proto = onnx.load(str(out))
    entry = proto.metadata_props.add()
    entry.key, entry.value = "refiner_config", json.dumps(asdict(model.config))
    onnx.save(proto, str(out))
    return diff


def export_sign_reader(checkpoint: str | Path, out: str | Path, tolerance: float = 1e-4) -> float:
    """Write the sign reader to ONNX (config in the metadata); returns ONNX Runtime's largest difference from torch."""
    from towndrive.agent.perception.sign_reader import CROP, load_sign_reader

    model = load_sign_reader(checkpoint)
    gen = torch.Generator().manual_seed(0)
    example = torch.rand(3, 3, CROP, CROP, generator=gen) - 0.5
    return export_onnx(model, [example], out, ["crops"], ["signs"], tolerance=tolerance,
                       metadata={"sign_reader_config": json.dumps(asdict(model.config))})
