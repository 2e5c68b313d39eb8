"""Stereo depth: semi-global matching (OpenCV ``StereoSGBM``, 3-way mode) on a rectified pair, disparity to
metric depth with the rig's focal length and baseline, and one distance per detected object.

The simulator's pair is already rectified (two identical pinhole cameras side by side, parallel axes), as
a calibrated ZED's output is, so depth is ``Z = f B / d``. With ``f`` = 160 px (320 px wide, 90 degrees)
and the ZED-like 0.12 m baseline, an object 20 m away is 0.96 px of disparity: a quarter-pixel matching
error is already 5 m there, which is why the evaluation also reports a wider (0.3 m) automotive rig.

An object's distance is the median depth over the central part of its box (``core`` of its width and
height): the box's corners are mostly background, and the median ignores the few wrong matches on the
object's own textureless paint.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from sim.render import CameraConfig


@dataclass(frozen=True)
class StereoConfig:
    num_disparities: int = 48  # multiple of 16; the nearest depth measured is f B / (num - 1)
    block_size: int = 5
    uniqueness_ratio: int = 5
    speckle_window: int = 50
    speckle_range: int = 2
    disp12_max_diff: int = 1
    pre_filter_cap: int = 31
    core: float = 0.5  # share of a box's width and height whose depths count for its distance


class StereoDepth:
    """Disparity and depth from a left/right pair, and object distances."""

    def __init__(self, camera: CameraConfig | None = None, config: StereoConfig | None = None) -> None:
        self.camera = camera or CameraConfig(stereo=True)
        self.config = cfg = config or StereoConfig()
        bs = cfg.block_size
        self.matcher = cv2.StereoSGBM_create(
            minDisparity=0, numDisparities=cfg.num_disparities, blockSize=bs, P1=8 * 3 * bs * bs, P2=32 * 3 * bs * bs,
            disp12MaxDiff=cfg.disp12_max_diff, preFilterCap=cfg.pre_filter_cap, uniquenessRatio=cfg.uniqueness_ratio,
            speckleWindowSize=cfg.speckle_window, speckleRange=cfg.speckle_range, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)

    @property
    def focal_baseline(self) -> float:
        """f B in pixel metres: depth = f B / disparity."""
        return self.camera.focal_px * self.camera.stereo_baseline_m

    def disparity(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """Disparity in pixels (float32, left image's frame); <= 0 where there is no match."""
        gl = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY)
        gr = cv2.cvtColor(right, cv2.COLOR_RGB2GRAY)
        return self.matcher.compute(gl, gr).astype(np.float32) / 16.0  # SGBM returns fixed point, 4 fractional bits

    def depth(self, disparity_px: np.ndarray) -> np.ndarray:
        """Metric z-depth (float32); inf where the disparity is invalid."""
        with np.errstate(divide="ignore"):
            return np.where(disparity_px > 0, self.focal_baseline / disparity_px, np.inf).astype(np.float32)

    def object_distance(self, depth_m: np.ndarray, box: np.ndarray) -> float:
        """Median depth over the central ``core`` of a box (x0, y0, x1, y1); nan when nothing there matched."""
        x0, y0, x1, y1 = (float(v) for v in box)
        c = self.config.core
        cx, cy, hw, hh = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) * c / 2, (y1 - y0) * c / 2
        h, w = depth_m.shape
        r0, r1 = int(max(0, np.floor(cy - hh))), int(min(h, np.ceil(cy + hh) + 1))
        c0, c1 = int(max(0, np.floor(cx - hw))), int(min(w, np.ceil(cx + hw) + 1))
        patch = depth_m[r0:r1, c0:c1]
        vals = patch[np.isfinite(patch)]
        return float(np.median(vals)) if len(vals) else float("nan")

    def object_distances(self, depth_m: np.ndarray, boxes: np.ndarray) -> np.ndarray:
        return np.array([self.object_distance(depth_m, b) for b in np.asarray(boxes).reshape(-1, 4)])


def fill_invalid(disparity_px: np.ndarray) -> np.ndarray:
    """KITTI's background interpolation: along each row, an invalid pixel takes the smaller of the nearest
    valid disparities left and right of it (the farther surface), so that every pixel has an estimate."""
    d = disparity_px.astype(np.float32).copy()
    h, w = d.shape
    valid = d > 0
    cols = np.arange(w)
    for r in range(h):
        v = valid[r]
        if not v.any():
            d[r] = 0.0
            continue
        left_i = np.maximum.accumulate(np.where(v, cols, -1))
        right_i = np.minimum.accumulate(np.where(v, cols, w)[::-1])[::-1]
        lv = np.where(left_i >= 0, d[r, np.clip(left_i, 0, w - 1)], np.inf)
        rv = np.where(right_i < w, d[r, np.clip(right_i, 0, w - 1)], np.inf)
        fill = np.minimum(lv, rv)
        d[r] = np.where(v, d[r], fill)
    return d


def colorize(disparity_px: np.ndarray, max_px: float | None = None) -> np.ndarray:
    """Disparity as an RGB picture (near = warm), invalid pixels black."""
    valid = disparity_px > 0
    top = max_px if max_px is not None else (float(np.percentile(disparity_px[valid], 99)) if valid.any() else 1.0)
    norm = np.clip(disparity_px / max(top, 1e-6), 0, 1)
    img = cv2.applyColorMap((norm * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1].copy()
    img[~valid] = 0
    return img
