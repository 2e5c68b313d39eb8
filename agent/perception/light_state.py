"""Traffic-light state: the HSV colour-threshold baseline the detector's light classes are compared against.

The detector reports a light's state through its class (``light_red``, ``light_yellow``, ``light_green``).
The baseline is what the seed theses did: crop the light's box, convert to HSV and count the bright,
saturated pixels in each lamp colour's hue band; the band with the most pixels wins. It needs a box from
somewhere (the detector's, or the ground truth's as its best case) and has no notion of which lamp is lit,
only of colour, so dusk light, glow and a red car behind the housing can fool it.
"""

from __future__ import annotations

import cv2
import numpy as np

# OpenCV hue is 0..179. Lit lamps render at hue ~2 (red), ~23 (yellow) and ~67 (green).
HUE_BANDS: dict[str, tuple[tuple[int, int], ...]] = {
    "red": ((0, 9), (170, 179)),
    "yellow": ((14, 34),),
    "green": ((45, 95),),
}
MIN_SATURATION = 110
MIN_VALUE = 140
MIN_PIXELS = 2


def hsv_counts(rgb: np.ndarray, box: tuple[float, float, float, float]) -> dict[str, int]:
    """Bright, saturated pixels per lamp colour inside ``box`` (x0, y0, x1, y1) of an RGB frame."""
    h, w = rgb.shape[:2]
    x0, y0 = max(0, int(np.floor(box[0]))), max(0, int(np.floor(box[1])))
    x1, y1 = min(w, int(np.ceil(box[2]))), min(h, int(np.ceil(box[3])))
    if x1 <= x0 or y1 <= y0:
        return dict.fromkeys(HUE_BANDS, 0)
    hsv = cv2.cvtColor(np.ascontiguousarray(rgb[y0:y1, x0:x1]), cv2.COLOR_RGB2HSV)
    hue, sat, val = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    bright = (sat >= MIN_SATURATION) & (val >= MIN_VALUE)
    out = {}
    for state, bands in HUE_BANDS.items():
        in_band = np.zeros_like(bright)
        for lo, hi in bands:
            in_band |= (hue >= lo) & (hue <= hi)
        out[state] = int(np.count_nonzero(bright & in_band))
    return out


def hsv_state(rgb: np.ndarray, box: tuple[float, float, float, float]) -> str:
    """"red", "yellow", "green", or "none" when no colour has enough pixels."""
    counts = hsv_counts(rgb, box)
    state = max(counts, key=lambda k: counts[k])
    return state if counts[state] >= MIN_PIXELS else "none"
