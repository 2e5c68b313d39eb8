"""Export a deployment profile's models: ONNX (fp32, fp16, int8), INT8 calibration frames and the engine-build script.

  python train.py export --profile jetson-xavier            # -> out/deploy/jetson-xavier/
  python train.py export --profile cpu --pilotnet out/pilotnet/bc.pt

For each model of the profile (``pilotnet``, ``detector``) the folder gets:

  <model>.fp32.onnx          exported from the torch checkpoint; ONNX Runtime must match torch within 1e-4
  <model>.fp16.onnx          the same graph with fp16 weights and arithmetic, fp32 inputs and outputs; it must
                             match torch within the fp16 tolerance (``FP16_ATOL`` + ``FP16_RTOL`` x the
                             output channel's largest |value|)
  <model>.int8.onnx          statically quantized for ONNX Runtime's CPU (QDQ, calibrated on the frames below);
                             its accuracy is measured by evaluation (the detector's AP), not by a tolerance
  <model>.calib.npy          INT8 calibration inputs (uint8 N x C x H x W, the model's input before its scale),
                             frames drawn evenly from recorded episodes (``--calibration-data``), seeded
  pilotnet.calib_command.npy the route command of each calibration frame (conditional PilotNet)
  manifest.json              what was written, the parity figures, the models' metadata (so a Jetson without
                             torch can run the files), the calibration inputs' scales
  build_engines.sh           run on the device: the INT8 calibration cache (``python -m towndrive.agent.deploy.trt_calibrate``)
                             and ``trtexec`` with ``--fp16`` or ``--int8 --calib``, one engine per TensorRT model

Why build engines on the device: a TensorRT engine is specific to the GPU and the TensorRT version, so
only the ONNX files and the calibration frames travel; the script does the rest where it will run.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shlex
import stat
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from towndrive.agent.deploy.profiles import Profile, ProfileError, load_profile, resolve

FP32_TOLERANCE = 1e-4
# fp16 has an 11-bit significand (relative step 2^-11 ~ 4.9e-4 per rounding); through a dozen layers the
# error grows to a few steps. A value passes when |fp16 - torch| <= FP16_ATOL + FP16_RTOL x S, where S is the
# largest |torch| value of its output channel (last axis): 0.012 on steering and scores, about 0.7 pixel on box
# edges (S ~ 330 px). The channel scale, not the value itself, because a box edge near x = 0 is the difference
# of two numbers near 100 and carries their rounding error.
FP16_ATOL = 1e-2
FP16_RTOL = 2e-3


@dataclass
class ModelExport:
    """One model ready to export: the torch module, example inputs, names and metadata."""

    name: str
    module: Any
    examples: list[Any]  # torch tensors, for export_onnx's parity check
    input_names: list[str]
    output_names: list[str]
    meta: dict[str, Any]
    input_shapes: dict[str, tuple[int, ...]]  # batch 1, for trtexec --shapes


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--profile", default="cpu", help="profile name (agent/deploy/profiles/*.yaml) or a .yaml path")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: the profile's export_dir)")
    p.add_argument("--calibration-data", type=Path, nargs="+", default=[Path("data/episodes/autopilot")],
                   help="recorded episode folders for INT8 calibration frames")
    p.add_argument("--calib-frames", type=int, default=300, help="calibration frames (TensorRT suggests ~500)")
    p.add_argument("--seed", type=int, default=0, help="which calibration frames are drawn")
    p.add_argument("--pilotnet", type=Path, default=None, help="PilotNet checkpoint instead of the profile's")
    p.add_argument("--detector", type=Path, default=None, help="detector checkpoint instead of the profile's")
    p.add_argument("--models", default="", help="comma-separated subset of the profile's models (default: all)")


def run(args: argparse.Namespace) -> int:
    try:
        profile = load_profile(args.profile)
    except ProfileError as exc:
        print(f"train.py export: {exc}")
        return 2
    checkpoints = {k: v for k, v in (("pilotnet", args.pilotnet), ("detector", args.detector)) if v is not None}
    models = [m for m in args.models.split(",") if m] or list(profile.models)
    try:
        manifest = export_profile(profile, args.out, models, args.calibration_data, args.calib_frames, args.seed, checkpoints)
    except (FileNotFoundError, ValueError) as exc:
        print(f"train.py export: {exc}")
        return 2
    out = Path(manifest["out"])
    for name, entry in manifest["models"].items():
        print(f"{name}: fp32 max |onnx - torch| {entry['fp32_max_diff']:.2e} (<= {FP32_TOLERANCE:.0e}); fp16 max diff "
              f"{entry['fp16_max_diff']:.2e}, worst share of its tolerance {entry['fp16_tolerance_used']:.2f}; "
              f"{entry['calibration']['frames']} calibration frames"
              + (f"; int8 max diff {entry['int8_max_diff']:.3g} (judge it by evaluation)" if entry["int8"] else
                 "; no int8 file (no recorded episodes to calibrate on)"))
    print(f"wrote {out}; on the device run: bash {out / 'build_engines.sh'}")
    return 0


# ---------------------------------------------------------------------- models
def prepare(name: str, checkpoint: Path, input_size: tuple[int, int]) -> ModelExport:
    """The torch module and example inputs of one model, at the profile's input size (width, height)."""
    import torch

    gen = torch.Generator().manual_seed(0)
    w, h = input_size
    if name == "pilotnet":
        from towndrive.agent.perception.pilotnet import load_model

        model, meta = load_model(checkpoint)
        conditional = bool(meta["conditional"])
        image = torch.rand(4, 3, h, w, generator=gen) * 255.0
        examples = [image, torch.tensor([0, 1, 2, 3], dtype=torch.int64)] if conditional else [image]
        names = ["image", "command"] if conditional else ["image"]
        shapes = {"image": (1, 3, h, w), **({"command": (1,)} if conditional else {})}
        return ModelExport(name, model, examples, names, ["steer"],
                           {"conditional": conditional, "crop": dict(meta.get("crop", {}))}, shapes)
    if name == "detector":
        from towndrive.agent.perception.classes import CLASSES
        from towndrive.agent.perception.detector import DecodedDetector, load_detector

        net = load_detector(checkpoint)
        module = DecodedDetector(net).eval()
        classes = list(CLASSES[:net.config.num_classes])  # a model of before the road signs has the first six
        return ModelExport(name, module, [torch.rand(2, 3, h, w, generator=gen)], ["image"], ["detections"],
                           {"classes": classes, "input_size": [w, h]}, {"image": (1, 3, h, w)})
    raise ValueError(f"Unknown model {name!r}; a profile has pilotnet and detector.")


