"""Which traffic light is ours: the nearest confident light box whose head hangs near the lane we came along.

Positions are turned back into the frame of the approach lane (by the heading change since the car began to
turn): as the camera swings into a turn before the stop line, the cross street's light (green while ours is red)
comes to hang over the camera axis, but not over the lane we came along. Once the stop line has been measured,
ours must also hang where the road design puts it (``RoadDesign.light_beyond_stop_line_m`` beyond the line):
the cross street's head on the near right corner hangs over our lane's edge, 12 m nearer, lit green while ours is
red. Where it hangs is told give or take the design's spread and the reading's own: a head's distance comes from
its elevation, and a post's head (3.6 m) 30 m off stands 3-4 degrees above the camera, where one image row is 4 m;
a fixed tolerance turned our own red far-corner head away as not ours while the car waited at the line, and the car
drove on into the junction once the red it had seen was forgotten. The near corner's head stands 7 degrees up,
where a row is under a metre, so the reading's share does not let it in.
A box cut by the top of the image is a light beside the car (the cross street's, seen edge-on at night):
never ours, which stands across the junction, well inside the picture.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from towndrive.agent.decision.odometry import in_approach_frame
from towndrive.agent.decision.stop_line_track import StopLineTrack, camera_to_bar_m
from towndrive.agent.perception.box_geometry import BoxGeometry
from towndrive.agent.perception.detector import Detection
from towndrive.sim.spec import ROAD, RoadDesign


@dataclass
class LightSeen:
    state: str  # "red", "yellow", "green"
    box: tuple[float, float, float, float]
    distance_m: float
    score: float
    in_view_m: float = 0.0  # nearer than this (camera to head) the head leaves the picture (``OurLight.in_view``)


BY_ELEVATION_RAD = math.radians(2.0)  # a head higher above the horizon than this is placed by its elevation


@dataclass(frozen=True)
class LightRules:
    light_score_threshold: float = 0.4
    light_max_lateral_m: float = 4.5  # our light hangs over the lane divider, within a lane of our axis
    light_line_tolerance_m: float = 5.0  # with the stop line measured, ours hangs where the design says, give or take
    light_reading_sigmas: float = 2.0  # ... and this many standard errors of the head's distance reading (one row)
    light_box_pad_px: float = 1.0  # light boxes come out about a pixel taller than the housing (measured)
    light_size_agreement: float = 0.3  # with several mounts, the head's height and its box's size agree this well
    view_margin_px: float = 4.0  # a head kept in view stays this far inside the picture's edges
    view_min_box_px: float = 8.0  # a head box at least this tall says where the head would leave the picture


class OurLight:
    """Chooses our light among the frame's light detections (module docstring)."""

    def __init__(self, geometry: BoxGeometry, rules: LightRules, road: RoadDesign = ROAD) -> None:
        self.geometry = geometry
        self.rules = rules
        self.road = road  # where signal heads hang (height, housing, distance beyond the stop line)

    def distance(self, box: tuple[float, float, float, float], height_m: float | None = None) -> float:
        """Ground distance (m) to a signal head from how far above the horizon its box's centre is (the head
        hangs at ``height_m``, the design's mast-arm height by default), or from its height in pixels when it is
        too near the horizon for that."""
        elevation = self._elevation(box)
        if elevation > BY_ELEVATION_RAD:
            return self._above_camera_m(height_m) / math.tan(elevation)
        return self.by_size(box)

    def _elevation(self, box: tuple[float, float, float, float]) -> float:
        """The box centre's angle above the horizontal (rad), through the camera's intrinsics and pitch."""
        k, f = self.geometry.k, self.geometry.f
        return math.atan((float(k[1, 2]) - 0.5 * (box[1] + box[3])) / f) + math.radians(self.geometry.camera.pitch_deg)

    def _above_camera_m(self, height_m: float | None) -> float:
        """How high a head hanging at ``height_m`` (the design's mast-arm height by default) is above the camera."""
        height = self.road.signal_head_height_m if height_m is None else height_m
        return height - self.geometry.camera.mount_height_m

    def _housing_px(self, box: tuple[float, float, float, float]) -> float:
        """The head's housing height in pixels: the box's, less its padding (at least a pixel)."""
        return max(box[3] - box[1] - self.rules.light_box_pad_px, 1.0)

    def distance_sd(self, box: tuple[float, float, float, float], height_m: float | None = None) -> float:
        """The standard error of ``distance`` from one image row (``BoxGeometry.row_sigma``) of the box's place: by
        elevation, the head's height over the camera divided by sin^2 of the elevation, times a row's angle; by
        size, the distance over the box's height in pixels."""
        geometry = self.geometry
        elevation = self._elevation(box)
        if elevation > BY_ELEVATION_RAD:
            return self._above_camera_m(height_m) / math.sin(elevation) ** 2 * geometry.row_sigma / geometry.f
        return self.by_size(box) * geometry.row_sigma / self._housing_px(box)

    def line_tolerance(self, box: tuple[float, float, float, float], height_m: float | None = None) -> float:
        """How far from where the design puts our head a box's head may stand and still be ours: the design's
        spread (``light_line_tolerance_m``) and ``light_reading_sigmas`` of the reading's (``distance_sd``)."""
        rules = self.rules
        return math.hypot(rules.light_line_tolerance_m, rules.light_reading_sigmas * self.distance_sd(box, height_m))

    def by_size(self, box: tuple[float, float, float, float]) -> float:
        """Ground distance (m) to a signal head from its housing's height in pixels."""
        return self.geometry.f * self.road.signal_housing_height_m / self._housing_px(box)

    def choose(self, lights: list[Detection], line: StopLineTrack, turned_rad: float) -> LightSeen | None:
        """Our light among ``lights``, given the tracked stop line and the heading change ``turned_rad`` since the
        car last drove along its lane; None when none qualifies.

        A design with several signal mounts (``RoadDesign.signal_mounts``) is a prior with one mode per mount: a
        box is ours if it fits one of them, with that mount's height (the distance by the head's height must then
        agree with the distance by the box's size), across the lane where that mount puts heads, and, the stop
        line measured, that far beyond it. Before the line is measured only the main mount (the scalar fields)
        can be ours: a post beside the line and the cross street's heads are told apart only by where the line is.
        """
        best = None
        rules, road = self.rules, self.road
        mounts = road.signal_mounts
        several = len(mounts) > 1
        measured = line.stop_line_measured and line.stop_line is not None
        for d in lights:
            x0, y0, x1, y1 = d.box
            if d.score < rules.light_score_threshold or y1 - y0 < 2 or y0 <= 1.0:
                continue
            size_z = self.by_size(d.box) if several else math.nan
            for k, mount in enumerate(mounts):
                if k > 0 and not measured:
                    break
                z_cam = self.distance(d.box, mount.height_m)
                if several and abs(z_cam - size_z) > rules.light_size_agreement * size_z:
                    continue
                x_cam = self.geometry.lateral(0.5 * (x0 + x1), z_cam)
                lateral, z = in_approach_frame(x_cam, z_cam, turned_rad)
                if abs(lateral - (mount.lateral_m - road.light_lateral_m)) > rules.light_max_lateral_m:
                    continue
                if measured:
                    expected = camera_to_bar_m(line) + mount.beyond_stop_line_m
                    if abs(z - expected) > self.line_tolerance(d.box, mount.height_m):
                        continue
                if best is None or z < best.distance_m:
                    best = LightSeen(d.name.removeprefix("light_"), d.box, z, d.score, self.in_view(d.box, z))
                break
        return best

    def in_view(self, box: tuple[float, float, float, float], z_m: float) -> float:
        """How near (camera to head, along the road) the car may come before this head leaves the picture by its
        top or its side (``view_margin_px`` inside). Driving straight at it, a head's angles above and beside
        the axis grow as 1 / distance; a head beside the stop line (a near-side post) leaves the 90-degree view
        before the car reaches the line, and then its change to green is never seen."""
        x0, y0, x1, y1 = box
        k, camera, margin = self.geometry.k, self.geometry.camera, self.rules.view_margin_px
        if y1 - y0 < self.rules.view_min_box_px:  # too small to tell (far off, where it does not matter)
            return 0.0
        cx, cy, f = float(k[0, 2]), float(k[1, 2]), self.geometry.f
        pitch = math.radians(camera.pitch_deg)
        # tangents of the head top's elevation above the horizontal, now and at the picture's top edge
        up = math.tan(math.atan((cy - y0) / f) + pitch)
        up_limit = math.tan(math.atan((cy - margin) / f) + pitch)
        side = max(abs(x0 - cx), abs(x1 - cx)) / f
        side_limit = (camera.width - 1.0 - margin - cx) / f
        return z_m * max(up / up_limit, side / side_limit, 0.0)
