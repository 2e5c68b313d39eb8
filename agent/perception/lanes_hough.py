"""Canny + Hough lane finding (seed 004 ch. 3.3), kept for comparison with the sliding-window detector.

Seed 004's steps: colour masks for white and yellow paint, grayscale, blur, Canny edges, a region of
interest, probabilistic Hough segments, then the segments split by slope into a left and a right line,
averaged and extrapolated. Here the colour masks are the same relative (top-hat) masks the sliding-window
detector uses, applied in the camera image, because the seed's fixed levels (HLS L >= 210) find no white
paint at dusk or night in this simulator; the region of interest is the road trapezoid the bird's-eye view
covers. The straight image lines are mapped onto the road with the same homography, so the offset is in
metres and comparable. No curvature: a straight line has none (that is the method's known limit).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from towndrive.agent.perception.lanes import BirdsEye, BirdsEyeConfig, LaneLine, LaneResult, ThresholdConfig, lane_masks
from towndrive.sim.spec import CameraConfig


@dataclass(frozen=True)
class HoughConfig:
    birdseye: BirdsEyeConfig = field(default_factory=BirdsEyeConfig)
    thresholds: ThresholdConfig = field(default_factory=ThresholdConfig)
    image_kernel_px: float = 7.0  # top-hat width in the camera image
    canny: tuple[int, int] = (50, 150)
    hough_threshold: int = 12
    min_line_px: int = 8
    max_gap_px: int = 12
    min_abs_slope: float = 0.35  # |dv/du|: flatter segments are stop lines, crossings or kerbs far away
    lane_width_range_m: tuple[float, float] = (2.6, 4.4)
    smoothing: float = 0.5


class HoughLaneDetector:
    """Straight left and right lane lines from Hough segments."""

    def __init__(self, camera: CameraConfig | None = None, config: HoughConfig | None = None) -> None:
        self.camera = camera or CameraConfig()
        self.config = config or HoughConfig()
        self.birdseye = BirdsEye(self.camera, self.config.birdseye)
        h, w = self.camera.height, self.camera.width
        self.roi = np.zeros((h, w), np.uint8)
        cv2.fillPoly(self.roi, [np.round(self.birdseye.roi_polygon).astype(np.int32)], 255)
        self.reset()

    def reset(self) -> None:
        self._prev: list[np.ndarray | None] = [None, None]

    def segments(self, rgb: np.ndarray) -> np.ndarray:
        """Hough segments (N x 4: u0, v0, u1, v1) in the region of interest."""
        cfg = self.config
        masks = lane_masks(rgb, cfg.thresholds, cfg.image_kernel_px / cfg.thresholds.line_kernel_m)
        paint = (masks["white"] | masks["yellow"]) * 255
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        gray = cv2.bitwise_and(gray, gray, mask=cv2.dilate(paint, np.ones((3, 3), np.uint8)))
        edges = cv2.Canny(cv2.GaussianBlur(gray, (3, 3), 0), *cfg.canny)
        edges &= self.roi
        lines = cv2.HoughLinesP(edges, 1, math.pi / 180, cfg.hough_threshold, minLineLength=cfg.min_line_px,
                                maxLineGap=cfg.max_gap_px)
        return np.zeros((0, 4)) if lines is None else lines.reshape(-1, 4).astype(float)

    def detect(self, rgb: np.ndarray) -> LaneResult:
        cfg = self.config
        segs = self.segments(rgb)
        cu = self.camera.intrinsics()[0, 2]
        fits: list[np.ndarray | None] = [None, None]
        for side in (0, 1):
            pts_g: list[np.ndarray] = []
            weights: list[float] = []
            for u0, v0, u1, v1 in segs:
                if abs(v1 - v0) < cfg.min_abs_slope * abs(u1 - u0):
                    continue
                du_dv = (u1 - u0) / (v1 - v0) if v1 != v0 else 0.0
                left = du_dv < 0  # a left line leans right going up the image
                mid_left = 0.5 * (u0 + u1) < cu
                if left != (side == 0) or mid_left != left:
                    continue
                g = self._to_ground(np.array([[u0, v0], [u1, v1]]))
                if not np.all(np.isfinite(g)):
                    continue
                pts_g.append(g)
                weights.append(float(math.hypot(u1 - u0, v1 - v0)))
            if not pts_g:
                continue
            # Length-weighted average line on the road plane: x = b z + c.
            g = np.concatenate(pts_g)
            w = np.repeat(np.array(weights), 2)
            b, c = np.polyfit(g[:, 1], g[:, 0], 1, w=np.sqrt(w))
            fits[side] = np.array([0.0, b, c])
        if fits[0] is not None and fits[1] is not None:
            width = float(fits[1][2] - fits[0][2])
            if not cfg.lane_width_range_m[0] <= width <= cfg.lane_width_range_m[1]:
                fits = [None, None]
        for side in (0, 1):
            prev = self._prev[side]
            if fits[side] is not None and prev is not None:
                fits[side] = cfg.smoothing * fits[side] + (1 - cfg.smoothing) * prev
            self._prev[side] = fits[side]
        zr = (cfg.birdseye.z_min_m, cfg.birdseye.z_max_m)
        left = LaneLine(fits[0], zr, 1.0, 0) if fits[0] is not None else None
        right = LaneLine(fits[1], zr, 1.0, 0) if fits[1] is not None else None
        nan = float("nan")
        if left is None or right is None:
            return LaneResult(left, right, nan, nan, nan, nan, 0.0, False)
        z0 = -self.camera.mount_forward_m
        centre = 0.5 * (left.coeffs + right.coeffs)
        heading = math.atan(centre[1])
        offset = -float(np.polyval(centre, z0)) * math.cos(heading)
        width = float(right.x_at(z0) - left.x_at(z0))
        return LaneResult(left, right, offset, math.inf, heading, width, 1.0, True)

    def _to_ground(self, uv: np.ndarray) -> np.ndarray:
        """Image pixels -> road-plane (x, z); nan above the horizon."""
        h_inv = np.linalg.inv(self.birdseye.ground_to_image)
        p = h_inv @ np.vstack([uv.T, np.ones(len(uv))])
        with np.errstate(divide="ignore", invalid="ignore"):
            g = (p[:2] / p[2]).T
        g[g[:, 1] <= 0] = np.nan
        return g