def to_fp16(src: Path, dst: Path) -> None:
    """fp16 weights and arithmetic, fp32 inputs and outputs (casts at the edges), so callers feed the same arrays.

    Uses onnxconverter_common where installed, else the same converter that ships inside onnxruntime.
    """
    import onnx

    try:
        from onnxconverter_common.float16 import convert_float_to_float16  # type: ignore[import-not-found]
    except ImportError:
        from onnxruntime.transformers.float16 import convert_float_to_float16
    model = convert_float_to_float16(onnx.load(str(src)), keep_io_types=True)
    onnx.save(model, str(dst))


def to_int8(src: Path, dst: Path, calib: dict[str, np.ndarray], scales: dict[str, float], frames: int = 100) -> None:
    """A statically quantized copy for ONNX Runtime's CPU (QDQ: int8 per-channel weights, uint8 activations, the
    ranges from up to ``frames`` calibration inputs). Only convolutions and matrix products are quantized; the
    detector's decoding (sigmoid, exp, box arithmetic) stays fp32. Its accuracy is measured, not bounded: there
    is no tolerance against torch that int8 could be held to, so ``train.py detector evaluate`` reports its AP.
    """
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

    n = min(frames, len(calib["image"]))

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self.k = 0

        def get_next(self) -> dict[str, np.ndarray] | None:
            if self.k >= n:
                return None
            self.k += 1
            return {name: (arr[self.k - 1:self.k].astype(np.float32) * np.float32(scales[name])
                           if name == "image" else arr[self.k - 1:self.k].astype(np.int64)) for name, arr in calib.items()}

    # asymmetric uint8 activations: the fast u8s8 kernels of ONNX Runtime on x86 (symmetric int8 ran 2x slower)
    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)  # its advice to run symbolic shape pre-processing fails on this graph's decoding
    try:
        quantize_static(str(src), str(dst), Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        op_types_to_quantize=["Conv", "Gemm", "MatMul"])
    finally:
        root.setLevel(level)


