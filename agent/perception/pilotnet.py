"""NVIDIA's PilotNet (Bojarski et al. 2016) and its conditional variant, plus the one preprocessing function.

The network is the paper's: a 66x200 YUV image, a fixed normalisation layer inside the network,
convolutions 24, 36, 48 (5x5, stride 2) and 64, 64 (3x3), then fully connected 100, 50, 10, 1:
252,219 parameters. There is no 1164-unit layer (the paper's figure labels the flattened 1164
features, which ports often turn into an extra layer).

The conditional variant (Codevilla et al. 2018, "branched") shares everything up to the 100-unit
layer and ends in one 50-10-1 branch per route command (follow, left, right, straight); the command
selects the branch. It is how a cloned driver can take the turn the route asks for.

``preprocess`` is the single function that turns a camera frame into the network's input, used by
training and driving alike: crop the sky (and a bonnet, if the camera shows one), resize to 200x66,
convert RGB to YUV.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import nn

from towndrive.agent.perception.checkpoints import load_checkpoint
from towndrive.agent.shipped import PILOTNET

DEFAULT_MODEL = PILOTNET  # the shipped pair: pilotnet.pt and pilotnet.onnx

INPUT_HEIGHT = 66
INPUT_WIDTH = 200
N_COMMANDS = 4  # sim.town.Command: follow, left, right, straight


@dataclass(frozen=True)
class Crop:
    """Rows of the camera frame the network sees, as fractions of the height (so any camera size works).

    The default drops the top 40% (sky and building tops above the horizon of the default camera, which
    sits at about row 68 of 160) and keeps everything down to the bottom row (the simulated car shows no
    bonnet). The crop keeps a little above the horizon so that curves far ahead are visible.
    """

    top: float = 0.40
    bottom: float = 1.0

    def rows(self, height: int) -> tuple[int, int]:
        return int(round(self.top * height)), int(round(self.bottom * height))


DEFAULT_CROP = Crop()


def preprocess(rgb: np.ndarray, crop: Crop = DEFAULT_CROP) -> np.ndarray:
    """Camera RGB (H x W x 3 uint8) -> PilotNet input, uint8 YUV 66 x 200 x 3 (normalised inside the net)."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"preprocess expects an H x W x 3 uint8 RGB frame; got {rgb.dtype} {rgb.shape}.")
    r0, r1 = crop.rows(rgb.shape[0])
    cropped = rgb[r0:r1]
    resized = cv2.resize(cropped, (INPUT_WIDTH, INPUT_HEIGHT), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(resized, cv2.COLOR_RGB2YUV)


def to_array(yuv: np.ndarray) -> np.ndarray:
    """uint8 (N x) 66 x 200 x 3 YUV -> float32 N x 3 x 66 x 200 (0..255; the network normalises), in NumPy: the
    ONNX Runtime path never calls torch (whose thread pool made the conversion take ms of waiting under load)."""
    arr = yuv if yuv.ndim == 4 else yuv[None]
    return np.ascontiguousarray(arr.transpose(0, 3, 1, 2), dtype=np.float32)


def to_tensor(yuv: np.ndarray) -> torch.Tensor:
    """uint8 (N x) 66 x 200 x 3 YUV -> float32 N x 3 x 66 x 200 (0..255; the network normalises)."""
    return torch.from_numpy(to_array(yuv))


class Normalize(nn.Module):
    """The paper's fixed (not learned) normalisation layer: pixels 0..255 -> about -1..1."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x / 127.5 - 1.0


def _features() -> nn.Sequential:
    return nn.Sequential(
        Normalize(),
        nn.Conv2d(3, 24, 5, stride=2), nn.ELU(),
        nn.Conv2d(24, 36, 5, stride=2), nn.ELU(),
        nn.Conv2d(36, 48, 5, stride=2), nn.ELU(),
        nn.Conv2d(48, 64, 3), nn.ELU(),
        nn.Conv2d(64, 64, 3), nn.ELU(),
        nn.Flatten(),  # 64 x 1 x 18 = 1152 features
    )


class PilotNet(nn.Module):
    """Steering from one frame: input N x 3 x 66 x 200 YUV (0..255), output N x 1 steer in about [-1, 1]."""

    conditional = False

    def __init__(self) -> None:
        super().__init__()
        self.features = _features()
        self.head = nn.Sequential(
            nn.Linear(1152, 100), nn.ELU(),
            nn.Linear(100, 50), nn.ELU(),
            nn.Linear(50, 10), nn.ELU(),
            nn.Linear(10, 1),
        )

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(image))


class ConditionalPilotNet(nn.Module):
    """PilotNet with one 50-10-1 branch per route command; input image and command (N,) int64."""

    conditional = True

    def __init__(self) -> None:
        super().__init__()
        self.features = _features()
        self.trunk = nn.Sequential(nn.Linear(1152, 100), nn.ELU())
        self.branches = nn.ModuleList(
            nn.Sequential(nn.Linear(100, 50), nn.ELU(), nn.Linear(50, 10), nn.ELU(), nn.Linear(10, 1))
            for _ in range(N_COMMANDS)
        )

    def forward(self, image: torch.Tensor, command: torch.Tensor) -> torch.Tensor:
        h = self.trunk(self.features(image))
        outs = torch.cat([branch(h) for branch in self.branches], dim=1)  # N x 4
        return outs.gather(1, command.long().view(-1, 1))


def build(conditional: bool) -> nn.Module:
    return ConditionalPilotNet() if conditional else PilotNet()


def parameter_count(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def load_model(path: str | Path) -> tuple[torch.nn.Module, dict[str, Any]]:
    """A PilotNet checkpoint (ours): the model in eval mode and its metadata. Errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PilotNet model {path} not found; train one with: python train.py pilotnet")
    ckpt = load_checkpoint(path, "PilotNet")
    try:
        model = build(bool(ckpt["conditional"]))
        model.load_state_dict(ckpt["state_dict"])
    except (KeyError, RuntimeError, ValueError, TypeError) as exc:
        # a wrong shape, a truncated file, or not ours at all
        raise ValueError(f"{path} is not a PilotNet checkpoint of this version ({exc}); retrain it with train.py.") from exc
    return model.eval(), {k: v for k, v in ckpt.items() if k not in ("state_dict", "optimizer")}


class PilotNetModel:
    """A trained PilotNet behind one call, ``steer(rgb, command)``, on ONNX Runtime or torch."""

    def __init__(self, path: str | Path = DEFAULT_MODEL, backend: str | None = "onnx", threads: int = 1) -> None:
        path = Path(path)
        shipped = path.resolve() == DEFAULT_MODEL
        backend = backend or ("torch" if path.suffix == ".pt" and not shipped else "onnx")  # None: as the file says
        if backend not in ("onnx", "torch"):
            raise ValueError(f"Unknown PilotNet backend {backend!r}; use 'onnx' or 'torch'.")
        if shipped:  # the shipped pair, not a file the user named
            path = DEFAULT_MODEL.with_suffix(".onnx" if backend == "onnx" else ".pt")
        wanted = ".onnx" if backend == "onnx" else ".pt"
        if path.suffix != wanted:
            raise ValueError(f"{path}: the {backend} backend runs {wanted} files; give the model's {wanted} file or "
                             f"the {'torch' if backend == 'onnx' else 'onnx'} backend (--backend).")
        self.backend = backend
        if backend == "onnx":
            import json

            from towndrive.agent.perception.onnx_runtime import onnx_session

            self.session = onnx_session(path, threads=threads, role="PilotNet")
            self.conditional = "command" in {i.name for i in self.session.get_inputs()}
            meta = self.session.get_modelmeta().custom_metadata_map.get("pilotnet_meta")
            try:
                self.crop = Crop(**json.loads(meta).get("crop", {})) if meta else Crop()
            except (ValueError, TypeError, AttributeError):
                raise ValueError(f"{path}: its pilotnet_meta metadata is not valid; re-export the model.") from None
        else:
            import torch

            self.model, meta = load_model(path)
            self.conditional = bool(meta["conditional"])
            self.crop = Crop(**meta.get("crop", {}))
            torch.set_num_threads(threads)

    def steer(self, rgb: np.ndarray, command: int) -> float:
        x = to_array(preprocess(rgb, self.crop))
        cmd = np.array([int(command)], np.int64)
        if self.backend == "onnx":
            feeds = {"image": x}
            if self.conditional:
                feeds["command"] = cmd
            return float(self.session.run(["steer"], feeds)[0][0, 0])
        import torch

        x = torch.from_numpy(x)
        with torch.no_grad():
            y = self.model(x, torch.from_numpy(cmd)) if self.conditional else self.model(x)
        return float(y[0, 0])
