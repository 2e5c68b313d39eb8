"""Lane detection by classic computer vision (seed 000 ch. 5, seed 003 ch. 5): bird's-eye warp, colour and
gradient thresholds, sliding windows, second-order fits, the car's offset and the curvature radius in metres.

Why each piece is the way it is:

- The bird's-eye warp is a homography computed from the camera's intrinsics ``K``, its mounting height and
  pitch (``BirdsEye``), not from four hand-picked pixels, so the metric scale is exact and follows the rig.
- Thresholds run in the bird's-eye image, where a lane line has a known width in pixels. White is HLS
  lightness clearly above the local road lightness (a horizontal top-hat), yellow is an HSV hue band with
  saturation and brightness above the local road; both must sit next to a horizontal intensity gradient.
  Relative rather than absolute levels are what let one detector work at noon, dusk, overcast and night
  (a white line is L=246 at noon and L=110 at dusk, with the road at 68 and 34).
- The top-hat kernel (0.35 m) is wider than a line (0.14 m) and narrower than a zebra stripe (0.5 m) or a
  stop bar seen sideways, so crossings and stop lines do not pull the fits.
- Both lines share curvature and heading when both are found (parallel lines), which lets a solid line
  steady the fit of a dashed one that shows only two or three dashes.
- ``LaneResult.detected`` is False ("no lane") when neither line has enough evidence; nothing is guessed.
- The painted lines are not the lane's boundaries: the town (like a real road) paints its edge line and
  its centre line inside the lane and its dashed divider on the boundary (``MarkingSpec``). Each line is
  classified from the image alone, yellow or white by its paint's colour and solid or dashed by how much
  of its length has paint in the bird's-eye view, and the lane boundary is placed beyond it as the marking
  convention says (``LaneResult.centre_offset_m``, ``centre_coeffs``). ``offset_m`` and the line fits stay
  the painted lines' (the agent's path and lane-departure warning read them).

Coordinates: the ground frame is metric, origin below the camera, ``x_m`` to the right, ``z_m`` forward.
A line is ``x = a z^2 + b z + c``. Offsets are signed, positive when the car is right of the lane centre,
measured at the vehicle centre (``camera.mount_forward_m`` behind the camera), like ``World.lane_offset_m``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from towndrive.sim.spec import ROAD, CameraConfig


# --------------------------------------------------------------------------- geometry
@dataclass(frozen=True)
class BirdsEyeConfig:
    """The patch of road the bird's-eye image covers and its resolution."""

    x_min_m: float = -7.0
    x_max_m: float = 7.0
    z_min_m: float = 3.0  # the bonnet-free near edge: the lowest image row sees ~2.2 m ahead of the camera
    z_max_m: float = 30.0  # beyond this one image row spans more than 3 m of road at 320x160
    px_per_m_x: float = 20.0
    px_per_m_z: float = 10.0

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return (int(round((self.x_max_m - self.x_min_m) * self.px_per_m_x)),
                int(round((self.z_max_m - self.z_min_m) * self.px_per_m_z)))


def pitch_rotation(pitch_deg: float) -> np.ndarray:
    """The rotation from the level frame (x right, y down, z forward) into a camera pitched ``pitch_deg``
    (negative: down): y_c = y cos - z sin, z_c = y sin + z cos."""
    theta = math.radians(-pitch_deg)
    s, c = math.sin(theta), math.cos(theta)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def ground_homography(camera: CameraConfig) -> np.ndarray:
    """3x3 H mapping a road-plane point (x_m right, z_m forward, 1) below the camera to its image pixel.

    The camera sits ``mount_height_m`` above the road, pitched down by ``-pitch_deg``. In a level frame
    (x right, y down, z forward) a road point is (x, h, z); rotating by the pitch gives the camera frame,
    and ``K`` projects it.
    """
    level = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, camera.mount_height_m], [0.0, 1.0, 0.0]])  # (x, z, 1) -> (x, h, z)
    return camera.intrinsics() @ (pitch_rotation(camera.pitch_deg) @ level)


def below_horizontal(camera: CameraConfig, v: np.ndarray | float) -> np.ndarray:
    """The angle (rad) below the level horizontal of the ray through image row ``v`` (negative above the horizon)."""
    k = camera.intrinsics()
    return np.arctan((np.asarray(v, float) - k[1, 2]) / k[1, 1]) + math.radians(-camera.pitch_deg)


def horizon_row(camera: CameraConfig) -> float:
    """The image row of the level horizon."""
    k = camera.intrinsics()
    return float(k[1, 2]) - float(k[1, 1]) * math.tan(math.radians(-camera.pitch_deg))


