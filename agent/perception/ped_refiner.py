"""A second stage for pedestrians: a tiny CNN that re-places and re-scores each pedestrian box from a crop.

Why: a pedestrian within 40 m is often 2-4 px wide on the 320x160 frame, and the one-stage detector finds
most of them but places the box a pixel off: on the test towns its pedestrian AP is 0.90 at IoU 0.1 and
0.81 at IoU 0.5. A crop centred on each candidate box, resampled so the pedestrian fills a fixed 32x16
grid, lets a small network see the person's pixel columns directly and predict the box edges again; the
same network says whether the crop holds a pedestrian at all (night-time poles and tail lights do not),
and its probability is blended with the detector's score (a geometric mean, ``score_weight``).

The labelled boxes are pixel-exact (the renderer has no anti-aliasing, so a person covers whole pixels);
``snap_to_pixels`` rounds the refined edges to the pixel grid for the same reason.

Input of the network: N x 4 x 32 x 16, the crop's RGB in [-0.5, 0.5] and the candidate box as a mask
channel (+0.5 inside, -0.5 outside). Output: N x 5, the change of the four box edges in window units and
a pedestrian logit.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from towndrive.agent.perception.classes import CLASSES
from towndrive.agent.perception.detections import Detection, nms_numpy

PEDESTRIAN = CLASSES.index("pedestrian")
DEFAULT_REFINER_ONNX = "data/models/ped_refiner.onnx"
CROP_HW = (32, 16)


@dataclass(frozen=True)
class RefinerConfig:
    channels: tuple[int, int, int] = (24, 48, 96)
    hidden: int = 256
    context: float = 2.0  # the window is this many times the candidate box
    min_window_px: float = 16.0  # window height at least this (a 6 px pedestrian is seen 2.7x magnified)
    score_weight: float = 0.5  # final score = detector score^(1 - w) * refiner probability^w
    candidate_score: float = 0.01  # detector pedestrian boxes at least this score are refined
    snap_to_pixels: bool = True
    nms_iou: float = 0.7  # refined boxes that now coincide are merged again (1.0: never)

    def __post_init__(self) -> None:
        object.__setattr__(self, "channels", tuple(self.channels))

    def lowest_candidate(self, score_threshold: float) -> float:
        """The lowest detector score worth refining: a final s^(1-w) p^w >= t needs s >= t^(1/(1-w)) at p = 1."""
        lowest = score_threshold ** (1.0 / (1.0 - self.score_weight)) if self.score_weight < 1.0 else 0.0
        return max(self.candidate_score, lowest)


def _block(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


class PedRefiner(nn.Module):
    """Six 3x3 conv-BN-ReLU layers down to 8x4, then two linear layers: 4 edge changes and a logit."""

    def __init__(self, config: RefinerConfig | None = None) -> None:
        super().__init__()
        self.config = config or RefinerConfig()
        a, b, c = self.config.channels
        self.features = nn.Sequential(_block(4, a), _block(a, a), _block(a, b, 2), _block(b, b),
                                      _block(b, c, 2), _block(c, c))
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(c * (CROP_HW[0] // 4) * (CROP_HW[1] // 4), self.config.hidden),
                                  nn.ReLU(inplace=True), nn.Linear(self.config.hidden, 5))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x))


# --------------------------------------------------------------------------- crops
def windows(boxes: np.ndarray, config: RefinerConfig) -> np.ndarray:
    """Candidate boxes (x0, y0, x1, y1) -> crop windows (x0, y0, width, height) in pixels, 2:1 tall."""
    b = np.asarray(boxes, np.float32).reshape(-1, 4)
    cx, cy = (b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2
    height = np.maximum(config.context * (b[:, 3] - b[:, 1]), config.min_window_px)
    width = np.maximum(height * CROP_HW[1] / CROP_HW[0], config.context * (b[:, 2] - b[:, 0]))
    return np.stack([cx - width / 2, cy - height / 2, width, height], 1).astype(np.float32)


def crop_windows(rgb: np.ndarray, win: np.ndarray) -> np.ndarray:
    """uint8 N x 32 x 16 x 3 crops of the windows, bilinear, the border pixels repeated outside the frame."""
    import cv2

    h, w = CROP_HW
    out = np.empty((len(win), h, w, 3), np.uint8)
    for i, (x0, y0, ww, hh) in enumerate(win):
        sx, sy = ww / w, hh / h
        # Output pixel (u, v) samples the frame at pixel-centre coordinates x0 + (u + 0.5) sx - 0.5.
        m = np.array([[sx, 0, x0 + 0.5 * sx - 0.5], [0, sy, y0 + 0.5 * sy - 0.5]], np.float32)
        out[i] = cv2.warpAffine(rgb, m, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                borderMode=cv2.BORDER_REPLICATE)
    return out


def to_window(boxes: np.ndarray, win: np.ndarray) -> np.ndarray:
    """Pixel boxes -> window units (0..1 across the window)."""
    return np.stack([(boxes[:, 0] - win[:, 0]) / win[:, 2], (boxes[:, 1] - win[:, 1]) / win[:, 3],
                     (boxes[:, 2] - win[:, 0]) / win[:, 2], (boxes[:, 3] - win[:, 1]) / win[:, 3]], 1)


def from_window(boxes: np.ndarray, win: np.ndarray) -> np.ndarray:
    return np.stack([win[:, 0] + boxes[:, 0] * win[:, 2], win[:, 1] + boxes[:, 1] * win[:, 3],
                     win[:, 0] + boxes[:, 2] * win[:, 2], win[:, 1] + boxes[:, 3] * win[:, 3]], 1)


def refiner_inputs(crops: np.ndarray, cand_win: np.ndarray) -> np.ndarray:
    """uint8 crops and the candidate boxes in window units -> the network's float32 N x 4 x 32 x 16 input."""
    h, w = CROP_HW
    x = crops.transpose(0, 3, 1, 2).astype(np.float32) / np.float32(255.0) - np.float32(0.5)
    ys = (np.arange(h, dtype=np.float32) + 0.5) / h
    xs = (np.arange(w, dtype=np.float32) + 0.5) / w
    c = cand_win.astype(np.float32)
    inside = ((xs[None, None, :] >= c[:, 0, None, None]) & (xs[None, None, :] <= c[:, 2, None, None])
              & (ys[None, :, None] >= c[:, 1, None, None]) & (ys[None, :, None] <= c[:, 3, None, None]))
    return np.ascontiguousarray(np.concatenate([x, inside[:, None].astype(np.float32) - np.float32(0.5)], 1))