def fp16_check(outputs: Sequence[np.ndarray], reference: Sequence[np.ndarray]) -> tuple[float, float]:
    """(largest |fp16 - fp32 torch|, largest share of the allowed error used); the share must be <= 1."""
    diff, used = 0.0, 0.0
    for got, ref in zip(outputs, reference, strict=True):
        ref = ref.astype(np.float64)
        err = np.abs(got.astype(np.float64) - ref)
        flat = np.abs(ref).reshape(-1, ref.shape[-1]) if ref.ndim else np.abs(ref).reshape(1, 1)
        scale = flat.max(axis=0, initial=0.0)  # per output channel
        diff = max(diff, float(err.max(initial=0.0)))
        used = max(used, float((err / (FP16_ATOL + FP16_RTOL * scale)).max(initial=0.0)))
    return diff, used


def torch_outputs(module: Any, feeds: dict[str, np.ndarray], names: Sequence[str]) -> list[np.ndarray]:
    from towndrive.agent.deploy.backends import TorchBackend

    return TorchBackend(module, names, threads=0).run(feeds)


# ---------------------------------------------------------------------- calibration frames
def calibration_frames(folders: Sequence[Path], n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` camera frames (uint8 N x H x W x 3) and their route commands, drawn evenly across the episodes of
    ``folders`` (every episode gives its share, random moving frames within it). Empty arrays when none."""
    import h5py

    from towndrive.data.episodes import EpisodeError, list_episodes

    paths = []
    for folder in folders:
        try:
            paths += list_episodes(resolve(folder))
        except EpisodeError:
            continue
    if not paths or n <= 0:
        return np.zeros((0, 0, 0, 3), np.uint8), np.zeros(0, np.int64)
    rng = np.random.default_rng(seed)
    share = np.diff(np.linspace(0, n, len(paths) + 1).round().astype(int))
    frames, commands = [], []
    for path, k in zip(paths, share, strict=True):
        if k == 0:
            continue
        try:
            with h5py.File(path, "r") as f:
                speed = f["speed"][()]
                moving = np.flatnonzero(speed >= 1.0)
                pool = moving if len(moving) >= k else np.arange(len(speed))
                idx = np.sort(rng.choice(pool, size=min(k, len(pool)), replace=False))
                frames.append(f["frames"][idx])
                commands.append(f["command"][idx].astype(np.int64))
        except (OSError, KeyError) as exc:
            raise EpisodeError(f"{path}: cannot read calibration frames ({exc}); re-record or remove it.") from exc
    shapes = {fr.shape[1:] for fr in frames}
    if len(shapes) > 1:
        raise ValueError(f"Calibration episodes have different frame sizes {sorted(shapes)}; use one camera size.")
    return np.concatenate(frames), np.concatenate(commands)


def calibration_inputs(name: str, meta: dict[str, Any], input_size: tuple[int, int], frames: np.ndarray,
                       commands: np.ndarray) -> dict[str, np.ndarray]:
    """The model's inputs for the calibration frames, as compact integers (the runtime multiplies by the scale)."""
    from towndrive.agent.deploy.backends import detector_feeds, pilotnet_feeds
    from towndrive.agent.perception.pilotnet import Crop

    if name == "pilotnet":
        crop = Crop(**meta.get("crop", {}))
        images = [pilotnet_feeds(f, 0, False, crop)["image"][0] for f in frames]
        out = {"image": np.stack(images).astype(np.uint8) if images else np.zeros((0, 3, 66, 200), np.uint8)}
        if meta["conditional"]:
            out["command"] = commands.astype(np.int64)
        return out
    w, h = input_size
    images = [np.rint(detector_feeds(f, input_size)["image"][0] * 255.0) for f in frames]
    return {"image": np.stack(images).astype(np.uint8) if images else np.zeros((0, 3, h, w), np.uint8)}


# ---------------------------------------------------------------------- the whole export
def export_profile(profile: Profile, out: Path | None = None, models: Sequence[str] | None = None,
                   episodes: Sequence[Path] = (Path("data/episodes/autopilot"),), calib_frames: int = 300, seed: int = 0,
                   checkpoints: dict[str, Path] | None = None) -> dict[str, Any]:
    """Write every file listed in the module docstring into ``out``; returns the manifest."""
    from towndrive.agent.deploy.backends import OnnxRuntimeBackend
    from towndrive.agent.deploy.onnx_export import export_onnx

    out = resolve(out) if out is not None else profile.export_path
    out.mkdir(parents=True, exist_ok=True)
    models = list(models or profile.models)
    unknown = [m for m in models if m not in profile.models]
    if unknown:
        raise ValueError(f"Unknown model {unknown[0]!r}; the profile has {', '.join(profile.models)}.")
    frames, commands = calibration_frames(episodes, calib_frames, seed)
    manifest: dict[str, Any] = {"profile": profile.name, "profile_file": profile.source_file, "out": str(out),
                                "fp32_tolerance": FP32_TOLERANCE, "fp16_atol": FP16_ATOL, "fp16_rtol": FP16_RTOL,
                                "calibration_episodes": [str(e) for e in episodes], "seed": seed, "models": {}}
    for name in models:
        spec = profile.models[name]
        checkpoint = resolve((checkpoints or {}).get(name, spec.checkpoint))
        job = prepare(name, checkpoint, spec.input_size)
        fp32, fp16 = out / f"{name}.fp32.onnx", out / f"{name}.fp16.onnx"
        fp32_diff = export_onnx(job.module, job.examples, fp32, job.input_names, job.output_names, FP32_TOLERANCE)
        to_fp16(fp32, fp16)
        calib = calibration_inputs(name, job.meta, spec.input_size, frames, commands)
        scales = {"image": 1.0 / 255.0 if name == "detector" else 1.0, "command": 1.0}
        # fp16 parity on real frames where there are some (activations of real scenes), else on the examples
        feeds_list = ([{k: (v[:8].astype(np.float32) * scales[k]).astype(np.float32 if k == "image" else np.int64)
                        for k, v in calib.items()}] if len(calib["image"]) else
                      [{n: t.numpy() for n, t in zip(job.input_names, job.examples, strict=True)}])
        session = OnnxRuntimeBackend(fp16, "fp16", threads=0)
        diffs = [fp16_check(session.run(f), torch_outputs(job.module, f, job.input_names)) for f in feeds_list]
        fp16_diff, used = max(d for d, _ in diffs), max(u for _, u in diffs)
        if used > 1.0:
            fp16.unlink(missing_ok=True)
            raise ValueError(f"{name}: the fp16 ONNX differs from torch by {fp16_diff:.3g}, more than the fp16 tolerance "
                             f"({FP16_ATOL} + {FP16_RTOL} x the channel's largest |value|); not written.")
        int8_entry: dict[str, Any] = {"int8": None}
        if len(calib["image"]):
            int8 = out / f"{name}.int8.onnx"
            to_int8(fp32, int8, calib, scales)
            int8_diff = max(max(float(np.abs(g - r).max()) for g, r in zip(
                OnnxRuntimeBackend(int8, "int8", threads=0).run(f), torch_outputs(job.module, f, job.input_names),
                strict=True)) for f in feeds_list)
            int8_entry = {"int8": int8.name, "int8_max_diff": int8_diff}
        calib_files = {}
        for k, arr in calib.items():
            path = out / (f"{name}.calib.npy" if k == "image" else f"{name}.calib_{k}.npy")
            np.save(path, arr)
            calib_files[k] = {"file": path.name, "scale": scales[k], "dtype": "float32" if k == "image" else "int32"}
        manifest["models"][name] = {
            "checkpoint": str(checkpoint), "backend": spec.backend, "precision": spec.precision,
            "input_size": list(spec.input_size), "inputs": job.input_names, "outputs": job.output_names,
            "input_shapes": {k: list(v) for k, v in job.input_shapes.items()}, "fp32": fp32.name, "fp16": fp16.name,
            "fp32_max_diff": fp32_diff, "fp16_max_diff": fp16_diff, "fp16_tolerance_used": used,
            "fp16_checked_on": "calibration frames" if len(calib["image"]) else "random inputs", **int8_entry,
            "engine": f"{name}.{spec.precision}.engine" if spec.backend == "tensorrt" else None,
            "dla_core": spec.dla_core, "workspace_mb": spec.workspace_mb,
            "calibration": {"frames": int(len(calib["image"])), "inputs": calib_files, "cache": f"{name}.calib.cache"},
            "meta": job.meta,
        }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2))
    script = out / "build_engines.sh"
    script.write_text(engine_script(manifest, out))
    script.chmod(script.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    return manifest


def engine_script(manifest: dict[str, Any], out: Path) -> str:
    """The bash script that builds the profile's TensorRT engines on the device (see module docstring)."""
    repo = os.path.relpath(resolve("."), out)
    lines = [
        "#!/usr/bin/env bash",
        f"# Build the TensorRT engines of profile {manifest['profile']} ON THE DEVICE (an engine only runs on the GPU",
        "# and TensorRT version that built it). Written by `python train.py export`; run from anywhere:",
        f"#   bash {os.path.relpath(out / 'build_engines.sh', resolve('.'))}    (TRTEXEC=/path/to/trtexec to use another one)",
        "set -euo pipefail",
        'HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"',
        f'REPO="${{REPO:-$(cd "$HERE/{repo}" && pwd)}}"',
        'PYTHON="${PYTHON:-python3}"',
        'TRTEXEC="${TRTEXEC:-$(command -v trtexec || echo /usr/src/tensorrt/bin/trtexec)}"',
        'if [ ! -x "$TRTEXEC" ]; then',
        '  echo "trtexec not found (looked in PATH and /usr/src/tensorrt/bin): install TensorRT (JetPack ships it)' +
        ' or set TRTEXEC=/path/to/trtexec." >&2',
        "  exit 1",
        "fi",
        "# TensorRT >= 8.4 sizes the builder's memory with --memPoolSize; older ones (JetPack 4.6) with --workspace.",
        'pool() { if "$TRTEXEC" --help 2>&1 | grep -q memPoolSize; then echo "--memPoolSize=workspace:$1"; '
        'else echo "--workspace=$1"; fi; }',
    ]
    todo = [(n, m) for n, m in manifest["models"].items() if m["backend"] == "tensorrt"]
    if not todo:
        lines += [f'echo "profile {manifest["profile"]} runs no model on TensorRT; nothing to build."', "exit 0"]
        return "\n".join(lines) + "\n"
    for name, m in todo:
        shapes = ",".join(f"{k}:{'x'.join(str(d) for d in v)}" for k, v in m["input_shapes"].items())
        pool = f'"$(pool {int(m["workspace_mb"])})"'
        args = [f'--onnx="$HERE/{m["fp32"]}"', f'--saveEngine="$HERE/{m["engine"]}"', f"--shapes={shapes}", pool]
        lines.append("")
        lines.append(f"# {name}: {m['precision']}")
        if m["precision"] == "fp16":
            args.append("--fp16")
        elif m["precision"] == "int8":
            if not m["calibration"]["frames"]:
                lines.append(f'echo "{name}: no calibration frames were exported (no recorded episodes); record some '
                             'with drive.py --record and run train.py export again." >&2; exit 1')
                continue
            lines.append(f'(cd "$REPO" && "$PYTHON" -m towndrive.agent.deploy.trt_calibrate '
                         f'--manifest "$HERE/manifest.json" --model {name})')
            args += ["--int8", "--fp16", f'--calib="$HERE/{m["calibration"]["cache"]}"']  # fp16 where int8 has no kernel
        if m["dla_core"] is not None:
            args += [f"--useDLACore={int(m['dla_core'])}", "--allowGPUFallback"]
        lines.append('"$TRTEXEC" ' + " \\\n    ".join(args))
        lines.append(f'echo "built $HERE/{shlex.quote(m["engine"])}"')
    return "\n".join(lines) + "\n"