class BirdsEye:
    """Warp between the camera image and a metric top-down view of the road plane."""

    def __init__(self, camera: CameraConfig, config: BirdsEyeConfig | None = None) -> None:
        self.camera = camera
        self.config = cfg = config or BirdsEyeConfig()
        self.size = cfg.size
        # bev pixel (u, v) -> ground (x, z): x = x_min + (u + .5)/ppx, z = z_max - (v + .5)/ppz
        self.bev_to_ground = np.array([[1.0 / cfg.px_per_m_x, 0.0, cfg.x_min_m + 0.5 / cfg.px_per_m_x],
                                       [0.0, -1.0 / cfg.px_per_m_z, cfg.z_max_m - 0.5 / cfg.px_per_m_z],
                                       [0.0, 0.0, 1.0]])
        self.ground_to_image = ground_homography(camera)
        self.bev_to_image = self.ground_to_image @ self.bev_to_ground
        self.image_to_bev = np.linalg.inv(self.bev_to_image)
        # Each bird's-eye row's forward distance, and each column's lateral position.
        w, h = self.size
        self.z_of_row = cfg.z_max_m - (np.arange(h) + 0.5) / cfg.px_per_m_z
        self.x_of_col = cfg.x_min_m + (np.arange(w) + 0.5) / cfg.px_per_m_x
        # Where the warp samples the image: a trapezoid on the road (the region of interest).
        corners = np.array([[cfg.x_min_m, cfg.z_min_m], [cfg.x_max_m, cfg.z_min_m], [cfg.x_max_m, cfg.z_max_m],
                            [cfg.x_min_m, cfg.z_max_m]])
        self.roi_polygon = self.image_of_ground(corners[:, 0], corners[:, 1])

    def warp(self, image: np.ndarray, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
        """Bird's-eye image (top row = farthest) of a camera image."""
        return cv2.warpPerspective(image, self.bev_to_image, self.size, flags=interpolation | cv2.WARP_INVERSE_MAP,
                                   borderMode=cv2.BORDER_CONSTANT)

    def image_of_ground(self, x_m: np.ndarray, z_m: np.ndarray) -> np.ndarray:
        """Image pixels (N x 2, u right, v down) of road-plane points."""
        pts = np.stack([np.asarray(x_m, float).ravel(), np.asarray(z_m, float).ravel(), np.ones(np.size(x_m))])
        uvw = self.ground_to_image @ pts
        return (uvw[:2] / uvw[2]).T

    def ground_z_of_row(self, v: np.ndarray) -> np.ndarray:
        """Forward distance of the road seen on image row ``v`` (nan at and above the horizon)."""
        below = below_horizontal(self.camera, v)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = self.camera.mount_height_m / np.tan(below)
        # z is along the level forward axis; the ground point's z in the ground frame is the same
        return np.where(below > 1e-4, z, np.nan)


# --------------------------------------------------------------------------- thresholds
@dataclass(frozen=True)
class ThresholdConfig:
    line_kernel_m: float = 0.35  # top-hat width: wider than a line, narrower than a zebra stripe
    white_min_contrast: float = 18.0  # lightness above the local road, 0..255
    white_min_ratio: float = 1.45  # lightness / local road lightness
    yellow_hue: tuple[int, int] = (8, 38)  # OpenCV hue (0..180)
    yellow_min_sat: int = 90
    yellow_min_ratio: float = 1.35  # HSV value / local road value
    yellow_background_m: float = 1.5  # width of the road background yellow is compared with
    gradient_min: float = 6.0  # |d lightness / d x| per pixel, 0..255
    gradient_ratio: float = 0.12  # ... or this share of the local road lightness, whichever is larger


def lane_masks(bev_rgb: np.ndarray, cfg: ThresholdConfig, px_per_m_x: float) -> dict[str, np.ndarray]:
    """Binary masks (uint8 0/1) of white paint, yellow paint, gradient support and their combination."""
    hls = cv2.cvtColor(bev_rgb, cv2.COLOR_RGB2HLS)
    hsv = cv2.cvtColor(bev_rgb, cv2.COLOR_RGB2HSV)
    light = hls[..., 1]
    k = max(3, int(round(cfg.line_kernel_m * px_per_m_x)) | 1)
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (k, 1))
    bg_l = cv2.morphologyEx(light, cv2.MORPH_OPEN, kernel).astype(np.float32)
    lf = light.astype(np.float32)
    white = ((lf - bg_l) >= cfg.white_min_contrast) & (lf >= cfg.white_min_ratio * bg_l)
    hue, sat, val = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    # Yellow is told apart by its hue, so its brightness is compared with a wider road background: a yellow
    # line seen at a shallow angle smears wider than the top-hat kernel in the bird's-eye view.
    kw = max(3, int(round(cfg.yellow_background_m * px_per_m_x)) | 1)
    bg_v = cv2.morphologyEx(val, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_RECT, (kw, 1))).astype(np.float32)
    yellow = ((hue >= cfg.yellow_hue[0]) & (hue <= cfg.yellow_hue[1]) & (sat >= cfg.yellow_min_sat)
              & (val.astype(np.float32) >= cfg.yellow_min_ratio * bg_v) & (val >= 30))
    gx = np.abs(cv2.Sobel(lf, cv2.CV_32F, 1, 0, ksize=3)) / 4.0
    strong = (gx >= np.maximum(cfg.gradient_min, cfg.gradient_ratio * bg_l)).astype(np.uint8)
    support = cv2.dilate(strong, cv2.getStructuringElement(cv2.MORPH_RECT, (k, 1)))
    white_u8, yellow_u8 = white.astype(np.uint8), yellow.astype(np.uint8)
    combined = (white_u8 | yellow_u8) & support
    return {"white": white_u8, "yellow": yellow_u8, "gradient": support, "combined": combined}


