"""Stop-line detection: a wide, short, bright bar across the lane in the bird's-eye view, and its distance.

A stop bar is a band about half a metre deep that spans the whole lane. Bright paint is found in the
camera image with a vertical top-hat (``bar_kernel_rows`` image rows: longer than the bar is tall at 3 m,
so the bar survives at every distance), then warped into the bird's-eye view, where a row is a
stop-line row when most of the lane corridor is bright in it. Zebra stripes (half the width painted),
dashes and lane lines (narrow) fail that fill test. Far away a bar is less than one image row tall, so the
depth a band may have grows with the distance (one image row spans ``z^2 / (f h)`` metres of road).
The corridor is the detected lane (so the opposite direction's stop bar, across the centre line, is
ignored); with ``require_lane`` (the default) there is no stop line without a lane, which keeps zebra
crossings and the far side's bars seen from inside a junction out, and a bar must lie near where the lane
lines end. Without a lane result the corridor is a band straight ahead of the car.
The distance is from the camera to the bar's near edge along the road, in metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from towndrive.agent.perception.lanes import BirdsEye, BirdsEyeConfig, LaneResult
from towndrive.sim.spec import CameraConfig


@dataclass(frozen=True)
class StopLineConfig:
    birdseye: BirdsEyeConfig = field(default_factory=BirdsEyeConfig)
    bar_kernel_rows: int = 11  # vertical top-hat length in image rows
    min_contrast: float = 18.0  # lightness above the road, 0..255
    min_ratio: float = 1.45  # lightness / road lightness
    min_fill: float = 0.6  # share of the corridor's width that must be bright
    depth_range_m: tuple[float, float] = (0.2, 1.4)  # how deep (along the road) the band may be
    corridor_half_m: float = 1.2  # half width of the corridor when no lane is known
    corridor_inset_m: float = 0.25  # kept clear of the lane lines
    nominal_depth_m: float = 0.5  # stop bars are 0.3-0.6 m deep; used where the band is too thin to measure
    max_distance_m: float = 20.0  # beyond this a 0.5 m bar is a fraction of an image row at 320x160
    require_lane: bool = True  # stop bars end painted lanes: without a lane in view (inside a junction) report none,
    #                            unless the bar continues one tracked from frames that had a lane (see detect)
    track_frames: int = 10  # frames a tracked bar may go unseen before it is forgotten
    beyond_lane_m: float = 6.0  # the bar may lie at most this far past the end of the detected lane lines
    own_lane_margin_m: float = 0.6  # a left line this far right of the camera, or a right line this far left of
    #                                 it, bounds another lane (see detect), not the corridor of our bar


@dataclass
class StopLine:
    distance_m: float  # camera to the near edge, along the road
    depth_m: float  # how deep the band is
    fill: float  # share of the corridor that is bright at the band
    row: int  # bird's-eye row of the near edge


def lane_corridor(lanes: LaneResult | None, z_m: np.ndarray, half_m: float,
                  inset_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Left and right bounds (x, metres) of the car's lane corridor at each forward distance ``z_m``.

    Between the two lines, ``inset_m`` clear of each, when both are known; ``half_m`` either side of the
    lane centre placed half a lane width from the one line there is; ``half_m`` either side of the camera
    without a lane. Shared by the painted-band detectors (stop bars, zebras) so they look at the same lane.
    """
    if lanes is not None and lanes.left is not None and lanes.right is not None:
        return lanes.left.x_at(z_m) + inset_m, lanes.right.x_at(z_m) - inset_m
    if lanes is not None and lanes.detected and math.isfinite(lanes.offset_m):
        line = lanes.left or lanes.right
        assert line is not None
        centre = line.x_at(z_m) + (lanes.lane_width_m / 2 if line is lanes.left else -lanes.lane_width_m / 2)
        return centre - half_m, centre + half_m
    return np.full(len(z_m), -half_m), np.full(len(z_m), half_m)


def row_bands(rows: np.ndarray) -> list[tuple[int, int]]:
    """Runs of consecutive True bird's-eye rows as (first, one past the last), nearest (bottom) first."""
    edges = np.diff(np.r_[0, rows.astype(np.int8), 0])
    starts, ends = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    return sorted(zip(starts.tolist(), ends.tolist(), strict=True), key=lambda b: -b[1])


