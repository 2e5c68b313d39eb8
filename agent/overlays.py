"""Drawing detections on frames, for videos, sheets and the HUD.

One function, ``draw_detections``, takes the frame and the detections and, when the tracker and stereo
depth exist, their track ids and distances, so every video in the project labels objects the same way.
Frames are small (320x160), so the drawing can upscale first: text is legible at 2x.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from towndrive.agent.perception.detector import Detection

# RGB per class: vehicles blue-ish, people orange, lights in their own colour, signs magenta to white (not red:
# a red box would read as a red light).
CLASS_COLORS: dict[str, tuple[int, int, int]] = {
    "car": (60, 170, 255), "truck": (150, 110, 255), "pedestrian": (255, 150, 30),
    "light_red": (255, 40, 40), "light_yellow": (255, 220, 0), "light_green": (40, 255, 90),
    "stop_sign": (255, 60, 200), "yield_sign": (255, 170, 230), "speed_limit_30": (230, 230, 255),
    "speed_limit_50": (200, 255, 255),
}
SHORT_NAMES = {"car": "car", "truck": "truck", "pedestrian": "ped", "light_red": "red", "light_yellow": "yellow",
               "light_green": "green", "stop_sign": "STOP", "yield_sign": "yield", "speed_limit_30": "30",
               "speed_limit_50": "50"}


def draw_detections(frame: np.ndarray, detections: Sequence[Detection], scale: int = 2,
                    track_ids: Sequence[int | None] | None = None,
                    distances_m: Sequence[float | None] | None = None, show_scores: bool = True) -> np.ndarray:
    """A copy of ``frame`` (RGB), upscaled by ``scale``, with each detection's box, class and score, and its
    track id (``#7``) and distance (``12.3 m``) when given (one entry per detection; None skips it)."""
    if track_ids is not None and len(track_ids) != len(detections):
        raise ValueError(f"track_ids has {len(track_ids)} entries for {len(detections)} detections.")
    if distances_m is not None and len(distances_m) != len(detections):
        raise ValueError(f"distances_m has {len(distances_m)} entries for {len(detections)} detections.")
    out = cv2.resize(frame, (frame.shape[1] * scale, frame.shape[0] * scale), interpolation=cv2.INTER_NEAREST)
    font, font_scale = cv2.FONT_HERSHEY_SIMPLEX, 0.3 * scale
    for k, d in enumerate(detections):
        color = CLASS_COLORS.get(d.name, (255, 255, 255))
        x0, y0, x1, y1 = (int(round(v * scale)) for v in d.box)
        cv2.rectangle(out, (x0, y0), (x1, y1), color, 1, cv2.LINE_8)
        parts = [SHORT_NAMES.get(d.name, d.name)]
        if show_scores:
            parts.append(f"{d.score:.2f}")
        if track_ids is not None and track_ids[k] is not None:
            parts.append(f"#{track_ids[k]}")
        if distances_m is not None and distances_m[k] is not None:
            parts.append(f"{distances_m[k]:.1f} m")
        text = " ".join(parts)
        (tw, th), base = cv2.getTextSize(text, font, font_scale, 1)
        ty = y0 - 2 if y0 - th - 3 >= 0 else y1 + th + 2
        cv2.rectangle(out, (x0, ty - th - 1), (x0 + tw + 1, ty + base - 1), (0, 0, 0), -1)
        cv2.putText(out, text, (x0 + 1, ty - 1), font, font_scale, color, 1, cv2.LINE_AA)
    return out