def white_any_direction(bev_rgb: np.ndarray, cfg: ThresholdConfig, px_per_m: float) -> np.ndarray:
    """White paint (uint8 0/1) by a square top-hat: lines running any way across the view, where ``lane_masks``'
    horizontal one finds only lines running up it (a line along the kernel is its own background)."""
    light = cv2.cvtColor(bev_rgb, cv2.COLOR_RGB2HLS)[..., 1].astype(np.float32)
    k = max(3, int(round(cfg.line_kernel_m * px_per_m)) | 1)
    bg = cv2.morphologyEx(light, cv2.MORPH_OPEN, np.ones((k, k), np.uint8))
    return (((light - bg) >= cfg.white_min_contrast) & (light >= cfg.white_min_ratio * bg)).astype(np.uint8)


# --------------------------------------------------------------------------- marking conventions
@dataclass(frozen=True)
class MarkingSpec:
    """Where each kind of line is painted relative to the lane boundary it marks.

    The numbers are the town's marking spec, ``sim/town.py`` (``generate_town``: ``line_half`` and
    ``add_markings``; lanes 3.5 m wide, lines 0.14 m wide):

    - solid white edge line: painted from 0.35 to 0.21 m inside the lane's outer edge (its middle 0.28 m in);
    - dashed white divider between same-direction lanes (3 m dashes, 6 m gaps): centred on the boundary;
    - yellow centre line: each direction paints a solid yellow line from 0.06 to 0.20 m inside its lane's
      left edge, so the road has a double yellow line (two 0.14 m lines 0.12 m apart) centred on the
      boundary between the directions. The detector's search band (0.4-0.6 m each side of the line) takes
      the paint of both, and at 320x160 the pair is one blur beyond a few metres, so a yellow fit is the
      middle of the pair: the boundary.

    A detector knows only these conventions, as a real lane-keeping system knows its country's; it never
    reads the lane model.
    """

    line_width_m: float = 0.14
    solid_white_gap_m: float = 0.21  # from a solid white line's outer side to the lane boundary
    yellow_gap_m: float = 0.06  # from one yellow line's outer side to the boundary (the pair straddles it)
    double_yellow: bool = True  # the centre line is a pair centred on the boundary (False: a single line)
    dash_m: float = 3.0
    dash_gap_m: float = 6.0  # a dashed line is centred on the boundary: paint on a third of its length
    # How a fitted line is called solid or dashed (bird's-eye rows along the fit that have paint near it):
    coverage_margin_m: float = 0.2  # paint this close to the fit counts
    coverage_z_max_m: float = 18.0  # look no farther: beyond, one image row smears over a dash gap
    coverage_min_span_m: float = 6.0  # at least two thirds of a dash period must be in view
    solid_min_coverage: float = 0.65  # between a dashed line's third (a little more, smeared) and a solid one's all
    dashed_min_coverage: float = 0.15  # less paint than a dashed line's leaves its pattern untold (a line cut
    #                                    short by a stop bar a few metres ahead: "unknown", not "dashed")
    style_memory: float = 0.6  # weight of the previous frames' coverage of the same line

    def boundary_beyond_m(self, color: str, style: str) -> float:
        """How far beyond the middle of a line (away from the lane it bounds) the lane boundary lies."""
        if color == "yellow":
            return 0.0 if self.double_yellow else self.line_width_m / 2 + self.yellow_gap_m
        if style == "solid":
            return self.line_width_m / 2 + self.solid_white_gap_m
        return 0.0  # dashed (or not known: taken as painted on the boundary)


# --------------------------------------------------------------------------- results
@dataclass
class LaneLine:
    """One lane boundary on the road plane: ``x_m = a z^2 + b z + c`` for ``z_m`` in ``z_range_m``."""

    coeffs: np.ndarray  # (a, b, c)
    z_range_m: tuple[float, float]
    confidence: float  # 0..1
    n_pixels: int
    color: str = "white"  # "white" or "yellow", by majority of its pixels
    style: str = "unknown"  # "solid", "dashed", or "unknown" (too little of it in view), from its paint coverage
    coverage: float = float("nan")  # share of its length (3-18 m ahead, smoothed over frames) with paint

    def x_at(self, z_m: np.ndarray | float) -> np.ndarray:
        return np.polyval(self.coeffs, z_m)


