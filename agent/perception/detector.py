"""A small one-stage YOLO-style detector in plain PyTorch, its decoding, NMS and ONNX Runtime inference.

Why this shape: the camera is 320x160 and the CPU must run it in well under 15 ms, so the backbone is a
plain stack of 3x3 conv-BN-ReLU layers (what ONNX Runtime's CPU kernels run fastest) down to stride 16,
with a top-down path that brings stride-16 context to the stride-8 map, where the small things live
(a pedestrian at 40 m is 2x7 pixels, a traffic light 3x8). Optionally (``DetectorConfig.strides`` =
``(4, 8, 16)``) the top-down path goes on to the stride-4 map with a third head: pedestrians 2-4 px wide
are placed too coarsely from stride-8 cells to reach IoU 0.5 (their predicted widths were 1.3x too large).
The anchor-free grid heads predict per cell:
objectness, one score per class and a box (centre offset in cells as in YOLOv5, ``2 sigmoid - 0.5``, and
width and height as ``exp`` times the stride). Scores are ``objectness x class probability``. NMS is
OpenCV's ``NMSBoxesBatched`` within class groups (car and truck share one, the three light states
another, the road signs a third), so one object is never reported both as a red and a green light, or as a
30 and a 50 limit.

The ONNX model contains the decoding: its one output is ``N x cells x (4 + 1 + classes)`` with boxes in
pixels (x0, y0, x1, y1), so ONNX Runtime's caller only has to threshold and run NMS.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from towndrive.agent.perception.classes import CLASSES, SIGN_CLASSES, classes_of_model
from towndrive.agent.perception.detections import Detection, box_iou, nms_numpy  # noqa: F401 (re-exported)

if TYPE_CHECKING:
    from towndrive.agent.perception.ped_refiner import Refine
    from towndrive.agent.perception.sign_reader import Read

STRIDES = (8, 16)  # the default (and every checkpoint without "strides" in its config); (4, 8, 16) adds a stride-4 head
INPUT_HW = (160, 320)
# Class groups for NMS: the same object cannot be two classes of one group.
NMS_GROUP = {"car": 0, "truck": 0, "pedestrian": 1, "light_red": 2, "light_yellow": 2, "light_green": 2,
             "stop_sign": 3, "yield_sign": 3, "speed_limit_30": 3, "speed_limit_50": 3}


def conv(c_in: int, c_out: int, stride: int = 1, k: int = 3) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, k, stride, k // 2, bias=False), nn.BatchNorm2d(c_out),
                         nn.ReLU(inplace=True))


class Residual(nn.Module):
    """Two 3x3 convs with a skip: depth without the vanishing gradients of a plain stack."""

    def __init__(self, c: int) -> None:
        super().__init__()
        self.body = nn.Sequential(conv(c, c), nn.Conv2d(c, c, 3, 1, 1, bias=False), nn.BatchNorm2d(c))
        self.act = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(x + self.body(x))


@dataclass(frozen=True)
class DetectorConfig:
    width: int = 32  # channels at stride 4; doubled at each stride
    num_classes: int = len(CLASSES)
    strides: tuple[int, ...] = STRIDES  # (8, 16), or (4, 8, 16) with a head on the stride-4 map for small objects
    s4_blocks: int = 0  # residual blocks on the stride-4 path before its head (0: the first stride-4 model)
    s4_pixels: bool = False  # add the raw pixels of each 4x4 cell (space-to-depth, 1x1 conv) to the stride-4 path

    def __post_init__(self) -> None:
        object.__setattr__(self, "strides", tuple(int(s) for s in self.strides))
        if self.strides not in ((8, 16), (4, 8, 16)):
            raise ValueError(f"Detector strides must be (8, 16) or (4, 8, 16), not {self.strides}.")
        if self.s4_blocks and 4 not in self.strides:
            raise ValueError("s4_blocks needs the stride-4 head (strides 4, 8, 16).")
        if self.s4_pixels and 4 not in self.strides:
            raise ValueError("s4_pixels needs the stride-4 head (strides 4, 8, 16).")


class Detector(nn.Module):
    """Input: float RGB N x 3 x 160 x 320 in [0, 1]. ``forward`` returns raw head maps; ``decode`` boxes."""

    def __init__(self, config: DetectorConfig | None = None) -> None:
        super().__init__()
        self.config = config or DetectorConfig()
        c = self.config.width
        nc = self.config.num_classes
        self.stem = nn.Sequential(conv(3, c // 2, 2), conv(c // 2, c, 2))  # stride 4
        self.s8 = nn.Sequential(conv(c, 2 * c, 2), Residual(2 * c))
        self.s16 = nn.Sequential(conv(2 * c, 4 * c, 2), Residual(4 * c))
        self.lateral = conv(4 * c, 2 * c, k=1)
        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        self.fuse8 = nn.Sequential(conv(4 * c, 2 * c, k=1), conv(2 * c, 2 * c))
        self.head8 = nn.Conv2d(2 * c, 5 + nc, 1)
        self.head16 = nn.Conv2d(4 * c, 5 + nc, 1)
        if 4 in self.config.strides:
            # Stride 4: pedestrians 2-4 px wide need finer cells than stride 8 to be placed within IoU 0.5.
            self.lateral4 = conv(2 * c, c, k=1)
            self.fuse4 = conv(c, c)  # on f4 + upsampled p8 (FPN's sum: the stride-4 map is costly per layer)
            # Optional depth at stride 4: f4 is only two convs from the pixels, and p8 arrives upsampled
            # (constant over 2x2), so a 3 px pedestrian's edges are placed by very shallow features.
            self.refine4 = nn.Sequential(*(Residual(c) for _ in range(self.config.s4_blocks)))
            if self.config.s4_pixels:
                # The 48 pixel values of each 4x4 cell, projected: which of a cell's four columns a 2 px wide
                # pedestrian fills is what IoU 0.5 needs, and two strided convs blur it (YOLOv5's "Focus" idea).
                self.pixels4 = nn.Sequential(nn.PixelUnshuffle(4), nn.Conv2d(48, c, 1, bias=False), nn.BatchNorm2d(c))
            self.head4 = nn.Conv2d(c, 5 + nc, 1)
        self._init_bias()

    def heads(self) -> list[nn.Conv2d]:
        """The head convolutions in the order of ``config.strides``."""
        return ([self.head4] if 4 in self.config.strides else []) + [self.head8, self.head16]

    def _init_bias(self) -> None:
        """Objectness starts near 0.01 and classes near 0.05 (RetinaNet's prior), so early losses are sane.
        The stride-4 refinement blocks start as the identity (last BN's scale 0) and the pixel projection as
        zero, so weights of a model without them (``train.py detector train --init``) give the same outputs
        before training."""
        for block in getattr(self, "refine4", []):
            nn.init.zeros_(block.body[-1].weight)
        if hasattr(self, "pixels4"):
            nn.init.zeros_(self.pixels4[-1].weight)
        for head in self.heads():
            with torch.no_grad():
                head.bias.zero_()
                head.bias[4] = -4.6
                head.bias[5:] = -3.0

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        f4 = self.stem(x)
        f8 = self.s8(f4)
        f16 = self.s16(f8)
        p8 = self.fuse8(torch.cat([f8, self.up(self.lateral(f16))], 1))
        out = [self.head8(p8), self.head16(f16)]
        if 4 in self.config.strides:
            p4 = self.fuse4(f4 + self.up(self.lateral4(p8)))
            if self.config.s4_pixels:
                p4 = p4 + self.pixels4(x)
            p4 = self.refine4(p4)
            out.insert(0, self.head4(p4))
        return out


def grids(height: int = INPUT_HW[0], width: int = INPUT_HW[1],
          strides: tuple[int, ...] = STRIDES) -> list[tuple[np.ndarray, int]]:
    """Per stride: cell (col, row) coordinates, flattened in the head's row-major order."""
    out = []
    for s in strides:
        gy, gx = np.meshgrid(np.arange(height // s), np.arange(width // s), indexing="ij")
        out.append((np.stack([gx.ravel(), gy.ravel()], 1).astype(np.float32), s))
    return out


def decode(maps: list[torch.Tensor], strides: tuple[int, ...] = STRIDES) -> torch.Tensor:
    """Raw head maps -> N x cells x (x0, y0, x1, y1, objectness, class probabilities...), boxes in pixels."""
    outs = []
    for m, stride in zip(maps, strides, strict=True):
        n, ch, h, w = m.shape
        t = m.permute(0, 2, 3, 1).reshape(n, h * w, ch)
        gy, gx = torch.meshgrid(torch.arange(h, dtype=m.dtype, device=m.device),
                                torch.arange(w, dtype=m.dtype, device=m.device), indexing="ij")
        grid = torch.stack([gx.reshape(-1), gy.reshape(-1)], 1)
        xy = (torch.sigmoid(t[..., :2]) * 2 - 0.5 + grid) * stride
        wh = torch.exp(t[..., 2:4].clamp(-6, 6)) * stride
        boxes = torch.cat([xy - wh / 2, xy + wh / 2], -1)
        outs.append(torch.cat([boxes, torch.sigmoid(t[..., 4:])], -1))
    return torch.cat(outs, 1)


class DecodedDetector(nn.Module):
    """Network plus decoding, as exported to ONNX: uint8-free float input, one output tensor."""

    def __init__(self, net: Detector) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return decode(self.net(x), self.net.config.strides)


# --------------------------------------------------------------------------- post-processing
def postprocess(pred: np.ndarray, score_threshold: float = 0.3, iou_threshold: float = 0.5,
                max_detections: int = 100, classes: tuple[int, ...] | None = None) -> list[Detection]:
    """One image's decoded cells (cells x (4 + 1 + C)) -> detections after per-group NMS (OpenCV). ``classes``:
    only these (NMS runs within class groups, so their boxes are those of the full call). C may be fewer than
    ``CLASSES`` (a detector trained before the signs were appended has six): its classes are the first C."""
    import cv2

    classes_of_model(pred.shape[1] - 5)
    obj = pred[:, 4:5]
    scores_all = obj * pred[:, 5:]
    cls = scores_all.argmax(1)
    score = scores_all[np.arange(len(cls)), cls]
    wanted = score >= score_threshold
    if classes is not None:
        wanted &= np.isin(cls, classes)
    keep = np.flatnonzero(wanted)
    if len(keep) == 0:
        return []
    if len(keep) > 2000:
        keep = keep[np.argsort(-score[keep])[:2000]]
    boxes = pred[keep, :4]
    xywh = np.stack([boxes[:, 0], boxes[:, 1], boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]], 1)
    groups = np.array([NMS_GROUP[CLASSES[c]] for c in cls[keep]], np.int32)
    idx = cv2.dnn.NMSBoxesBatched(xywh.tolist(), score[keep].astype(float).tolist(), groups.tolist(),
                                  float(score_threshold), float(iou_threshold))
    idx = np.asarray(idx, dtype=np.int64).reshape(-1)
    idx = idx[np.argsort(-score[keep][idx])][:max_detections]
    return [Detection(tuple(float(v) for v in boxes[i]), int(cls[keep][i]), float(score[keep][i])) for i in idx]


def to_input(rgb: np.ndarray) -> np.ndarray:
    """uint8 H x W x 3 RGB (160 x 320) -> float32 1 x 3 x H x W in [0, 1]."""
    if rgb.shape != (*INPUT_HW, 3):
        raise ValueError(f"The detector takes {INPUT_HW[1]}x{INPUT_HW[0]} RGB frames; got shape {rgb.shape}. "
                         "Use the default CameraConfig (320x160) or resize the frame.")
    return np.ascontiguousarray(rgb.transpose(2, 0, 1)[None], dtype=np.float32) / np.float32(255.0)


# --------------------------------------------------------------------------- checkpoints and inference
def load_detector(path: str | Path) -> Detector:
    """A trained detector from a checkpoint written by ``train.py detector train``."""
    from towndrive.agent.perception.checkpoints import load_checkpoint

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Detector checkpoint {path} not found; train one with `python train.py detector train`.")
    ckpt = load_checkpoint(path, "detector")
    classes = tuple(ckpt.get("classes", ()))
    # A model of fewer classes than today's is one of before the road signs (the list only ever grows at its end):
    # it loads, with its own channels, and simply reports none of the later classes.
    if not classes or classes != CLASSES[:len(classes)]:
        raise ValueError(f"{path} was trained for classes {ckpt.get('classes')}, not {CLASSES}; retrain it.")
    config = {**ckpt.get("config", {}), "num_classes": len(classes)}
    model = Detector(DetectorConfig(**config))  # no "strides" in the config: (8, 16)
    model.load_state_dict(ckpt["state_dict"])
    return model.eval()


def detect_only_classes(raw: np.ndarray, rgb: np.ndarray, score_threshold: float, refine: Refine | None,
                        names: tuple[str, ...], read: Read | None = None) -> list[Detection]:
    """The detections of the classes ``names`` alone, as ``detect_and_refine`` gives them: without pedestrians
    the refiner (which only re-places and re-scores pedestrian boxes) has nothing to do and is not run, and without
    signs neither is the sign reader. The mirror look reads only vehicles."""
    if "pedestrian" in names or (read is not None and any(n in SIGN_CLASSES for n in names)):
        wanted = refine if "pedestrian" in names else None
        return [d for d in detect_and_refine(raw, rgb, score_threshold, wanted, read) if d.name in names]
    return postprocess(raw, score_threshold, classes=tuple(CLASSES.index(n) for n in names))


def detect_and_refine(raw: np.ndarray, rgb: np.ndarray, score_threshold: float,
                      refine: Refine | None, read: Read | None = None) -> list[Detection]:
    """Post-processing, then the sign reader and the pedestrian refiner if there are any (each sees candidates
    down to its own threshold, since its re-scoring can lift a sign or a pedestrian the detector alone scored too
    low)."""
    if read is not None and raw.shape[1] - 5 <= CLASSES.index(SIGN_CLASSES[0]):
        read = None  # a model of before the signs has no sign boxes to read
    if refine is None and read is None:
        return postprocess(raw, score_threshold)
    low = score_threshold
    for stage in (refine, read):
        if stage is not None:
            low = min(low, stage.config.lowest_candidate(score_threshold))
    dets = postprocess(raw, low)
    if read is not None:
        dets = read(rgb, dets, score_threshold)  # signs read and thresholded; the rest passed on as they were
    if refine is not None:
        return refine(rgb, dets, score_threshold)
    return [d for d in dets if d.score >= score_threshold]


class TorchDetector:
    """Frames in, detections out, with torch; ``refiner``: a pedestrian refiner checkpoint (agent/perception/ped_refiner.py)."""

    def __init__(self, path: str | Path = "data/models/detector.pt", score_threshold: float = 0.3,
                 refiner: str | Path | None = None, signs: str | Path | None = None) -> None:
        from towndrive.agent.perception.ped_refiner import torch_refine
        from towndrive.agent.perception.sign_reader import torch_read

        self.model = DecodedDetector(load_detector(path)).eval()
        self.score_threshold = score_threshold
        self.refine = torch_refine(refiner) if refiner else None
        self.read = torch_read(signs) if signs else None

    def raw(self, rgb: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return self.model(torch.from_numpy(to_input(rgb)))[0].numpy()

    def __call__(self, rgb: np.ndarray) -> list[Detection]:
        return detect_and_refine(self.raw(rgb), rgb, self.score_threshold, self.refine, self.read)

    def detect_only(self, rgb: np.ndarray, names: tuple[str, ...]) -> list[Detection]:
        """``detect_only_classes`` with this detector."""
        return detect_only_classes(self.raw(rgb), rgb, self.score_threshold, self.refine, names, self.read)


class OnnxDetector:
    """Frames in, detections out, through ONNX Runtime (the deployment path); ``refiner``: an exported
    pedestrian refiner (.onnx), run after the detector. Two threads may call it at once (ONNX Runtime's
    ``run`` is thread-safe and nothing else here keeps state)."""

    thread_safe = True

    def __init__(self, path: str | Path = "data/models/detector.onnx", score_threshold: float = 0.3,
                 threads: int = 0, refiner: str | Path | None = None, signs: str | Path | None = None) -> None:
        from towndrive.agent.perception.onnx_runtime import onnx_session
        from towndrive.agent.perception.ped_refiner import onnx_refine
        from towndrive.agent.perception.sign_reader import onnx_read

        self.session = onnx_session(path, threads, role="detector")
        self.input_name = self.session.get_inputs()[0].name
        self.score_threshold = score_threshold
        self.refine = onnx_refine(refiner, threads) if refiner else None
        self.read = onnx_read(signs, threads) if signs else None

    def raw(self, rgb: np.ndarray) -> np.ndarray:
        return self.session.run(None, {self.input_name: to_input(rgb)})[0][0]

    def __call__(self, rgb: np.ndarray) -> list[Detection]:
        return detect_and_refine(self.raw(rgb), rgb, self.score_threshold, self.refine, self.read)

    def detect_only(self, rgb: np.ndarray, names: tuple[str, ...]) -> list[Detection]:
        """``detect_only_classes`` with this detector."""
        return detect_only_classes(self.raw(rgb), rgb, self.score_threshold, self.refine, names, self.read)
