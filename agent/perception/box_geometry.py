"""Where a detection box's object stands, from the pinhole camera model and the flat road.

Distance is the ground-plane distance of the box's bottom row through the camera intrinsics and mounting (exact
for things standing on the road, but one image row is ``z^2 / (f h)`` metres of road: 4 m at 30 m), fused with the
distance a known height gives (``f H / h_px``: a few per cent at any range, but wrong for an unusual size), each
weighted by its variance.
"""

from __future__ import annotations

import math

import numpy as np

from towndrive.agent.perception.lanes import BirdsEye, below_horizontal
from towndrive.sim.spec import CameraConfig

# Size priors (metres): typical heights, which unlike widths do not change with the viewing angle.
HEIGHT_PRIOR_M = {"car": 1.5, "truck": 2.8, "pedestrian": 1.75}
# The least depth a vehicle shows, whatever its yaw: its width (depth = L|sin| + W|cos| >= W). A vehicle wholly
# to one side of the camera axis draws its inner box edge from its far side, not from its near face.
DEPTH_PRIOR_M = {"car": 1.9, "truck": 2.3}
# Typical lengths, on the short side (a shorter length puts the inner edge nearer our path): the depth a vehicle
# shows when it stands lengthwise along the camera axis (parked at the kerb, waiting in the next lane).
LENGTH_PRIOR_M = {"car": 4.3, "truck": 6.5}
LENGTHWISE_TOLERANCE = 0.25  # a box this far (a fraction) from the lengthwise width is not judged lengthwise


def prior_height_m(kind: str) -> float:
    """The prior height of an object of ``kind`` (a kind without one is taken for a car)."""
    return HEIGHT_PRIOR_M.get(kind, HEIGHT_PRIOR_M["car"])


def at_side_edge(box: tuple[float, float, float, float] | np.ndarray, width_px: int, margin_px: float = 0.5) -> bool:
    """Whether a box touches the image's left or right edge, within ``margin_px`` (the object is leaving the view
    sideways, or is cut by its edge)."""
    return float(box[0]) <= margin_px or float(box[2]) >= width_px - 1.0 - margin_px


