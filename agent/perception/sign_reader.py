"""A second stage for road signs: a small CNN that reads which sign a detected sign box holds.

Why: the one-stage detector finds sign plates (most of its sign boxes lie at IoU 0.8-0.9 with the plate) but tells
them apart badly. A plate 5-15 px wide is the stride-4 head's, whose features are two convolutions from the pixels
plus upsampled stride-8 context: enough for a light's colour, too little for a plate's shape and digits. Fine-tuned
on the styled towns, the ten-class detector read most 50 limits as 30 and most yield signs as stop or 30 signs,
on its own training frames as well (``data/models/README.md``). A crop around each sign box, resampled to 32x32,
shows a small network the plate at a fixed scale, its outline and its digits a few pixels tall; it says which of
the four signs it is, or that it is none.

Input of the network: N x 3 x 32 x 32, the crop's RGB in [-0.5, 0.5]. Output: N x 5 logits, the sign classes in
``SIGN_CLASSES`` order and then "no sign". The detector's sign boxes are kept (their placement is good); their class
becomes the one read, their score the geometric blend of the detector's score and the probability of that class.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from towndrive.agent.perception.classes import CLASSES, SIGN_CLASSES
from towndrive.agent.perception.detections import Detection

SIGN_IDS: tuple[int, ...] = tuple(CLASSES.index(n) for n in SIGN_CLASSES)
NO_SIGN = len(SIGN_CLASSES)  # the network's last output
CROP = 32


@dataclass(frozen=True)
class SignReaderConfig:
    channels: tuple[int, int, int] = (16, 32, 64)
    context: float = 1.6  # the square window's side is this many times the box's longer side...
    min_window_px: float = 12.0  # ...and at least this (a 5 px plate is seen 2.7x magnified)
    score_weight: float = 0.5  # final score = detector score^(1 - w) * probability of the sign read^w
    candidate_score: float = 0.01  # detector sign boxes at least this score are read

    def __post_init__(self) -> None:
        object.__setattr__(self, "channels", tuple(self.channels))

    def lowest_candidate(self, score_threshold: float) -> float:
        """The lowest detector score worth reading: a final s^(1-w) p^w >= t needs s >= t^(1/(1-w)) at p = 1."""
        lowest = score_threshold ** (1.0 / (1.0 - self.score_weight)) if self.score_weight < 1.0 else 0.0
        return max(self.candidate_score, lowest)


def _block(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


class SignReader(nn.Module):
    """Six 3x3 conv-BN-ReLU layers from 32x32 down to 8x8, one more to 4x4, and a linear layer to 5 logits."""

    def __init__(self, config: SignReaderConfig | None = None) -> None:
        super().__init__()
        self.config = config or SignReaderConfig()
        a, b, c = self.config.channels
        self.features = nn.Sequential(_block(3, a), _block(a, a), _block(a, b, 2), _block(b, b), _block(b, c, 2),
                                      _block(c, c), _block(c, c, 2))
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(c * (CROP // 8) ** 2, NO_SIGN + 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x))


# --------------------------------------------------------------------------- crops
def windows(boxes: np.ndarray, config: SignReaderConfig) -> np.ndarray:
    """Sign boxes (x0, y0, x1, y1) -> square crop windows (x0, y0, side, side) in pixels, centred on the box."""
    b = np.asarray(boxes, np.float32).reshape(-1, 4)
    cx, cy = (b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2
    side = np.maximum(config.context * np.maximum(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]), config.min_window_px)
    return np.stack([cx - side / 2, cy - side / 2, side, side], 1).astype(np.float32)


def crop_windows(rgb: np.ndarray, win: np.ndarray) -> np.ndarray:
    """uint8 N x 32 x 32 x 3 crops of the windows, bilinear, the border pixels repeated outside the frame."""
    import cv2

    out = np.empty((len(win), CROP, CROP, 3), np.uint8)
    for i, (x0, y0, ww, hh) in enumerate(win):
        sx, sy = ww / CROP, hh / CROP
        # Output pixel (u, v) samples the frame at pixel-centre coordinates x0 + (u + 0.5) sx - 0.5.
        m = np.array([[sx, 0, x0 + 0.5 * sx - 0.5], [0, sy, y0 + 0.5 * sy - 0.5]], np.float32)
        out[i] = cv2.warpAffine(rgb, m, (CROP, CROP), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                borderMode=cv2.BORDER_REPLICATE)
    return out


def reader_inputs(crops: np.ndarray) -> np.ndarray:
    """uint8 N x 32 x 32 x 3 crops -> the network's float32 N x 3 x 32 x 32 input in [-0.5, 0.5]."""
    return np.ascontiguousarray(crops.transpose(0, 3, 1, 2).astype(np.float32) / np.float32(255.0) - np.float32(0.5))