# --------------------------------------------------------------------------- applying it
class Refine:
    """Detections in, detections out: pedestrian boxes re-placed and re-scored, everything else untouched.

    ``run`` maps the network input (N x 4 x 32 x 16 float32) to its output (N x 5), with torch or ONNX Runtime.
    """

    def __init__(self, run: Callable[[np.ndarray], np.ndarray], config: RefinerConfig) -> None:
        self.run = run
        self.config = config

    def __call__(self, rgb: np.ndarray, detections: list[Detection], score_threshold: float) -> list[Detection]:
        cfg = self.config
        keep = [d for d in detections if d.cls != PEDESTRIAN and d.score >= score_threshold]
        peds = [d for d in detections if d.cls == PEDESTRIAN and d.score >= cfg.lowest_candidate(score_threshold)]
        if not peds:
            return keep
        cand = np.array([d.box for d in peds], np.float32)
        win = windows(cand, cfg)
        cand_win = to_window(cand, win)
        out = np.asarray(self.run(refiner_inputs(crop_windows(rgb, win), cand_win)), np.float32)
        boxes = from_window(cand_win + out[:, :4], win)
        boxes[:, 2] = np.maximum(boxes[:, 2], boxes[:, 0] + 0.5)
        boxes[:, 3] = np.maximum(boxes[:, 3], boxes[:, 1] + 0.5)
        if cfg.snap_to_pixels:
            snapped = np.round(boxes)
            ok = (snapped[:, 2] > snapped[:, 0]) & (snapped[:, 3] > snapped[:, 1])
            boxes[ok] = snapped[ok]
        prob = 1.0 / (1.0 + np.exp(-out[:, 4].astype(np.float64)))
        det_score = np.array([d.score for d in peds], np.float64)
        score = det_score ** (1.0 - cfg.score_weight) * prob ** cfg.score_weight
        idx = nms_numpy(boxes, score, cfg.nms_iou)
        refined = [Detection(tuple(float(v) for v in boxes[i]), PEDESTRIAN, float(score[i]))
                   for i in idx if score[i] >= score_threshold]
        return sorted(keep + refined, key=lambda d: -d.score)


def load_refiner(path: str | Path) -> PedRefiner:
    """A trained refiner from a checkpoint written by ``train.py detector refiner``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Pedestrian refiner {path} not found; train one with `python train.py detector refiner`.")
    from towndrive.agent.perception.checkpoints import load_checkpoint

    ckpt = load_checkpoint(path, "pedestrian refiner")
    if ckpt.get("kind") != "ped_refiner":
        raise ValueError(f"{path} is not a pedestrian refiner checkpoint; retrain it with train.py detector refiner.")
    model = PedRefiner(RefinerConfig(**ckpt["config"]))
    model.load_state_dict(ckpt["state_dict"])
    return model.eval()


def torch_refine(path: str | Path) -> Refine:
    from towndrive.agent.perception.checkpoints import numpy_forward

    model = load_refiner(path)
    return Refine(numpy_forward(model), model.config)


def onnx_refine(path: str | Path, threads: int = 0) -> Refine:
    """The exported refiner through ONNX Runtime; its config travels in the ONNX file's metadata."""
    from towndrive.agent.perception.onnx_runtime import second_stage_session

    run, config = second_stage_session(path, threads, "pedestrian refiner", "refiner_config")
    return Refine(run, RefinerConfig(**config))