@dataclass
class LaneResult:
    """What the lane detector saw in one frame."""

    left: LaneLine | None
    right: LaneLine | None
    offset_m: float  # car right of the lane centre (positive), at the vehicle centre; nan when no lane
    curvature_radius_m: float  # signed: positive bends right; inf when straight; nan when no lane
    heading_rad: float  # lane direction relative to the car (positive: lane turns right of the car's axis)
    lane_width_m: float
    confidence: float
    detected: bool
    windows: list[tuple[int, int, int, int]] = field(default_factory=list)  # bird's-eye (x0, y0, x1, y1)
    used_previous: bool = False  # True when the search ran around the previous fit instead of windows
    bev: np.ndarray | None = None
    mask: np.ndarray | None = None
    # The lane itself, with its boundaries placed beyond the painted lines by the marking conventions
    # (``MarkingSpec``): the centre line x = a z^2 + b z + c, the car's offset from it (positive right, at
    # the vehicle centre, in the lane holding the car) and the boundary-to-boundary width.
    centre_offset_m: float = float("nan")
    centre_coeffs: np.ndarray | None = None
    boundary_width_m: float = float("nan")

    def reach_m(self, default: float) -> float:
        """How far ahead the farther-reaching of the lines is seen; ``default`` when neither is."""
        return max((ln.z_range_m[1] for ln in (self.left, self.right) if ln is not None), default=default)


# --------------------------------------------------------------------------- detector
@dataclass(frozen=True)
class LaneConfig:
    birdseye: BirdsEyeConfig = field(default_factory=BirdsEyeConfig)
    thresholds: ThresholdConfig = field(default_factory=ThresholdConfig)
    n_windows: int = 9
    window_margin_m: float = 0.6  # half width of a sliding window
    window_min_pixels: int = 12  # pixels that re-centre the next window
    search_margin_m: float = 0.4  # half width of the band around the previous fit
    base_search_m: tuple[float, float] = (0.4, 3.4)  # where the histogram looks for each line's foot
    min_pixels: int = 40
    min_extent_m: float = 4.0  # a line must span at least this much road ahead
    partner_min_extent_m: float = 1.5  # ... or this much (one dash) when the other line is sure
    full_extent_m: float = 14.0  # ... and earns full confidence from this span on
    max_rms_m: float = 0.2  # residual of the fit beyond which confidence drops to 0
    min_confidence: float = 0.25  # per line
    lane_width_prior_m: float = ROAD.lane_width_m  # used until both lines have been seen together
    lane_width_range_m: tuple[float, float] = (2.6, 4.4)
    smoothing: float = 0.5  # weight of the new fit in the running average
    quadratic_min_extent_m: float = 10.0  # shorter evidence gets a straight-line fit
    markings: MarkingSpec = field(default_factory=MarkingSpec)


