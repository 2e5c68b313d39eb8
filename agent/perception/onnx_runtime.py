"""Open an ONNX model for inference on ONNX Runtime, checked for the role it plays in the car.

Why here: every network the car runs (PilotNet, the detector, the pedestrian refiner, the sign reader) is opened through one
function, so a wrong, damaged or mismatched file is one sentence naming the file when it is opened, never an
ONNX Runtime traceback at the first frame. Writing ONNX files is ``agent.deploy.onnx_export``.
"""

from __future__ import annotations

from pathlib import Path

# What each role's ONNX file must take and give: input name -> (element type, rank, fixed trailing dims or None),
# and the output names. A file for another role (a detector given as PilotNet) fails when it is opened, not at
# the first frame.
ROLES: dict[str, tuple[dict[str, tuple[str, int, tuple[int, ...] | None]], tuple[str, ...], frozenset[str]]] = {
    # role: (required inputs, required outputs, optional inputs)
    "PilotNet": ({"image": ("tensor(float)", 4, (3, 66, 200))}, ("steer",), frozenset({"command"})),
    "detector": ({"image": ("tensor(float)", 4, None)}, ("detections",), frozenset()),
    "pedestrian refiner": ({"crops": ("tensor(float)", 4, None)}, ("refined",), frozenset()),
    "sign reader": ({"crops": ("tensor(float)", 4, (3, 32, 32))}, ("signs",), frozenset()),
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
        raise FileNotFoundError(f"{what} {path} not found; export one with towndrive train or towndrive export.")
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
        raise ValueError(f"{path} is not a readable ONNX model ({reason[:160]}); re-export it with towndrive export.") from None
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


def second_stage_session(path: str | Path, threads: int, role: str, config_key: str):
    """A second stage's exported model (the pedestrian refiner, the sign reader): its run function, x -> the first
    output, and the config it was exported with (the JSON under ``config_key`` in the file's metadata)."""
    import json

    session = onnx_session(path, threads, role=role)
    meta = session.get_modelmeta().custom_metadata_map
    if config_key not in meta:
        raise ValueError(f"{path} is not an exported {role} (no {config_key} metadata); "
                         "export it with `python train.py detector export`.")
    name = session.get_inputs()[0].name
    return (lambda x: session.run(None, {name: x})[0]), json.loads(meta[config_key])
