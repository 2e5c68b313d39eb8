"""One small inference interface, ``Backend.run(feeds) -> outputs``, over torch, ONNX Runtime and TensorRT.

Why one interface: the agent should not know where a network runs. A profile (``agent.deploy.profiles``) names
the backend and precision per model; ``open_pilotnet(profile)`` and ``open_detector(profile)`` return the
objects the drivers already use (``steer(rgb, command)``; ``detector(rgb) -> detections``) on top of
whichever backend the profile asks for. Pre- and post-processing are the models' own functions
(``agent.perception.pilotnet.preprocess``, ``agent.perception.detector.to_input`` / ``postprocess``), so every backend sees the
same tensors.

TensorRT is imported only when a profile asks for it. Where it is missing (any machine but a Jetson or an
NVIDIA GPU host with TensorRT), opening it raises ``BackendUnavailable`` with one sentence saying what to
do. The TensorRT code follows the TensorRT 8.5+/10 tensor-name API and cuda-python for device memory; it
has not been run on this CPU-only machine.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    from towndrive.agent.deploy.profiles import Profile
    from towndrive.agent.perception.detector import Detection
    from towndrive.agent.perception.ped_refiner import Refine
    from towndrive.agent.perception.sign_reader import Read

DETECTOR_INPUTS = ("image",)
DETECTOR_OUTPUTS = ("detections",)
PILOTNET_OUTPUTS = ("steer",)


class BackendUnavailable(RuntimeError):
    """The backend a profile asks for cannot run on this machine; the message says what to do."""


class Backend(Protocol):
    """Named float32/int64 numpy inputs in, numpy outputs out (in the model's output order)."""

    name: str
    precision: str

    def run(self, feeds: dict[str, np.ndarray]) -> list[np.ndarray]: ...


class TorchBackend:
    """A torch module on the CPU, the reference every other backend is compared with."""

    name = "torch"
    precision = "fp32"

    def __init__(self, module: Any, input_names: Sequence[str], threads: int = 1) -> None:
        import torch

        if threads:
            torch.set_num_threads(threads)
        self.module = module.eval()
        self.input_names = list(input_names)

    def run(self, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        import torch

        with torch.no_grad():
            out = self.module(*(torch.from_numpy(np.ascontiguousarray(feeds[n])) for n in self.input_names))
        return [t.numpy() for t in ([out] if isinstance(out, torch.Tensor) else out)]


class OnnxRuntimeBackend:
    """An ONNX file through ONNX Runtime's CPU provider (fp32, or fp16 weights with fp32 inputs and outputs)."""

    name = "onnxruntime"

    def __init__(self, path: str | Path, precision: str = "fp32", threads: int = 1, role: str | None = None) -> None:
        from towndrive.agent.perception.onnx_runtime import onnx_session

        self.session = onnx_session(path, threads, role)
        self.precision = precision
        self.input_names = [i.name for i in self.session.get_inputs()]

    def run(self, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        return list(self.session.run(None, feeds))


def import_tensorrt() -> Any:
    """``tensorrt``, or ``BackendUnavailable`` saying where it comes from."""
    try:
        import tensorrt  # type: ignore[import-not-found]
    except ImportError as exc:
        raise BackendUnavailable(
            "TensorRT is not installed on this machine: the tensorrt backend runs on a Jetson (JetPack ships "
            "TensorRT) or an NVIDIA GPU host; here use a profile with backend onnxruntime (e.g. --profile cpu).") from exc
    return tensorrt


def import_cudart() -> Any:
    """cuda-python's runtime API (``cuda.bindings.runtime`` from 12.6 on, ``cuda.cudart`` before), or a clear error."""
    try:
        from cuda.bindings import runtime  # type: ignore[import-not-found]

        return runtime
    except ImportError:
        pass
    try:
        from cuda import cudart  # type: ignore[import-not-found]
    except ImportError as exc:
        raise BackendUnavailable("The tensorrt backend needs cuda-python for device memory: pip install cuda-python "
                                 "(the version of JetPack's CUDA).") from exc
    return cudart


class TensorRTBackend:
    """A serialized TensorRT engine (built on the device by the script ``train.py export`` writes)."""

    name = "tensorrt"

    def __init__(self, engine_path: str | Path, precision: str) -> None:
        trt = import_tensorrt()
        cudart = import_cudart()
        path = Path(engine_path)
        if not path.is_file():
            raise FileNotFoundError(f"TensorRT engine {path} not found; build it on this device with the "
                                    f"build_engines.sh that `python train.py export --profile NAME` wrote beside it.")
        self.precision = precision
        self.cudart = cudart
        self.logger = trt.Logger(trt.Logger.WARNING)
        self.engine = trt.Runtime(self.logger).deserialize_cuda_engine(path.read_bytes())
        if self.engine is None:
            raise ValueError(f"{path} could not be deserialized: it was built by another TensorRT version or GPU; rebuild it.")
        self.context = self.engine.create_execution_context()
        _, self.stream = cudart.cudaStreamCreate()
        self.names = [self.engine.get_tensor_name(i) for i in range(self.engine.num_io_tensors)]
        self.inputs = [n for n in self.names if self.engine.get_tensor_mode(n) == trt.TensorIOMode.INPUT]
        self.outputs = [n for n in self.names if n not in self.inputs]
        self.dtypes = {n: np.dtype(trt.nptype(self.engine.get_tensor_dtype(n))) for n in self.names}
        self._buffers: dict[str, tuple[int, int]] = {}  # name -> (device pointer, bytes)

    def _device(self, name: str, nbytes: int) -> int:
        ptr, size = self._buffers.get(name, (0, 0))
        if size < nbytes:
            if ptr:
                self.cudart.cudaFree(ptr)
            _, ptr = self.cudart.cudaMalloc(nbytes)
            self._buffers[name] = (ptr, nbytes)
        return ptr

    def run(self, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        cudart = self.cudart
        h2d, d2h = cudart.cudaMemcpyKind.cudaMemcpyHostToDevice, cudart.cudaMemcpyKind.cudaMemcpyDeviceToHost
        for n in self.inputs:
            host = np.ascontiguousarray(feeds[n], dtype=self.dtypes[n])
            self.context.set_input_shape(n, host.shape)
            ptr = self._device(n, host.nbytes)
            cudart.cudaMemcpyAsync(ptr, host.ctypes.data, host.nbytes, h2d, self.stream)
            self.context.set_tensor_address(n, ptr)
        outs = {}
        for n in self.outputs:
            outs[n] = np.empty(tuple(self.context.get_tensor_shape(n)), self.dtypes[n])
            self.context.set_tensor_address(n, self._device(n, outs[n].nbytes))
        self.context.execute_async_v3(self.stream)
        for n in self.outputs:
            cudart.cudaMemcpyAsync(outs[n].ctypes.data, self._buffers[n][0], outs[n].nbytes, d2h, self.stream)
        cudart.cudaStreamSynchronize(self.stream)
        return [outs[n] for n in self.outputs]


# ---------------------------------------------------------------------- models on a backend
def model_meta(profile: Profile, model: str) -> dict[str, Any]:
    """What a runtime needs besides the weights (PilotNet: conditional, crop). From the export's manifest.json
    when there is one (so a Jetson without torch can run the ONNX or engine files), else from the .pt."""
    manifest = profile.export_path / "manifest.json"
    if manifest.is_file():
        entry = json.loads(manifest.read_text()).get("models", {}).get(model)
        if entry and "meta" in entry:
            return dict(entry["meta"])
    from towndrive.agent.deploy.profiles import resolve

    checkpoint = resolve(profile.models[model].checkpoint)
    if model == "pilotnet":
        from towndrive.agent.perception.pilotnet import load_model

        _, meta = load_model(checkpoint)
        return {"conditional": bool(meta["conditional"]), "crop": dict(meta.get("crop", {}))}
    return {}


def open_backend(profile: Profile, model: str) -> Backend:
    """The profile's backend for ``model``, loaded from the file ``profile.model_file(model)`` names."""
    spec = profile.models[model]
    path = profile.model_file(model)
    if spec.backend == "tensorrt":
        return TensorRTBackend(path, spec.precision)
    if spec.backend == "onnxruntime":
        if not path.is_file():
            raise FileNotFoundError(f"{path} not found; write it with: python train.py export --profile {profile.name}")
        return OnnxRuntimeBackend(path, spec.precision, spec.threads, role="PilotNet" if model == "pilotnet" else "detector")
    if model == "pilotnet":
        from towndrive.agent.perception.pilotnet import load_model

        net, meta = load_model(path)
        return TorchBackend(net, ["image", "command"] if meta["conditional"] else ["image"], spec.threads)
    from towndrive.agent.perception.detector import DecodedDetector, load_detector

    return TorchBackend(DecodedDetector(load_detector(path)), DETECTOR_INPUTS, spec.threads)


def pilotnet_feeds(rgb: np.ndarray, command: int, conditional: bool, crop: Any = None) -> dict[str, np.ndarray]:
    """A camera frame as PilotNet's inputs: ``preprocess`` (crop, 200x66, YUV) as float32 NCHW 0..255, and the command."""
    from towndrive.agent.perception.pilotnet import DEFAULT_CROP, preprocess

    yuv = preprocess(rgb, crop or DEFAULT_CROP)
    feeds = {"image": np.ascontiguousarray(yuv.transpose(2, 0, 1)[None], dtype=np.float32)}
    if conditional:
        feeds["command"] = np.array([int(command)], np.int64)
    return feeds


def detector_feeds(rgb: np.ndarray, input_size: tuple[int, int] = (320, 160)) -> dict[str, np.ndarray]:
    """A camera frame as the detector's input: resized to ``input_size`` (width, height) if needed, float32
    NCHW in [0, 1] (what ``agent.perception.detector.to_input`` gives at the native size)."""
    import cv2

    w, h = input_size
    if rgb.shape[:2] != (h, w):
        rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
    return {"image": np.ascontiguousarray(rgb.transpose(2, 0, 1)[None], dtype=np.float32) / np.float32(255.0)}


class PilotNetRunner:
    """``steer(rgb, command)`` as ``agent.perception.pilotnet.PilotNetModel`` has it, on any backend."""

    def __init__(self, backend: Backend, conditional: bool, crop: dict[str, float] | None = None) -> None:
        from towndrive.agent.perception.pilotnet import Crop

        self.backend = backend
        self.conditional = conditional
        self.crop = Crop(**(crop or {}))

    def inputs(self, rgb: np.ndarray, command: int) -> dict[str, np.ndarray]:
        return pilotnet_feeds(rgb, command, self.conditional, self.crop)

    def steer(self, rgb: np.ndarray, command: int) -> float:
        return float(np.asarray(self.backend.run(self.inputs(rgb, command))[0]).reshape(-1)[0])


class DetectorRunner:
    """Frames in, detections out (as ``OnnxDetector``), on any backend and at the profile's input size:
    a frame of another size is resized to it, and the boxes are scaled back to the frame's pixels."""

    def __init__(self, backend: Backend, input_size: tuple[int, int] = (320, 160), score_threshold: float = 0.3,
                 refine: Refine | None = None, read: Read | None = None) -> None:
        self.backend = backend
        self.input_size = input_size
        self.score_threshold = score_threshold
        self.refine = refine  # the pedestrian refiner (agent/perception/ped_refiner.py), on the frame's pixels
        self.read = read  # the sign reader (agent/perception/sign_reader.py), likewise; skipped for a six-class model

    def inputs(self, rgb: np.ndarray) -> dict[str, np.ndarray]:
        return detector_feeds(rgb, self.input_size)

    def raw(self, rgb: np.ndarray) -> np.ndarray:
        """Decoded cells (cells x (4 + 1 + classes)), boxes in the frame's pixels."""
        pred = np.array(self.backend.run(self.inputs(rgb))[0][0], dtype=np.float32)
        w, h = self.input_size
        if rgb.shape[:2] != (h, w):
            pred[:, [0, 2]] *= rgb.shape[1] / w
            pred[:, [1, 3]] *= rgb.shape[0] / h
        return pred

    def __call__(self, rgb: np.ndarray) -> list[Detection]:
        from towndrive.agent.perception.detector import detect_and_refine

        return detect_and_refine(self.raw(rgb), rgb, self.score_threshold, self.refine, self.read)

    def detect_only(self, rgb: np.ndarray, names: tuple[str, ...]) -> list[Detection]:
        """The detections of the classes ``names`` alone, as ``OnnxDetector.detect_only`` gives them: the agent's
        mirror look asks for vehicles only, so neither second stage runs on those frames (it does not in the
        simulator's agent either)."""
        from towndrive.agent.perception.detector import detect_only_classes

        return detect_only_classes(self.raw(rgb), rgb, self.score_threshold, self.refine, names, self.read)


def open_pilotnet(profile: Profile) -> PilotNetRunner:
    meta = model_meta(profile, "pilotnet")
    return PilotNetRunner(open_backend(profile, "pilotnet"), bool(meta["conditional"]), meta.get("crop"))


def open_detector(profile: Profile, score_threshold: float = 0.3) -> DetectorRunner:
    """The profile's detector, followed by the shipped sign reader and pedestrian refiner unless ``modules.sign_reader``
    or ``modules.refiner`` is disabled: the stages the simulator's agent runs (``agent.agent_driver``). Both are small
    and run on ONNX Runtime's CPU provider, one thread each, whatever the detector's backend."""
    refine, read = None, None
    if profile.every("refiner"):
        from towndrive.agent.deploy.profiles import resolve
        from towndrive.agent.perception.ped_refiner import DEFAULT_REFINER_ONNX, onnx_refine

        refine = onnx_refine(resolve(DEFAULT_REFINER_ONNX), threads=1)
    if profile.every("sign_reader"):
        from towndrive.agent.perception.sign_reader import onnx_read
        from towndrive.agent.shipped import SIGN_READER_ONNX

        read = onnx_read(SIGN_READER_ONNX, threads=1)
    return DetectorRunner(open_backend(profile, "detector"), profile.models["detector"].input_size, score_threshold,
                          refine, read)
