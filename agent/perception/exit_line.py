"""The road turned into, read during a junction turn: where its centre line lies and which way it runs.

Why: a junction turn's arc is placed before the turn, from the stop bar, the zebra beyond it and the road design's
priors, but where the lane turned into lies also depends on the cross street's lane count, which the camera does
not see before the turn (the street's far side is hidden or too far to resolve). Once the car has turned 20 degrees
(a right turn; a left turn's wider arc some 50), the camera looks down the road turned into and its centre line,
the yellow boundary between its two directions, is in view 8-25 m ahead; the corner camera on the turn's side,
turned out towards that road, sees it from the turn's start (``ExitLine.seen_from`` carries a line it reads into the
forward camera's ground frame). Where that line lies places the lane
turned into whatever the count: the inner lane is half a lane width to its right, in the direction of travel
(``junction.JunctionGuidance``).

Yellow paint is found by the lane finder's own thresholds (``lanes.lane_masks``: hue, saturation and brightness
above the local road, so it works at night as at noon) in a wide bird's-eye view, and the line is the straightest
dense band of it within a window around the direction the junction's geometry expects. Only a line long enough to
have a direction counts, and only one with road on both sides: at dusk the low sun lights white paint orange, and a
zebra's stripes (side by side, a metre apart) line up into a band as dense as the centre line; the centre line has
no paint of its colour within a metre or so beside it, a zebra has as much as on the band itself. The line is the
band's longest stretch without a gap, and it must be longer than a zebra's stripe: a single stripe lit orange with a
fleck of paint metres beyond it on its bearing spans as much as a line but is none. Nothing is guessed.

The white line a lane to the centre line's right (in the direction of travel) tells the street's lane count, which
a right turn's kerb lane depends on: beside a single lane it is the solid edge line, between two lanes the dashed
divider (``ExitLine.divider_fill``, the share of it painted over the length in view). It is found in white paint
by a square top-hat (the lane finder's runs across the view only, and the road turned into runs any way across it),
and only over 6 m or more in view: a dash and its gap are 9 m, so a dashed line is painted over half of any 6 m at
most, a solid one over nearly all.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from towndrive.agent.perception.lanes import BirdsEye, BirdsEyeConfig, ThresholdConfig, lane_masks, white_any_direction
from towndrive.sim.spec import ROAD, CameraConfig


@dataclass(frozen=True)
class ExitLineConfig:
    view: BirdsEyeConfig = field(default_factory=lambda: BirdsEyeConfig(
        x_min_m=-20.0, x_max_m=20.0, z_min_m=3.0, z_max_m=25.0, px_per_m_x=10.0, px_per_m_z=10.0))
    thresholds: ThresholdConfig = field(default_factory=ThresholdConfig)
    window_deg: float = 20.0  # the line's direction is searched this far either side of the expected one
    step_deg: float = 1.0
    bin_m: float = 0.25  # paint is binned across the candidate direction at this spacing
    inlier_m: float = 0.4  # paint this near the best line is its own (the double line's pair and its blur)
    min_pixels: int = 60  # bird's-eye pixels of paint on the line (about 2 m of a double line)
    # the paint must span this much along the line without a gap over ``max_gap_m``: longer than a zebra's stripes
    # (``RoadDesign.crosswalk_depth_m``), which at dusk the low sun can light as orange as the centre line
    min_length_m: float = ROAD.crosswalk_depth_m + 1.0
    max_gap_m: float = 1.0
    # paint beside the line (from ``inlier_m`` to this far across it, along its span) ...
    side_m: float = 1.5
    side_max_share: float = 0.5  # ... at most this share of the line's own: else it is a patch (a zebra), not a line
    # The white line a lane to the centre line's right (in the direction of travel), looked for this far from it:
    # a lane width less an edge line's set-in, to a wide lane's width.
    divider_min_m: float = 2.2
    divider_max_m: float = 4.4
    divider_bin_m: float = 0.5  # its length seen is counted in steps of this
    # at least this much of it in view: 3 m dashes and 6 m gaps (US practice 10 ft and 30 ft) paint at most half
    divider_min_span_m: float = 6.0


@dataclass(frozen=True)
class ExitLine:
    """A straight centre line on the road plane, in the camera's ground frame (x right, z ahead, metres)."""

    point: tuple[float, float]  # the middle of its paint
    direction_rad: float  # the way it runs, from the camera's forward axis (positive right)
    n_pixels: int
    length_m: float  # how much of it was in view
    # The share of the white line a lane to its right that is painted, over the length of that line in view: a
    # single lane's edge line is solid (about 1), the divider between two lanes dashed (about a third to a half);
    # None when no such line was found or less than ``divider_min_span_m`` of it was in view.
    divider_fill: float | None = None

    def seen_from(self, x_m: float, z_m: float, yaw_rad: float) -> ExitLine:
        """This line, read by a camera standing at (``x_m``, ``z_m``) in another camera's ground frame and turned
        ``yaw_rad`` to the right of that camera's axis (a corner camera), in the other camera's ground frame."""
        (x, z), c, s = self.point, math.cos(yaw_rad), math.sin(yaw_rad)
        return replace(self, point=(x_m + z * s + x * c, z_m + z * c - x * s),
                       direction_rad=math.remainder(self.direction_rad + yaw_rad, 2 * math.pi))