def softmax(logits: np.ndarray) -> np.ndarray:
    z = logits - logits.max(axis=1, keepdims=True)
    e = np.exp(z)
    return e / e.sum(axis=1, keepdims=True)


# --------------------------------------------------------------------------- applying it
class Read:
    """Detections in, detections out: every sign box (any of the four sign classes) read again; the other
    detections are passed on untouched, whatever their score (the pedestrian refiner may come next).

    ``run`` maps the network input (N x 3 x 32 x 32 float32) to its output (N x 5), with torch or ONNX Runtime.
    """

    def __init__(self, run: Callable[[np.ndarray], np.ndarray], config: SignReaderConfig) -> None:
        self.run = run
        self.config = config

    def probabilities(self, rgb: np.ndarray, boxes: np.ndarray) -> np.ndarray:
        """N x 5: the four signs and "no sign", for boxes of a frame."""
        if len(boxes) == 0:
            return np.zeros((0, NO_SIGN + 1), np.float32)
        x = reader_inputs(crop_windows(rgb, windows(boxes, self.config)))
        return softmax(np.asarray(self.run(x), np.float32))

    def __call__(self, rgb: np.ndarray, detections: list[Detection], score_threshold: float) -> list[Detection]:
        cfg = self.config
        others = [d for d in detections if d.cls not in SIGN_IDS]
        signs = [d for d in detections if d.cls in SIGN_IDS and d.score >= cfg.lowest_candidate(score_threshold)]
        if not signs:
            return others
        p = self.probabilities(rgb, np.array([d.box for d in signs], np.float32))
        read = relabel(signs, p, cfg.score_weight)
        return others + [d for d in read if d.score >= score_threshold]


def relabel(signs: list[Detection], p: np.ndarray, score_weight: float) -> list[Detection]:
    """Sign detections with the class the reader gives the highest probability among the four signs, and the
    score ``detector^(1 - w) * p^w`` (so "no sign" lowers it)."""
    k = p[:, :NO_SIGN].argmax(axis=1)
    pk = p[np.arange(len(k)), k]
    out = []
    for d, cls, prob in zip(signs, k.tolist(), pk.tolist(), strict=True):
        score = float(d.score ** (1.0 - score_weight) * max(prob, 0.0) ** score_weight)
        out.append(Detection(d.box, SIGN_IDS[cls], score))
    return out


def load_sign_reader(path: str | Path) -> SignReader:
    from towndrive.agent.perception.checkpoints import load_checkpoint

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Sign reader checkpoint {path} not found; train one with "
                                "`python train.py detector signs`.")
    ckpt = load_checkpoint(path, "sign reader")
    if tuple(ckpt.get("classes", ())) != SIGN_CLASSES:
        raise ValueError(f"{path} reads the signs {ckpt.get('classes')}, not {SIGN_CLASSES}; retrain it.")
    model = SignReader(SignReaderConfig(**ckpt.get("config", {})))
    model.load_state_dict(ckpt["state_dict"])
    return model.eval()


def torch_read(path: str | Path) -> Read:
    from towndrive.agent.perception.checkpoints import numpy_forward

    model = load_sign_reader(path)
    return Read(numpy_forward(model), model.config)


def onnx_read(path: str | Path, threads: int = 0) -> Read:
    """The exported sign reader through ONNX Runtime; its config travels in the ONNX file's metadata."""
    from towndrive.agent.perception.onnx_runtime import second_stage_session

    run, config = second_stage_session(path, threads, "sign reader", "sign_reader_config")
    return Read(run, SignReaderConfig(**config))
