"""A detection box and the greedy NMS on boxes: what the detector gives and the refiner and tracker take.

Why a module of its own: the detector and the pedestrian refiner both speak of detections; with the type here,
neither has to import the other to name it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from towndrive.agent.perception.classes import CLASSES
from towndrive.agent.perception.tracking import iou_matrix as box_iou  # one IoU for NMS, evaluation and tracking


@dataclass(frozen=True)
class Detection:
    box: tuple[float, float, float, float]  # x0, y0, x1, y1 in pixels
    cls: int
    score: float

    @property
    def name(self) -> str:
        return CLASSES[self.cls]


def nms_numpy(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Greedy NMS in numpy (the reference the OpenCV path is tested against); returns kept indices."""
    order = np.argsort(-scores)
    keep = []
    while len(order):
        i = order[0]
        keep.append(i)
        rest = order[1:]
        iou = box_iou(boxes[i:i + 1], boxes[rest])[0]
        order = rest[iou <= iou_threshold]
    return np.array(keep, dtype=np.int64)
