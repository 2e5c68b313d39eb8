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

# What each role's ONNX file must take and give: input name -> (element type, rank, fixed trailing dims or None),
# and the output names. A file for another role (a detector given as PilotNet) fails when it is opened, not at
# the first frame.
ROLES: dict[str, tuple[dict[str, tuple[str, int, tuple[int, ...] | None]], tuple[str, ...], frozenset[str]]] = {
    # role: (required inputs, required outputs, optional inputs)
    "PilotNet": ({"image": ("tensor(float)", 4, (3, 66, 200))}, ("steer",), frozenset({"command"})),
    "detector": ({"image": ("tensor(float)", 4, None)}, ("detections",), frozenset()),
    "pedestrian refiner": ({"crops": ("tensor(float)", 4, None)}, ("refined",), frozenset()),
}


def onnx_session(path: str | Path, threads: int = 0, role: str | None = None):  # -> onnxruntime.InferenceSession
    """A CPU ONNX Runtime session; ``threads`` 0 lets ONNX Runtime choose. With ``role`` (a key of ``ROLES``)
    the file's inputs and outputs are checked for that role. Every failure is one ``ValueError`` sentence naming
    the file (not parseable, or the wrong inputs or outputs), never ONNX Runtime's own traceback.

    With more than one thread the pool's workers do not spin-wait after a run: the detector and the
    pedestrian refiner run one after the other, each with its own pool, and on a 2-core machine the
    detector's spinning workers held the cores the refiner needed (the refiner took 20 ms instead of 4).
    """
    import onnxruntime as ort

    what = f"{role} model" if role else "ONNX model"
    if not Path(path).is_file():
        raise FileNotFoundError(f"{what} {path} not found; export it with train.py first.")
    options = ort.SessionOptions()
    if threads:
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
    if threads != 1:
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    try:
        session = ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime's exceptions (InvalidProtobuf, Fail, ...) share no base but Exception
        reason = " ".join(str(exc).split())
        reason = reason.split(" : ")[-1] if " : " in reason else reason
        raise ValueError(f"{path} is not a readable ONNX model ({reason[:160]}); re-export it with train.py.") from None
    if role is not None:
        check_role(session, path, role)
    return session


def check_role(session, path: str | Path, role: str) -> None:
    """Raise one ``ValueError`` sentence when ``session``'s inputs or outputs are not those of ``role``."""
    inputs, outputs, optional = ROLES[role]
    have = {i.name: i for i in session.get_inputs()}
    out_names = [o.name for o in session.get_outputs()]

    def describe() -> str:
        return (f"inputs {', '.join(f'{n} {have[n].shape}' for n in have) or 'none'}, outputs {', '.join(out_names)}; "
                f"a {role} takes {', '.join(inputs)} and gives {', '.join(outputs)}")

    problems = [n for n in inputs if n not in have] + [n for n in have if n not in inputs and n not in optional]
    problems += [n for n in outputs if n not in out_names]
    for name, (dtype, rank, tail) in inputs.items():
        if name not in have:
            continue
        shape = have[name].shape
        if have[name].type != dtype or len(shape) != rank or (
                tail is not None and [d if isinstance(d, int) else None for d in shape[-len(tail):]] != list(tail)):
            problems.append(name)
    if problems:
        raise ValueError(f"{path} is not a {role} model (it has {describe()}).")


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
