"""Zebra-crossing detection: where the crossing beyond the stop bar begins and ends, from the camera alone.

Why: the junction (and the turn arc through it) starts where the near-side zebra ends, and how far that is
past the stop bar differs between towns (0.9 m in classic towns, 1-5.5 m where kerbs are rounded). The far
edge of the zebra is therefore the number the agent wants; the near edge comes along.

How, and why each step:

- A zebra is stripes 0.5 m wide, 0.5 m apart, 3 m long along the road. Near the car a stripe is many image
  rows tall, so the stop-line detector's vertical top-hat erases it. Here the top-hat is horizontal, and
  its width follows the image row: ``kernel_stripes`` times a stripe's width in pixels at that row's road
  distance (a few row bands, each with one kernel). A stripe is narrower than the kernel and survives; a
  stop bar spanning the lane is wider and is taken for background, so it never looks like a zebra.
- The bright mask is warped into the metric bird's-eye view (``BirdsEye``), where each row is one road
  distance. A zebra row has the lane corridor about half painted (``fill_range``) in at least
  ``min_runs`` separate pieces. Lane lines are kept out by the corridor's inset and are one narrow piece;
  dashes are one piece and lie on lane boundaries; a stop bar is erased by the top-hat.
- Zebra rows form a band ``depth_range_m`` deep. Far away one image row spans more than a bird's-eye row
  (``z^2 / (f h)`` metres of road), so the band's allowed depth and the gaps it may have grow with the
  distance.
- The corridor is the detected lane's (``lane_corridor``, shared with the stop-line detector), continued
  straight beyond where the lane lines end (the zebra lies past them); without a lane it is straight ahead.
- With ``stop_line_m`` given only a band starting ``after_bar_m`` past the bar counts.
- **The cross street's direction** (``Zebra.tilt``): a zebra's edges run parallel to the street it lies beside
  (where junctions are not square, across the car's road at the cross street's angle, not at right angles).
  Each stripe across the whole view, not only the corridor, gives its near and far ends; a line fitted to them
  (robustly, twice) over at least ``tilt_min_stripes`` stripes spanning ``tilt_min_span_m`` gives the edges'
  slope. Lane lines reach beyond the band and are left out; a stripe's ends are sharp only near the car, so the
  junction guidance takes the tilt only from near readings, and their median.
- **The bar checked against it** (``bar_checked``): approaching a turn, the zebra ahead is looked for with no bar
  given. A "bar" read inside its band is the zebra (far off its stripes run together), and where no bar is painted
  (an arm with priority) the zebra stands in for one, put where the road design puts bars before a zebra.
- Relative thresholds (contrast and ratio to the local road) keep it working from noon to dusk; at night the
  headlights' pool and the darkness can leave too little contrast, and then it reports nothing.

Distances are from the camera along the road (the bird's-eye ``z``), in metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from towndrive.agent.perception.lanes import BirdsEye, BirdsEyeConfig, LaneResult
from towndrive.agent.perception.stop_line import StopLine, lane_corridor, row_bands
from towndrive.sim.spec import ROAD, CameraConfig, RoadDesign

# Paint read as a stop bar this far or more past the near edge of a zebra read in the same frame lies inside the
# zebra's band (a bar lies before its zebra; the near edge is read within a few tenths of a metre).
BAR_IN_ZEBRA_MARGIN_M = 0.5


@dataclass(frozen=True)
class ZebraConfig:
    # Half the lane detector's lateral resolution: a stripe and a gap are still 5 columns each, and the warp and
    # the row statistics cost half as much.
    birdseye: BirdsEyeConfig = field(default_factory=lambda: BirdsEyeConfig(px_per_m_x=10.0))
    stripe_width_m: float = 0.5  # painted stripe (and gap) width across the road
    kernel_stripes: float = 1.7  # horizontal top-hat width, in stripe widths (a stop bar is several)
    kernel_bands: int = 6  # image row bands, each with one top-hat width
    min_contrast: float = 18.0  # lightness above the road, 0..255
    min_ratio: float = 1.35  # lightness / road lightness
    fill_range: tuple[float, float] = (0.25, 0.8)  # share of the corridor painted in a zebra row (ideal 0.5)
    min_runs: int = 2  # separate painted pieces across the corridor in a zebra row
    min_corridor_m: float = 1.2  # narrower corridor rows (the lines' fits crossing far out) are not judged
    depth_range_m: tuple[float, float] = (1.8, 4.2)  # how deep the band may be (stripes are 3 m long)
    gap_m: float = 0.3  # rows missing inside a band (noise, a pedestrian) that do not split it
    # used for the near edge when the band runs out of the view's near edge: the stripes' length
    nominal_depth_m: float = ROAD.crosswalk_depth_m
    corridor_half_m: float = 1.5  # half width of the corridor when no lane is known (or only one line)
    corridor_inset_m: float = 0.25  # kept clear of the lane lines
    after_bar_m: tuple[float, float] = (-1.0, 7.5)  # where the near edge may start past the stop bar (the bar
    #                                                 is erased by the top-hat, so a bar measured long is no risk)
    max_far_m: float = 29.0  # the bird's-eye view ends at 30 m
    tilt_pad_m: float = 1.5  # the stripes' ends are looked for this far beyond the band's rows
    tilt_stripe_width_m: tuple[float, float] = (0.2, 1.0)  # a stripe's width in the view (one or two merged)
    tilt_stripe_length_m: tuple[float, float] = (1.5, 4.5)  # its length along the road
    tilt_min_stripes: int = 4
    tilt_min_span_m: float = 3.0  # the stripes used span at least this across the road
    tilt_residual_m: float = 0.4  # an end farther than this from the fitted edge is left out (and the fit redone)


@dataclass
class Zebra:
    near_m: float  # camera to the zebra's near edge, along the road
    far_m: float  # camera to its far edge
    fill: float  # mean share of the corridor painted over the band
    rows: tuple[int, int] = (0, 0)  # bird's-eye rows of the band (first = farthest, one past the nearest)
    tilt: float | None = None  # dz/dx of its edges (camera ground frame): the cross street's direction; None: unsure


class ZebraDetector:
    """Finds the nearest zebra crossing across the car's lane ahead (stateless: one frame at a time)."""

    def __init__(self, camera: CameraConfig | None = None, config: ZebraConfig | None = None) -> None:
        self.camera = camera or CameraConfig()
        self.config = cfg = config or ZebraConfig()
        self.birdseye = BirdsEye(self.camera, cfg.birdseye)
        self._bands = self._kernel_bands()

    def _kernel_bands(self) -> list[tuple[int, int, np.ndarray]]:
        """(first row, one past the last, kernel) of the image row bands that see the bird's-eye patch."""
        cfg, cam = self.config, self.camera
        be = cfg.birdseye
        rows = np.arange(cam.height)
        z = self.birdseye.ground_z_of_row(rows + 0.5)
        seen = np.isfinite(z) & (z <= be.z_max_m + 2.0)
        if not seen.any():
            return []
        v_top = int(rows[seen].min())
        # Bands equal in log distance: the stripe's width in pixels halves as the distance doubles.
        z_lo, z_hi = max(float(np.nanmin(z[seen])), 0.5), be.z_max_m + 2.0
        cuts = np.geomspace(z_lo, z_hi, cfg.kernel_bands + 1)
        out = []
        for near, far in zip(cuts[:-1], cuts[1:], strict=True):
            band = np.nonzero(seen & (z >= near - 1e-9) & (z <= far + 1e-9))[0]
            if len(band) == 0:
                continue
            k = max(3, int(round(cfg.kernel_stripes * cfg.stripe_width_m * cam.focal_px / near)) | 1)
            out.append((max(v_top, int(band.min())), int(band.max()) + 1,
                        cv2.getStructuringElement(cv2.MORPH_RECT, (k, 1))))
        return out

    def bright_mask(self, rgb: np.ndarray) -> np.ndarray:
        """Camera-image mask (uint8 0/255) of paint narrower than the row's top-hat: stripes, lines, dashes."""
        out = np.zeros(rgb.shape[:2], np.uint8)
        if not self._bands:
            return out
        top = self._bands[-1][0]  # the rows above see beyond the bird's-eye view: not converted
        light = cv2.cvtColor(rgb[top:], cv2.COLOR_RGB2HLS)[..., 1]
        for v0, v1, kernel in self._bands:
            lf = light[v0 - top:v1 - top]
            bg = cv2.morphologyEx(lf, cv2.MORPH_OPEN, kernel, borderType=cv2.BORDER_REPLICATE).astype(np.int16)
            li = lf.astype(np.int16)
            cfg = self.config
            out[v0:v1] = (((li - bg) >= cfg.min_contrast) & (li >= cfg.min_ratio * bg)).astype(np.uint8) * 255
        return out

    def detect(self, rgb: np.ndarray, lanes: LaneResult | None, stop_line_m: float | None = None) -> Zebra | None:
        """The nearest zebra across the lane ahead (past the stop bar at ``stop_line_m`` if given), or None."""
        cam = self.camera
        if not (isinstance(rgb, np.ndarray) and rgb.dtype == np.uint8 and rgb.shape == (cam.height, cam.width, 3)):
            raise ValueError(f"The zebra detector takes {cam.width}x{cam.height} uint8 RGB frames (its camera's); got "
                             f"{getattr(rgb, 'dtype', type(rgb).__name__)} {getattr(rgb, 'shape', '')}.")
        cfg, be = self.config, self.birdseye
        bright = be.warp(self.bright_mask(rgb)) >= 128
        z, x = be.z_of_row, be.x_of_col
        lo, hi = self._corridor(lanes, z)
        inside = (x[None, :] >= lo[:, None]) & (x[None, :] <= hi[:, None])
        width = inside.sum(axis=1)
        paint = bright & inside
        fill = np.where(width > 0, paint.sum(axis=1) / np.maximum(width, 1), 0.0)
        runs = (np.diff(paint.astype(np.int8), axis=1) == 1).sum(axis=1) + paint[:, 0]
        # Each bird's-eye row's road span per image row: far away the image rows are coarser than the view's.
        row_span_m = z ** 2 / (cam.focal_px * cam.mount_height_m)
        wide = width / cfg.birdseye.px_per_m_x >= cfg.min_corridor_m
        rows = (fill >= cfg.fill_range[0]) & (fill <= cfg.fill_range[1]) & (runs >= cfg.min_runs) & wide
        rows = self._close_gaps(rows, np.maximum(cfg.gap_m, 1.5 * row_span_m) * cfg.birdseye.px_per_m_z)
        h = len(z)
        for r0, r1 in row_bands(rows):
            far, near = float(z[r0]) + 0.5 / cfg.birdseye.px_per_m_z, float(z[r1 - 1]) - 0.5 / cfg.birdseye.px_per_m_z
            slack = 2.0 * float(row_span_m[r0])
            clipped = r1 >= h - 1  # the band runs out of the view's near edge
            depth = far - near
            if depth > cfg.depth_range_m[1] + slack or far > cfg.max_far_m:
                continue
            if clipped:
                near = min(near, far - cfg.nominal_depth_m)
            elif depth < cfg.depth_range_m[0]:
                continue
            if stop_line_m is not None and not self.beyond_bar(near, stop_line_m):
                continue
            return Zebra(near, far, float(fill[r0:r1].mean()), (r0, r1), self._tilt(bright, r0, r1))
        return None

    def beyond_bar(self, near_m: float, stop_line_m: float) -> bool:
        """Whether a zebra whose near edge is ``near_m`` off lies where one lies past the stop bar at
        ``stop_line_m`` (``after_bar_m``)."""
        lo, hi = self.config.after_bar_m
        return lo <= near_m - stop_line_m <= hi

    def _tilt(self, bright: np.ndarray, r0: int, r1: int) -> float | None:
        """The slope dz/dx of the zebra's edges from its stripes' ends (module docstring), or None."""
        cfg, be = self.config, self.config.birdseye
        z, x = self.birdseye.z_of_row, self.birdseye.x_of_col
        pad = int(round(cfg.tilt_pad_m * be.px_per_m_z))
        a, b = max(0, r0 - pad), min(len(z), r1 + pad)
        window = bright[a:b]
        ends = []
        for c0, c1 in sorted(row_bands(window.any(axis=0))):  # runs of painted columns, left to right
            if not cfg.tilt_stripe_width_m[0] <= (c1 - c0) / be.px_per_m_x <= cfg.tilt_stripe_width_m[1]:
                continue
            rows = np.nonzero(window[:, c0:c1].any(axis=1))[0]
            if rows[0] == 0 or rows[-1] == len(window) - 1:  # runs out of the window: a lane line, not a stripe
                continue
            if not cfg.tilt_stripe_length_m[0] <= (rows[-1] - rows[0]) / be.px_per_m_z <= cfg.tilt_stripe_length_m[1]:
                continue
            ends.append((float(x[c0:c1].mean()), float(z[a + rows[-1]]), float(z[a + rows[0]])))
        if len(ends) < cfg.tilt_min_stripes:
            return None
        p = np.array(ends)
        if p[:, 0].max() - p[:, 0].min() < cfg.tilt_min_span_m:
            return None
        slopes = []
        for col in (1, 2):  # near ends, far ends
            keep = np.ones(len(p), bool)
            for _ in range(2):
                if keep.sum() < cfg.tilt_min_stripes - 1:
                    return None
                slope, icpt = np.polyfit(p[keep, 0], p[keep, col], 1)
                keep = np.abs(p[:, col] - (icpt + slope * p[:, 0])) < cfg.tilt_residual_m
            slopes.append(float(slope))
        return float(np.mean(slopes))

    def _corridor(self, lanes: LaneResult | None, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The lane corridor, continued straight beyond the end of the lane lines (the zebra lies past it)."""
        cfg = self.config
        have = lanes is not None and lanes.detected
        lo, hi = lane_corridor(lanes if have else None, z, cfg.corridor_half_m, cfg.corridor_inset_m)
        if not have or lanes is None:
            return lo, hi
        z_end = lanes.reach_m(math.inf)
        beyond = z > z_end
        if not beyond.any() or beyond.all():
            return lo, hi
        i = int(np.nonzero(~beyond)[0][0])  # rows run far to near: the farthest row still on the lines
        j = min(i + 5, len(z) - 1)  # half a metre nearer, for the direction
        dz = z[i] - z[j]
        for b in (lo, hi):
            slope = (b[i] - b[j]) / dz if dz > 0 else 0.0
            b[beyond] = b[i] + slope * (z[beyond] - z[i])
        return lo, hi

    @staticmethod
    def _close_gaps(rows: np.ndarray, max_gap_rows: np.ndarray) -> np.ndarray:
        """Fill runs of False rows no longer than the local allowance (rows, per row) between True rows."""
        out = rows.copy()
        idx = np.nonzero(rows)[0]
        if len(idx) < 2:
            return out
        for a, b in zip(idx[:-1], idx[1:], strict=True):
            if b - a > 1 and b - a - 1 <= float(max_gap_rows[a]):
                out[a:b] = True
        return out


def bar_checked(stop: StopLine | None, zebra: Zebra | None, road: RoadDesign,
                stand_in_within_m: float | None = None) -> StopLine | None:
    """The stop bar ahead checked against the nearest zebra ahead read in the same frame (``zebra``, looked for
    with no bar given). Paint read as a bar inside the zebra's band is the zebra: far off, its stripes run
    together into a band the stop-line detector takes for a bar. With ``stand_in_within_m`` (nothing governs our
    arm, so no bar is painted) and no bar read, the zebra stands in for one: the bar is put where the road design
    puts bars before a zebra's far edge (``RoadDesign.zebra_beyond_bar_m``), so a turn there is placed as from a
    bar; the design's spread between junctions is the stand-in's error. Only within that distance of the camera:
    nearer than a governed arm's light or sign is first seen, so an arm whose light or sign is still out of sight is
    not taken for one with nothing to obey."""
    if zebra is None:
        return stop
    if stop is not None and zebra.near_m + BAR_IN_ZEBRA_MARGIN_M < stop.distance_m < zebra.far_m:
        stop = None
    if stop is None and stand_in_within_m is not None:
        bar_m = zebra.far_m - road.zebra_beyond_bar_m
        if 0 < bar_m <= stand_in_within_m:
            return StopLine(bar_m, road.stop_bar_depth_m, 0.0, -1)
    return stop