class ExitLineFinder:
    """Finds the road turned into's centre line (module docstring) in one camera frame."""

    def __init__(self, camera: CameraConfig, config: ExitLineConfig | None = None) -> None:
        self.config = config or ExitLineConfig()
        self.birdseye = BirdsEye(camera, self.config.view)
        # the bird's-eye pixels the camera sees (the rest of the view is outside its image)
        seen = self.birdseye.warp(np.full((camera.height, camera.width), 255, np.uint8), cv2.INTER_NEAREST)
        self.in_view = cv2.erode(seen, np.ones((3, 3), np.uint8)) > 0
        # where along a line, from its middle, the divider is checked: the view's whole diagonal either way
        view = self.config.view
        reach = view.z_max_m + view.x_max_m
        self.divider_steps = np.arange(-reach, reach, self.config.divider_bin_m)

    def find(self, rgb: np.ndarray, expected_rad: float,
             corridor: tuple[float, float, float] | None = None, divider: bool = False) -> ExitLine | None:
        """The yellow line running within ``window_deg`` of ``expected_rad`` (from the camera's forward axis,
        positive right), or None when there is not enough of one. ``corridor`` (x, z, half width in metres): only
        paint within the half width of the line through (x, z) in the expected direction is looked at (where the
        line is expected to lie, so that nothing beside it, a kerb lit orange at dusk, outvotes it). ``divider``:
        also read the white line a lane to its right (``ExitLine.divider_fill``; a second top-hat of the view, so
        only where the lane count is wanted)."""
        cfg, bev = self.config, self.birdseye
        bev_rgb = bev.warp(rgb)
        yellow = lane_masks(bev_rgb, cfg.thresholds, cfg.view.px_per_m_x)["yellow"]
        rows, cols = np.nonzero(yellow)
        x, z = bev.x_of_col[cols], bev.z_of_row[rows]
        if corridor is not None:
            cx, cz, half_width = corridor
            keep = np.abs((x - cx) * math.cos(expected_rad) - (z - cz) * math.sin(expected_rad)) <= half_width
            x, z = x[keep], z[keep]
        if len(x) < cfg.min_pixels:
            return None
        best: tuple[int, float, float] | None = None  # (count, angle, offset across it)
        half = math.radians(cfg.window_deg)
        for angle in np.arange(expected_rad - half, expected_rad + half + 1e-9, math.radians(cfg.step_deg)):
            across = x * math.cos(angle) - z * math.sin(angle)  # signed distance from a line through the camera
            lo = float(across.min())
            counts = np.bincount(((across - lo) / cfg.bin_m).astype(int))
            k = int(np.argmax(counts))
            # the best bin with its two neighbours: a line straddling a bin edge counts whole
            total = int(counts[max(k - 1, 0):k + 2].sum())
            if best is None or total > best[0]:
                best = (total, float(angle), lo + (k + 0.5) * cfg.bin_m)
        assert best is not None
        _, angle, offset = best
        apart = np.abs(x * math.cos(angle) - z * math.sin(angle) - offset)  # each pixel's distance from the line
        along_all = x * math.sin(angle) + z * math.cos(angle)
        near = _longest_stretch(apart <= cfg.inlier_m, along_all, cfg.max_gap_m)
        if int(near.sum()) < cfg.min_pixels:
            return None
        first, last = float(along_all[near].min()), float(along_all[near].max())
        beside = (apart > cfg.inlier_m) & (apart <= cfg.side_m) & (along_all >= first) & (along_all <= last)
        if int(beside.sum()) > cfg.side_max_share * int(near.sum()):
            return None  # a patch of paint, not a line with road on both sides
        pts = np.stack([x[near], z[near]], axis=1)
        middle = pts.mean(axis=0)
        _, _, vt = np.linalg.svd(pts - middle, full_matrices=False)
        ax, az = vt[0]
        direction = math.atan2(ax, az)
        if math.cos(direction - angle) < 0:  # the way the search ran, not its reverse
            direction = math.atan2(-ax, -az)
        along = (pts - middle) @ np.array([math.sin(direction), math.cos(direction)])
        length = float(along.max() - along.min())
        if length < cfg.min_length_m or abs(math.remainder(direction - expected_rad, 2 * math.pi)) > half:
            return None
        fill = (self._divider_fill(white_any_direction(bev_rgb, cfg.thresholds, cfg.view.px_per_m_x),
                                   (float(middle[0]), float(middle[1])), direction) if divider else None)
        return ExitLine((float(middle[0]), float(middle[1])), direction, int(near.sum()), length, fill)

    def _divider_fill(self, white: np.ndarray, middle: tuple[float, float], direction: float) -> float | None:
        """``ExitLine.divider_fill``: the strongest white line parallel to the centre line (``middle``,
        ``direction``) between ``divider_min_m`` and ``divider_max_m`` to its right, and the share of its length in
        view that has paint on it."""
        cfg, bev = self.config, self.birdseye
        rows, cols = np.nonzero(white)
        c, s = math.cos(direction), math.sin(direction)
        dx, dz = bev.x_of_col[cols] - middle[0], bev.z_of_row[rows] - middle[1]
        right, along = dx * c - dz * s, dx * s + dz * c
        band = (right >= cfg.divider_min_m) & (right <= cfg.divider_max_m)
        if int(band.sum()) < cfg.min_pixels // 4:
            return None
        counts = np.bincount(((right[band] - cfg.divider_min_m) / cfg.bin_m).astype(int))
        k = int(np.argmax(counts))
        offset = cfg.divider_min_m + (k + 0.5) * cfg.bin_m
        on = band & (np.abs(right - offset) <= cfg.inlier_m)
        # that line's points every bin along, and which of them the camera sees
        steps = self.divider_steps
        px = middle[0] + steps * s + offset * c
        pz = middle[1] + steps * c - offset * s
        col = np.floor((px - cfg.view.x_min_m) * cfg.view.px_per_m_x).astype(int)
        row = np.floor((cfg.view.z_max_m - pz) * cfg.view.px_per_m_z).astype(int)
        h, w = self.in_view.shape
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        inside[inside] = self.in_view[row[inside], col[inside]]
        if int(inside.sum()) * cfg.divider_bin_m < cfg.divider_min_span_m:
            return None
        painted = np.zeros(len(steps), bool)
        idx = np.round((along[on] - steps[0]) / cfg.divider_bin_m).astype(int)
        painted[idx[(idx >= 0) & (idx < len(steps))]] = True
        return float((painted & inside).sum() / inside.sum())


def _longest_stretch(on_line: np.ndarray, along: np.ndarray, max_gap_m: float) -> np.ndarray:
    """Of the pixels ``on_line``, those of the stretch along it (positions ``along``) with the most of them, where
    no gap between neighbours is over ``max_gap_m``: paint in pieces far apart (a lit zebra stripe and a fleck
    beyond) is not one line, and a line cut by a car in front is as long as its longest piece in view."""
    keep = np.zeros(len(along), bool)
    idx = np.flatnonzero(on_line)
    if len(idx) == 0:
        return keep
    order = idx[np.argsort(along[idx])]
    breaks = np.flatnonzero(np.diff(along[order]) > max_gap_m) + 1
    pieces = np.split(order, breaks)
    keep[max(pieces, key=len)] = True
    return keep