class LaneDetector:
    """Sliding-window lane finder with search around the previous fit and temporal smoothing."""

    def __init__(self, camera: CameraConfig | None = None, config: LaneConfig | None = None) -> None:
        self.camera = camera or CameraConfig()
        self.config = config or LaneConfig()
        self.birdseye = BirdsEye(self.camera, self.config.birdseye)
        self.reset()

    def reset(self) -> None:
        """Forget the previous frames (call at the start of an episode)."""
        self._prev: tuple[LaneLine | None, LaneLine | None] = (None, None)
        self.lane_width_m = self.config.lane_width_prior_m
        self.boundary_width_m = self.config.lane_width_prior_m
        # Per side: (the line's x at the car, its smoothed paint coverage) while the same line is followed.
        self._coverage: list[tuple[float, float] | None] = [None, None]

    # ------------------------------------------------------------------ main entry
    def detect(self, rgb: np.ndarray, keep_images: bool = False) -> LaneResult:
        cfg = self.config
        bev = self.birdseye.warp(rgb)
        masks = lane_masks(bev, cfg.thresholds, cfg.birdseye.px_per_m_x)
        binary = masks["combined"]
        ys, xs = np.nonzero(binary)
        windows: list[tuple[int, int, int, int]] = []
        used_previous = False
        left_idx = right_idx = None
        prev_l, prev_r = self._prev
        if prev_l is not None and prev_r is not None:
            left_idx, right_idx = self._around_previous(xs, ys, prev_l, prev_r)
            used_previous = True
        lines = self._fit_pair(xs, ys, left_idx, right_idx, masks) if used_previous else (None, None)
        if used_previous and (lines[0] is None or lines[1] is None):
            used_previous = False
        if not used_previous:
            left_idx, right_idx, windows = self._sliding_windows(binary, xs, ys, self._prev)
            lines = self._fit_pair(xs, ys, left_idx, right_idx, masks)
        left, right = self._smooth(*lines)
        left, right = self._classify(left, right, binary)
        result = self._summarise(left, right)
        result.windows, result.used_previous = windows, used_previous
        if keep_images:
            result.bev, result.mask = bev, masks
        return result

    # ------------------------------------------------------------------ pixel selection
    def _around_previous(self, xs: np.ndarray, ys: np.ndarray, left: LaneLine,
                         right: LaneLine) -> tuple[np.ndarray, np.ndarray]:
        be = self.birdseye
        z = be.z_of_row[ys]
        x = be.x_of_col[xs]
        m = self.config.search_margin_m
        return (np.nonzero(np.abs(x - left.x_at(z)) < m)[0], np.nonzero(np.abs(x - right.x_at(z)) < m)[0])

    def _sliding_windows(self, binary: np.ndarray, xs: np.ndarray, ys: np.ndarray,
                         previous: tuple[LaneLine | None, LaneLine | None] = (None, None),
                         ) -> tuple[np.ndarray | None, np.ndarray | None, list[tuple[int, int, int, int]]]:
        """Windows stacked from the histogram's peaks upwards; until two windows have seen the line, the
        next one follows the previous frame's line direction (a slanted line, as in a lane change, leaves a
        window's width within two windows)."""
        cfg, be = self.config, self.birdseye
        h, w = binary.shape
        hist = binary[h // 2:].sum(axis=0).astype(np.float32)
        hist = np.convolve(hist, np.ones(5, np.float32), mode="same")
        ppx = cfg.birdseye.px_per_m_x
        centre_col = (0.0 - cfg.birdseye.x_min_m) * ppx
        lo, hi = cfg.base_search_m
        bases: list[int | None] = []
        for sign in (-1, 1):
            a, b = sorted((centre_col + sign * lo * ppx, centre_col + sign * hi * ppx))
            a, b = max(0, int(a)), min(w, int(b))
            seg = hist[a:b]
            bases.append(a + int(np.argmax(seg)) if len(seg) and seg.max() >= cfg.window_min_pixels else None)
        win_h = h // cfg.n_windows
        margin = int(round(cfg.window_margin_m * ppx))
        windows: list[tuple[int, int, int, int]] = []
        picked: list[np.ndarray | None] = []
        for base, prev in zip(bases, previous, strict=True):
            if base is None:
                picked.append(None)
                continue
            current = float(base)
            chosen = []
            hits: list[tuple[float, float]] = []  # (window index, line centre) of windows that saw the line
            for k in range(cfg.n_windows):
                y1 = h - k * win_h
                y0 = y1 - win_h
                x0, x1 = int(round(current)) - margin, int(round(current)) + margin
                windows.append((x0, y0, x1, y1))
                inside = np.nonzero((ys >= y0) & (ys < y1) & (xs >= x0) & (xs < x1))[0]
                chosen.append(inside)
                if len(inside) >= cfg.window_min_pixels:
                    hits.append((k, float(np.mean(xs[inside]))))
                # Next window: where the line through the last hits points (a bend leaves a window's
                # width within two windows), else straight on from the last hit.
                if len(hits) >= 2:
                    kk, cc = np.array(hits[-3:]).T
                    slope, icpt = np.polyfit(kk, cc, 1)
                    current = slope * (k + 1) + icpt
                elif prev is not None:
                    z_here, z_next = be.z_of_row[min(h - 1, y1 - 1)], be.z_of_row[max(0, y0 - 1)]
                    current = (hits[-1][1] if hits else current) + (prev.x_at(z_next) - prev.x_at(z_here)) * ppx
                elif hits:
                    current = hits[-1][1]
            picked.append(np.concatenate(chosen) if chosen else np.zeros(0, np.int64))
        return picked[0], picked[1], windows

    # ------------------------------------------------------------------ fitting
    def _line_stats(self, z: np.ndarray) -> tuple[int, float]:
        """How much a line's pixels can be trusted: 2 alone, 1 next to a sure partner line, 0 not at all;
        and a confidence from the stretch of road they cover (0..1)."""
        cfg = self.config
        if len(z) < cfg.min_pixels // 2:
            return 0, 0.0
        extent = float(np.ptp(z))
        level = 2 if extent >= cfg.min_extent_m and len(z) >= cfg.min_pixels else int(extent >= cfg.partner_min_extent_m)
        return level, min(1.0, extent / cfg.full_extent_m)

    def _fit_pair(self, xs: np.ndarray, ys: np.ndarray, left_idx: np.ndarray | None, right_idx: np.ndarray | None,
                  masks: dict[str, np.ndarray]) -> tuple[LaneLine | None, LaneLine | None]:
        cfg, be = self.config, self.birdseye
        sides: list[tuple[np.ndarray, np.ndarray, float, str] | None] = []
        levels = []
        for idx in (left_idx, right_idx):
            if idx is None or len(idx) == 0:
                sides.append(None)
                levels.append(0)
                continue
            z, x = be.z_of_row[ys[idx]], be.x_of_col[xs[idx]]
            level, extent_conf = self._line_stats(z)
            yellow = masks["yellow"][ys[idx], xs[idx]].mean() > 0.5
            sides.append((z, x, extent_conf, "yellow" if yellow else "white") if level else None)
            levels.append(level)
        if max(levels) < 2:  # a weak line is only kept beside a sure one
            sides = [None, None]
        fits: list[LaneLine | None] = [None, None]
        if sides[0] is not None and sides[1] is not None:
            # Parallel lines: shared a, b, separate offsets (least squares on both lines' pixels).
            zl, xl, cl, coll = sides[0]
            zr, xr, cr, colr = sides[1]
            z_all = np.concatenate([zl, zr])
            quad = min(np.ptp(zl), np.ptp(zr)) >= cfg.quadratic_min_extent_m or max(np.ptp(zl), np.ptp(zr)) >= 16.0
            cols = [z_all ** 2] if quad else []
            a_mat = np.column_stack(cols + [z_all, np.r_[np.ones_like(zl), np.zeros_like(zr)],
                                            np.r_[np.zeros_like(zl), np.ones_like(zr)]])
            sol, *_ = np.linalg.lstsq(a_mat, np.concatenate([xl, xr]), rcond=None)
            a, b = (sol[0], sol[1]) if quad else (0.0, sol[0])
            c_l, c_r = sol[-2], sol[-1]
            width = c_r - c_l
            # our lane: as wide as a lane and on both sides of the car (a pair followed from the last frames can
            # be the lane beside ours once the car has left it, or after a turn mistook a line for another)
            if cfg.lane_width_range_m[0] <= width <= cfg.lane_width_range_m[1] and c_l < 0.0 < c_r:
                for k, (z, x, conf, col), c in ((0, sides[0], c_l), (1, sides[1], c_r)):
                    coeffs = np.array([a, b, c])
                    rms = float(np.sqrt(np.mean((np.polyval(coeffs, z) - x) ** 2)))
                    fits[k] = self._make_line(coeffs, z, conf, rms, col, alone=False)
                if all(f is not None for f in fits):
                    return fits[0], fits[1]
            # Not a plausible lane: keep only the better-supported line.
            keep = 0 if (levels[0], len(zl) * cl) >= (levels[1], len(zr) * cr) else 1
            sides[1 - keep] = None
            fits = [None, None]
        for k, side in enumerate(sides):
            if side is None or levels[k] < 2:
                continue
            z, x, conf, col = side
            deg = 2 if np.ptp(z) >= cfg.quadratic_min_extent_m else 1
            coeffs = np.polyfit(z, x, deg)
            if deg == 1:
                coeffs = np.r_[0.0, coeffs]
            rms = float(np.sqrt(np.mean((np.polyval(coeffs, z) - x) ** 2)))
            line = self._make_line(coeffs, z, conf, rms, col)
            # A lone line must be on its own side of the car at the car.
            if line is not None and (line.x_at(0.0) < 0) == (k == 0):
                fits[k] = line
        return fits[0], fits[1]

    def _make_line(self, coeffs: np.ndarray, z: np.ndarray, extent_conf: float, rms: float, color: str,
                   alone: bool = True) -> LaneLine | None:
        """A fitted line, or None when its confidence is too low (a line fitted jointly with a sure partner
        only has to fit its own pixels well)."""
        cfg = self.config
        fit_quality = max(0.0, 1.0 - rms / cfg.max_rms_m)
        conf = extent_conf * fit_quality
        if fit_quality <= 0.0 or (alone and conf < cfg.min_confidence):
            return None
        return LaneLine(np.asarray(coeffs, float), (float(z.min()), float(z.max())), float(conf), int(len(z)), color)

    # ------------------------------------------------------------------ smoothing and summary
    def _smooth(self, left: LaneLine | None, right: LaneLine | None) -> tuple[LaneLine | None, LaneLine | None]:
        alpha = self.config.smoothing
        z_car = -self.camera.mount_forward_m
        out = []
        for new, old in zip((left, right), self._prev, strict=True):
            # only the same line is smoothed (at the car, within a third of a lane of where it was): another one
            # found afresh is taken as it is
            if new is not None and old is not None \
                    and abs(float(new.x_at(z_car)) - float(old.x_at(z_car))) < self.lane_width_m / 3:
                new = LaneLine(alpha * new.coeffs + (1 - alpha) * old.coeffs, new.z_range_m, new.confidence,
                               new.n_pixels, new.color)
            out.append(new)
        self._prev = (out[0], out[1])
        return out[0], out[1]

    def paint_coverage(self, line: LaneLine, binary: np.ndarray) -> tuple[float, float]:
        """Share of the bird's-eye rows along a line (from the near edge to the farthest paint found for it,
        at most ``coverage_z_max_m``, where the line is inside the camera image) that have paint within
        ``coverage_margin_m`` of the fit, and the stretch of road (m) those rows cover. Stopping at the
        line's own far end keeps a solid line that ends at a junction solid."""
        spec, be, bcfg = self.config.markings, self.birdseye, self.config.birdseye
        z = be.z_of_row
        rows = np.nonzero((z >= bcfg.z_min_m) & (z <= min(spec.coverage_z_max_m, line.z_range_m[1])))[0]
        x = line.x_at(z[rows])
        uv = be.image_of_ground(x, z[rows])
        seen = (uv[:, 0] >= 0) & (uv[:, 0] < self.camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < self.camera.height)
        rows, x = rows[seen], x[seen]
        if len(rows) < 2:
            return float("nan"), 0.0
        span = float(np.ptp(z[rows])) + 1.0 / bcfg.px_per_m_z
        m = int(round(spec.coverage_margin_m * bcfg.px_per_m_x))
        cols = np.round((x - bcfg.x_min_m) * bcfg.px_per_m_x - 0.5).astype(np.int64)[:, None] + np.arange(-m, m + 1)
        inside = (cols >= 0) & (cols < binary.shape[1])
        hit = (binary[rows[:, None], np.clip(cols, 0, binary.shape[1] - 1)] > 0) & inside
        return float(hit.any(axis=1).mean()), span

    def _classify(self, left: LaneLine | None, right: LaneLine | None,
                  binary: np.ndarray) -> tuple[LaneLine | None, LaneLine | None]:
        """Call each line solid or dashed from its paint coverage, smoothed over the frames that follow the
        same line (its position at the car moved less than a third of a lane)."""
        spec = self.config.markings
        z0 = -self.camera.mount_forward_m
        out: list[LaneLine | None] = []
        for k, line in enumerate((left, right)):
            if line is None:
                self._coverage[k] = None
                out.append(None)
                continue
            x_car = float(line.x_at(z0))
            cov, span = self.paint_coverage(line, binary)
            prev = self._coverage[k]
            same = prev is not None and abs(prev[0] - x_car) < self.lane_width_m / 3
            if span >= spec.coverage_min_span_m and math.isfinite(cov):
                cov = spec.style_memory * prev[1] + (1 - spec.style_memory) * cov if same and prev is not None else cov
            elif same and prev is not None:
                cov = prev[1]  # too little in view this frame: keep what was seen of this line
            else:
                cov = float("nan")
            self._coverage[k] = (x_car, cov) if math.isfinite(cov) else None
            style = ("unknown" if not math.isfinite(cov) or cov < spec.dashed_min_coverage
                     else "solid" if cov >= spec.solid_min_coverage else "dashed")
            out.append(LaneLine(line.coeffs, line.z_range_m, line.confidence, line.n_pixels, line.color, style, cov))
        return out[0], out[1]

    def _tracked_width(self, width_m: float, measured_m: float) -> float:
        """A lane width followed over frames: a plausible measurement moves it a tenth of the way."""
        lo, hi = self.config.lane_width_range_m
        return 0.9 * width_m + 0.1 * measured_m if lo <= measured_m <= hi else width_m

    def _boundary(self, line: LaneLine, sign: float) -> np.ndarray:
        """The lane boundary a line marks, as (a, b, c): the line moved ``sign`` (-1 left, +1 right) by the
        marking spec's distance, measured across the line."""
        beyond = self.config.markings.boundary_beyond_m(line.color, line.style)
        slope = float(np.polyval(np.polyder(line.coeffs), -self.camera.mount_forward_m))
        return line.coeffs + np.array([0.0, 0.0, sign * beyond * math.sqrt(1.0 + slope * slope)])

    def _lane_centre(self, left: LaneLine | None, right: LaneLine | None) -> tuple[np.ndarray, float]:
        """The centre between the boundaries the lines mark and the car's offset from it, both for the lane
        holding the car (the neighbouring lanes taken as wide as this one)."""
        z0 = -self.camera.mount_forward_m
        bl = self._boundary(left, -1.0) if left is not None else None
        br = self._boundary(right, 1.0) if right is not None else None
        if bl is not None and br is not None:
            self.boundary_width_m = self._tracked_width(self.boundary_width_m,
                                                        float(np.polyval(br, z0) - np.polyval(bl, z0)))
            centre = 0.5 * (bl + br)
        else:
            # One boundary: the centre half a lane across it (measured across the lane, so wider along the
            # car's x axis when the car is turned to the lane, as in a lane change).
            line, sign = (bl, 1.0) if bl is not None else (br, -1.0)
            assert line is not None
            slope = 2 * line[0] * z0 + line[1]
            centre = line + np.array([0.0, 0.0, sign * self.boundary_width_m / 2 * math.sqrt(1.0 + slope * slope)])
        slope = 2 * centre[0] * z0 + centre[1]
        offset = -float(np.polyval(centre, z0)) * math.cos(math.atan(slope))
        lanes_over = round(offset / self.boundary_width_m)
        offset -= lanes_over * self.boundary_width_m
        return centre + np.array([0.0, 0.0, lanes_over * self.boundary_width_m]), offset

    def _summarise(self, left: LaneLine | None, right: LaneLine | None) -> LaneResult:
        z0 = -self.camera.mount_forward_m  # the vehicle centre, behind the camera
        nan = float("nan")
        if left is None and right is None:
            return LaneResult(None, None, nan, nan, nan, self.lane_width_m, 0.0, False)
        if left is not None and right is not None:
            self.lane_width_m = self._tracked_width(self.lane_width_m, float(right.x_at(z0) - left.x_at(z0)))
            centre = 0.5 * (left.coeffs + right.coeffs)
            confidence = 0.5 * (left.confidence + right.confidence)
        elif left is not None:
            centre = left.coeffs + np.array([0.0, 0.0, self.lane_width_m / 2])
            confidence = 0.5 * left.confidence
        else:
            assert right is not None
            centre = right.coeffs - np.array([0.0, 0.0, self.lane_width_m / 2])
            confidence = 0.5 * right.confidence
        a, b, _ = centre
        slope = 2 * a * z0 + b
        heading = math.atan(slope)
        offset = -float(np.polyval(centre, z0)) * math.cos(heading)
        # The lane found need not hold the car: a lone line may bound the neighbouring lane (the car is
        # crossing the other line), and with the car turned the windows may lock onto the next lane over.
        # Report the offset from the centre of the lane the car is in, the nearest one, taking the
        # neighbouring lanes to be as wide as this one.
        offset -= round(offset / self.lane_width_m) * self.lane_width_m
        radius = math.inf if abs(a) < 1e-6 else (1 + slope ** 2) ** 1.5 / (2 * a)
        lane_centre, centre_offset = self._lane_centre(left, right)
        return LaneResult(left, right, offset, float(radius), heading, self.lane_width_m, float(confidence), True,
                          centre_offset_m=centre_offset, centre_coeffs=lane_centre, boundary_width_m=self.boundary_width_m)


# --------------------------------------------------------------------------- pictures
def draw_lanes(rgb: np.ndarray, result: LaneResult, birdseye: BirdsEye, centre: bool = True) -> np.ndarray:
    """The camera image with the lane area and lines drawn back through the homography, and (``centre``) the
    lane centre placed by the marking conventions as a dashed yellow line, up to 20 m."""
    out = rgb.copy()
    zz = np.linspace(birdseye.config.z_min_m, birdseye.config.z_max_m, 40)
    pts = {}
    for name, line, color in (("left", result.left, (255, 60, 60)), ("right", result.right, (60, 120, 255))):
        if line is None:
            continue
        z = zz[(zz >= line.z_range_m[0] - 3) & (zz <= max(line.z_range_m[1], 15.0))]
        uv = birdseye.image_of_ground(line.x_at(z), z)
        pts[name] = uv
        cv2.polylines(out, [np.round(uv).astype(np.int32)], False, color, 2, cv2.LINE_AA)
    if "left" in pts and "right" in pts:
        poly = np.round(np.concatenate([pts["left"], pts["right"][::-1]])).astype(np.int32)
        layer = out.copy()
        cv2.fillPoly(layer, [poly], (60, 220, 90))
        out = cv2.addWeighted(layer, 0.3, out, 0.7, 0)
    if centre and result.centre_coeffs is not None:  # the lane centre by the marking conventions
        z = zz[zz <= 20.0]
        uv = np.round(birdseye.image_of_ground(np.polyval(result.centre_coeffs, z), z)).astype(np.int32)
        for k in range(0, len(uv) - 1, 2):  # dashed
            cv2.line(out, tuple(uv[k]), tuple(uv[k + 1]), (255, 230, 0), 1, cv2.LINE_AA)
    return out


def draw_birdseye(result: LaneResult, birdseye: BirdsEye) -> np.ndarray:
    """Bird's-eye mask (white paint grey, yellow paint yellow), the sliding windows and the fits."""
    assert result.mask is not None
    m = result.mask
    h, w = m["combined"].shape
    out = np.zeros((h, w, 3), np.uint8)
    out[m["combined"] > 0] = (200, 200, 200)
    out[(m["combined"] > 0) & (m["yellow"] > 0)] = (230, 200, 40)
    for x0, y0, x1, y1 in result.windows:
        cv2.rectangle(out, (x0, y0), (x1, y1), (0, 200, 0), 1)
    cfg = birdseye.config
    if result.used_previous:  # the band searched around the previous fit, instead of windows
        margin = LaneConfig().search_margin_m
        for line in (result.left, result.right):
            if line is None:
                continue
            for side in (-1, 1):
                u = (line.x_at(birdseye.z_of_row) + side * margin - cfg.x_min_m) * cfg.px_per_m_x
                pts = np.stack([u, np.arange(h)], 1)
                cv2.polylines(out, [np.round(pts).astype(np.int32)], False, (0, 160, 0), 1)
    for line, color in ((result.left, (255, 60, 60)), (result.right, (60, 120, 255))):
        if line is None:
            continue
        z = birdseye.z_of_row
        u = (line.x_at(z) - cfg.x_min_m) * cfg.px_per_m_x
        pts = np.stack([u, np.arange(h)], 1)
        cv2.polylines(out, [np.round(pts).astype(np.int32)], False, color, 2)
    return out


def lane_centre_of(lanes: LaneResult, z0: float) -> np.ndarray | None:
    """The lane centre (a, b, c) holding the car: the detected lane, or its neighbour when the car is over a line."""
    if not lanes.detected:
        return None
    w = lanes.lane_width_m
    if lanes.left is not None and lanes.right is not None:
        centre = 0.5 * (lanes.left.coeffs + lanes.right.coeffs)
    elif lanes.left is not None:
        centre = lanes.left.coeffs + np.array([0.0, 0.0, w / 2])
    else:
        assert lanes.right is not None
        centre = lanes.right.coeffs - np.array([0.0, 0.0, w / 2])
    centre = np.asarray(centre, float).copy()
    at_car = float(np.polyval(centre, z0))
    centre[2] -= round(at_car / w) * w
    return centre