class StopLineDetector:
    """Finds the nearest stop bar in the lane ahead."""

    def __init__(self, camera: CameraConfig | None = None, config: StopLineConfig | None = None) -> None:
        self.camera = camera or CameraConfig()
        self.config = config or StopLineConfig()
        self.birdseye = BirdsEye(self.camera, self.config.birdseye)
        self.reset()

    def reset(self) -> None:
        """Forget the tracked bar (call at the start of an episode)."""
        self._track_m: float | None = None
        self._unseen = 0

    def detect(self, rgb: np.ndarray, lanes: LaneResult | None = None, bev: np.ndarray | None = None) -> StopLine | None:
        """The nearest stop line ahead, or None. Pass the lane result if there is one.

        Close to a stop bar the lane lines ahead are only a few metres long and the lane detector may
        report no lane; a bar first found with a lane is then followed without one, as long as it keeps
        coming nearer (it cannot move away while the car drives towards it).
        """
        del bev  # the bar is found in the camera image (see the module docstring)
        cfg = self.config
        have_lane = lanes is not None and lanes.detected
        if have_lane and lanes is not None and not self._holds_car(lanes):
            # Not the lane the car is in: at night the lane detector can lock onto the oncoming lane across the
            # centre line, where no bar of ours is painted and the zebra beyond the junction's near side, which
            # spans the road, fills the corridor enough to pass for a bar beyond ours (docs/agent_rules.md).
            lanes, have_lane = None, False
        following = self._track_m is not None and self._unseen <= cfg.track_frames
        # A new bar needs both lines of the lane (a lone line is often a kerb or a zebra's edge in a turn).
        both_lines = have_lane and lanes is not None and lanes.left is not None and lanes.right is not None
        if cfg.require_lane and not both_lines and not following:
            self._track_m = None
            return None
        found = self._find(rgb, lanes if have_lane else None)
        if found is not None and cfg.require_lane and not have_lane:
            assert self._track_m is not None
            if not (self._track_m - 3.0 <= found.distance_m <= self._track_m + 1.0):
                found = None
        if found is None:
            self._unseen += 1
            if self._unseen > cfg.track_frames:
                self._track_m = None
            return None
        self._track_m, self._unseen = found.distance_m, 0
        return found

    def _holds_car(self, lanes: LaneResult) -> bool:
        """Whether the detected lines bound the lane the camera is in (within the margin, for lane changes).
        ``LaneResult.offset_m`` cannot tell: it is the offset in whichever lane holds the car."""
        m = self.config.own_lane_margin_m
        return ((lanes.left is None or float(lanes.left.x_at(0.0)) <= m)
                and (lanes.right is None or float(lanes.right.x_at(0.0)) >= -m))

    def _find(self, rgb: np.ndarray, lanes: LaneResult | None) -> StopLine | None:
        cfg, be = self.config, self.birdseye
        lane_end = lanes.reach_m(math.inf) if lanes is not None else math.inf
        light = cv2.cvtColor(rgb, cv2.COLOR_RGB2HLS)[..., 1]
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (1, cfg.bar_kernel_rows | 1))
        bg = cv2.morphologyEx(light, cv2.MORPH_OPEN, kernel).astype(np.float32)
        lf = light.astype(np.float32)
        bright_img = (((lf - bg) >= cfg.min_contrast) & (lf >= cfg.min_ratio * bg)).astype(np.uint8) * 255
        bright = be.warp(bright_img) >= 128
        h, w = bright.shape
        z = be.z_of_row
        x = be.x_of_col
        lo, hi = lane_corridor(lanes, z, cfg.corridor_half_m, cfg.corridor_inset_m)
        inside = (x[None, :] >= lo[:, None]) & (x[None, :] <= hi[:, None])
        width = inside.sum(axis=1)
        fill = np.where(width > 0, (bright & inside).sum(axis=1) / np.maximum(width, 1), 0.0)
        rows = fill >= cfg.min_fill
        for r0, r1 in row_bands(rows):
            depth_m = (r1 - r0) / cfg.birdseye.px_per_m_z
            # Far away the band is one image row smeared over a metre or more of bird's-eye rows, so its
            # lower edge is biased near; its fill-weighted centre is not. Near edge = centre - half the depth.
            centre = self._centre_z(lf - bg, float(np.average(z[r0:r1], weights=fill[r0:r1])), float(z[r0]),
                                    float(z[r1 - 1]), float(np.median(lo[r0:r1])), float(np.median(hi[r0:r1])))
            near = centre - min(depth_m, cfg.nominal_depth_m) / 2
            row_span_m = near ** 2 / (self.camera.focal_px * self.camera.mount_height_m)  # road per image row
            max_depth = max(cfg.depth_range_m[1], 2.5 * row_span_m)
            if not (cfg.depth_range_m[0] <= depth_m + 0.05 <= max_depth) or near > min(cfg.max_distance_m,
                                                                                         lane_end + cfg.beyond_lane_m):
                continue
            if r1 >= h - 1:  # touching the near edge of the view: the bar may continue below it
                continue
            return StopLine(near, depth_m, float(fill[r0:r1].mean()), int(r1 - 1))
        return None

    def _centre_z(self, contrast: np.ndarray, fallback_z: float, z_far: float, z_near: float, x_lo: float,
                  x_hi: float) -> float:
        """Distance of the bar's middle from the image rows' contrast-weighted centroid.

        A far bar covers part of one or two image rows; with an anti-aliasing camera the contrast of each
        row is proportional to how much of it the bar covers, so the centroid locates the bar to a fraction
        of a row (and with a point-sampling renderer it is no worse than the bird's-eye band).
        """
        be = self.birdseye
        uv = be.image_of_ground(np.array([x_lo, x_hi, x_lo, x_hi]), np.array([z_far, z_far, z_near, z_near]))
        v0, v1 = int(np.floor(uv[:, 1].min())), int(np.ceil(uv[:, 1].max()))  # the band's rows only: the zebra is near
        u0, u1 = int(np.floor(uv[:, 0].min())), int(np.ceil(uv[:, 0].max())) + 1
        h, w = contrast.shape
        v0, v1, u0, u1 = max(0, v0), min(h, v1 + 1), max(0, u0), min(w, u1)
        if v1 <= v0 or u1 <= u0:
            return fallback_z
        weight = np.clip(contrast[v0:v1, u0:u1], 0, None).mean(axis=1)
        weight[weight < 0.5 * weight.max()] = 0.0  # only the bar's rows, not the road's noise
        if weight.sum() <= 0:
            return fallback_z
        v_c = float(np.average(np.arange(v0, v1), weights=weight))
        z_c = float(be.ground_z_of_row(np.array([v_c]))[0])
        return z_c if np.isfinite(z_c) else fallback_z