class BoxGeometry:
    """Where a box's object stands, from the pinhole camera model and the flat road (see module docstring)."""

    def __init__(self, camera: CameraConfig, row_sigma_px: float = 1.0, prior_sigma: float = 0.12) -> None:
        self.camera = camera
        self.k = camera.intrinsics()
        self.f = float(self.k[0, 0])
        self.birdseye = BirdsEye(camera)
        self.last_row_z_m = float(self.birdseye.ground_z_of_row(np.array([camera.height - 1.0]))[0])
        self.row_sigma = row_sigma_px
        self.prior_sigma = prior_sigma

    def cut(self, box: np.ndarray | tuple[float, ...]) -> tuple[bool, bool]:
        """Whether the box is cut off by the image's top edge (its height says nothing) and by its bottom edge
        (its bottom row is not where the object meets the road)."""
        return float(box[1]) <= 0.5, float(box[3]) >= self.camera.height - 1.5

    def distance(self, box: np.ndarray | tuple[float, ...], kind: str) -> float:
        """Forward ground distance (m) from the camera to the object's near face."""
        x0, y0, x1, y1 = (float(v) for v in box)
        z_ground = float(self.birdseye.ground_z_of_row(np.array([y1]))[0])
        height_px = y1 - y0
        z_size = self.f * prior_height_m(kind) / height_px if height_px >= 2 else math.nan
        cut_top, cut_bottom = self.cut(box)
        if cut_top:
            z_size = math.nan
        if cut_bottom and math.isfinite(z_ground):  # nearer than the last row
            return min(z_size, z_ground) if math.isfinite(z_size) else z_ground
        if not math.isfinite(z_ground) or z_ground <= 0:
            return z_size
        if not math.isfinite(z_size):
            return z_ground
        var_g, var_s = self._variances(z_ground, z_size, height_px)
        return (z_ground / var_g + z_size / var_s) / (1.0 / var_g + 1.0 / var_s)

    def _variances(self, z_ground: float, z_size: float, height_px: float) -> tuple[float, float]:
        """The variances of the two distance readings: the box's bottom row on the road (a row's error grows with
        the square of the distance) and its height against the kind's prior height."""
        var_g = (z_ground ** 2 / (self.f * self.camera.mount_height_m) * self.row_sigma) ** 2
        var_s = (z_size * self.row_sigma / height_px) ** 2 + (self.prior_sigma * z_size) ** 2
        return var_g, var_s

    def distance_sd(self, z_m: float, kind: str) -> float:
        """The standard error of ``distance`` for a whole object of ``kind`` standing ``z_m`` ahead: how far its
        reading may wander from one picture to the next while nothing moves but the camera."""
        var_g, var_s = self._variances(z_m, z_m, self.f * prior_height_m(kind) / max(z_m, 1e-6))
        return math.sqrt(1.0 / (1.0 / var_g + 1.0 / var_s))

    def height_ratio(self, box: np.ndarray | tuple[float, ...], kind: str) -> float:
        """The box's height over the height the kind's prior height would have where its bottom row meets the
        road: about 1 for a whole object standing there; nan when the box is cut at the top or bottom, or its
        bottom row is not on the road."""
        if any(self.cut(box)):
            return math.nan
        y0, y1 = float(box[1]), float(box[3])
        z = float(self.birdseye.ground_z_of_row(np.array([y1]))[0])
        if not math.isfinite(z) or z <= 0:
            return math.nan
        return z * (y1 - y0) / (self.f * prior_height_m(kind))

    def height_of_row(self, v_px: float, z_m: float) -> float:
        """Metres above the road seen at image row ``v_px`` at forward ground distance ``z_m``."""
        return self.camera.mount_height_m - z_m * math.tan(float(below_horizontal(self.camera, v_px)))

    def cut_height_ratio(self, box: np.ndarray | tuple[float, ...], kind: str) -> float:
        """For a box cut at the image's bottom edge only: the height its top row shows where the last image row
        meets the road, over the kind's prior height; nan for any other box.

        The object stands nearer than that row's distance. Its top, above the camera (as a standing person's
        head is), then shows at least its true height there, so a value well under 1 is no such object standing
        there: the one-sided form of ``height_ratio`` for what the picture cuts at the bottom."""
        cut_top, cut_bottom = self.cut(box)
        if cut_top or not cut_bottom:
            return math.nan
        if not math.isfinite(self.last_row_z_m) or self.last_row_z_m <= 0:
            return math.nan
        return self.height_of_row(float(box[1]), self.last_row_z_m) / prior_height_m(kind)

    def _inner_outer_px(self, box: np.ndarray | tuple[float, ...]) -> tuple[float, float, int]:
        """A box's inner and outer edges as pixels from the image centre on its side, and the side (1: right of the
        camera axis, -1: left, 0: across it)."""
        cx = float(self.k[0, 2])
        x0, x2 = float(box[0]), float(box[2])
        if x0 > cx:
            return x0 - cx, x2 - cx, 1
        if x2 < cx:
            return cx - x2, cx - x0, -1
        return 0.0, 0.0, 0

    def shows_outer_edge(self, box: np.ndarray | tuple[float, ...], z_m: float, kind: str) -> bool:
        """Whether the outer edge of a box wholly to one side of the camera axis can be the vehicle's near outer
        corner: the box does not touch the image's side edge, and that corner, where the narrower of the lengthwise
        and across hypotheses (``lengthwise``) puts it, falls inside the image.

        Near, a vehicle beside our path reaches past the image's side whichever way it stands, but the detector's
        box often stops short of the edge (a parked car 2.8 m ahead drew a box ending 16 pixels inside it): that
        edge is the box's, not the vehicle's, and judged by it the car seemed too narrow to stand lengthwise."""
        inner, outer, side = self._inner_outer_px(box)
        if kind not in LENGTH_PRIOR_M or side == 0 or at_side_edge(box, self.camera.width) or z_m <= 0:
            return False
        a = inner / self.f
        length, width = LENGTH_PRIOR_M[kind], DEPTH_PRIOR_M[kind]
        narrowest_px = self.f * min(a * length + width, a * width + length) / z_m
        room_px = (self.camera.width - 1.0 - float(self.k[0, 2])) if side > 0 else float(self.k[0, 2])
        return inner + narrowest_px <= room_px

    def lengthwise(self, box: np.ndarray | tuple[float, ...], z_m: float, kind: str) -> bool | None:
        """Whether a vehicle wholly to one side of the camera axis stands lengthwise along it rather than across.

        Its outer box edge comes from its near outer corner (at ``z_m``), its inner edge from its far inner corner,
        a depth D beyond. Seen lengthwise, D is its length and its lateral extent its width; seen across, the
        other way round. The box's width at ``z_m`` is then ``a D + E`` (``a``: the inner edge's ray, lateral
        metres per metre of depth; E: the lateral extent), and the two hypotheses predict ``a L + W`` and
        ``a W + L``: the nearer one wins. A yawed vehicle lies between and counts as across (the nearer inner
        edge). A box whose outer edge cannot be the vehicle's (``shows_outer_edge``) is not judged: None."""
        if not self.shows_outer_edge(box, z_m, kind):
            return None
        inner, outer, _ = self._inner_outer_px(box)
        a = inner / self.f
        apparent = (outer - inner) / self.f * z_m
        length, width = LENGTH_PRIOR_M[kind], DEPTH_PRIOR_M[kind]
        along, across = a * length + width, a * width + length
        # nearer the lengthwise prediction, and near it: a box far narrower than both (a car yawed well off our
        # axis, as one standing in a junction we turn through) fits neither and is read the safe way
        return bool(apparent < 0.5 * (along + across) and abs(apparent - along) <= LENGTHWISE_TOLERANCE * along)

    def lateral(self, u_px: float, z_m: float) -> float:
        """Metres right of the camera axis of image column ``u_px`` at forward distance ``z_m``."""
        return (u_px - float(self.k[0, 2])) * z_m / self.f
