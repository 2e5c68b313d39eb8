"""Write a TensorRT INT8 calibration cache from the frames ``train.py export`` saved (run on the device).

  python -m towndrive.agent.deploy.trt_calibrate --manifest out/deploy/jetson-xavier/manifest.json --model detector

``trtexec --int8 --calib=FILE`` only reads a calibration cache; it cannot compute one from images. This
module feeds the exported calibration frames (recorded simulator episodes) through TensorRT's entropy
calibrator once and writes ``<model>.calib.cache`` beside the manifest, which ``build_engines.sh`` then hands
to ``trtexec``. It needs TensorRT and cuda-python, so it runs on a Jetson, not on this CPU-only machine
(where it stops with one clear message).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from towndrive.agent.deploy.backends import BackendUnavailable, import_cudart, import_tensorrt


def calibration_arrays(manifest_path: Path, model: str) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The manifest entry of ``model`` and its calibration inputs, scaled as the model takes them."""
    manifest = json.loads(manifest_path.read_text())
    if model not in manifest.get("models", {}):
        raise ValueError(f"{manifest_path} has no model {model!r}; it has {', '.join(manifest.get('models', {}))}.")
    entry = manifest["models"][model]
    arrays = {}
    for name, spec in entry["calibration"]["inputs"].items():
        raw = np.load(manifest_path.parent / spec["file"])
        arrays[name] = raw.astype(np.float32) * np.float32(spec["scale"]) if name == "image" else raw.astype(np.int64)
    if not len(arrays.get("image", ())):
        raise ValueError(f"{manifest_path}: {model} has no calibration frames; record episodes and export again.")
    return entry, arrays


def build_cache(onnx_path: Path, arrays: dict[str, np.ndarray], cache_path: Path, batch: int = 8,
                workspace_mb: int = 1024) -> Path:
    """Calibrate ``onnx_path`` on ``arrays`` with TensorRT's IInt8EntropyCalibrator2; writes ``cache_path``."""
    trt = import_tensorrt()
    cudart = import_cudart()
    logger = trt.Logger(trt.Logger.INFO)
    n = len(next(iter(arrays.values())))
    batch = max(1, min(batch, n))

    class Calibrator(trt.IInt8EntropyCalibrator2):  # type: ignore[misc, name-defined]
        def __init__(self) -> None:
            super().__init__()
            self.index = 0
            self.ptrs: dict[str, int] = {}

        def get_batch_size(self) -> int:
            return batch

        def get_batch(self, names: list[str]) -> list[int] | None:
            if self.index + batch > n:
                return None
            out = []
            for name in names:
                host = np.ascontiguousarray(arrays[name][self.index:self.index + batch])
                if host.dtype == np.int64:
                    host = host.astype(np.int32)  # TensorRT's ONNX parser turns int64 inputs into int32
                if name not in self.ptrs:
                    _, self.ptrs[name] = cudart.cudaMalloc(host.nbytes)
                cudart.cudaMemcpy(self.ptrs[name], host.ctypes.data, host.nbytes,
                                  cudart.cudaMemcpyKind.cudaMemcpyHostToDevice)
                out.append(self.ptrs[name])
            self.index += batch
            return out

        def read_calibration_cache(self) -> bytes | None:
            return cache_path.read_bytes() if cache_path.exists() else None

        def write_calibration_cache(self, cache: Any) -> None:
            cache_path.write_bytes(bytes(cache))

    builder = trt.Builder(logger)
    explicit = 1 << int(trt.NetworkDefinitionCreationFlag.EXPLICIT_BATCH) if hasattr(
        trt.NetworkDefinitionCreationFlag, "EXPLICIT_BATCH") else 0
    network = builder.create_network(explicit)
    parser = trt.OnnxParser(network, logger)
    if not parser.parse(onnx_path.read_bytes()):
        errors = "; ".join(str(parser.get_error(i)) for i in range(parser.num_errors))
        raise ValueError(f"TensorRT cannot parse {onnx_path}: {errors}")
    config = builder.create_builder_config()
    config.set_flag(trt.BuilderFlag.INT8)
    if hasattr(config, "set_memory_pool_limit"):
        config.set_memory_pool_limit(trt.MemoryPoolType.WORKSPACE, workspace_mb << 20)
    shapes = builder.create_optimization_profile()
    for i in range(network.num_inputs):
        tensor = network.get_input(i)
        shape = (batch, *arrays[tensor.name].shape[1:])
        shapes.set_shape(tensor.name, shape, shape, shape)
    config.add_optimization_profile(shapes)
    config.set_calibration_profile(shapes)
    config.int8_calibrator = Calibrator()
    if builder.build_serialized_network(network, config) is None or not cache_path.exists():
        raise RuntimeError(f"TensorRT calibration of {onnx_path} failed; see TensorRT's log above.")
    return cache_path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--manifest", type=Path, required=True, help="manifest.json written by train.py export")
    ap.add_argument("--model", required=True, help="pilotnet or detector")
    ap.add_argument("--batch", type=int, default=8)
    args = ap.parse_args(argv)
    try:
        entry, arrays = calibration_arrays(args.manifest, args.model)
        cache = build_cache(args.manifest.parent / entry["fp32"], arrays, args.manifest.parent / entry["calibration"]["cache"],
                            args.batch, int(entry.get("workspace_mb", 1024)))
    except (BackendUnavailable, ValueError, FileNotFoundError, RuntimeError) as exc:
        print(f"trt_calibrate: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {cache}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
