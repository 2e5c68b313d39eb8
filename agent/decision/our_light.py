"""Which traffic light is ours: the nearest confident light box whose head hangs near the lane we came along.

Positions are turned back into the frame of the approach lane (by the heading change since the car began to
turn): as the camera swings into a turn before the stop line, the cross street's light (green while ours is red)
comes to hang over the camera axis, but not over the lane we came along. Once the stop line has been measured,
ours must also hang where the road design puts it (``RoadDesign.light_beyond_stop_line_m`` beyond the line):
the cross street's head on the near right corner hangs over our lane's edge, 12 m nearer, lit green while ours is
red. A box cut by the top of the image is a light beside the car (the cross street's, seen edge-on at night):
never ours, which stands across the junction, well inside the picture.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from towndrive.agent.decision.priors import fused
from towndrive.agent.decision.stop_line_track import StopLineTrack
from towndrive.agent.perception.box_geometry import BoxGeometry
from towndrive.agent.perception.detector import Detection
from towndrive.sim.spec import ROAD, RoadDesign


@dataclass
class LightSeen:
    state: str  # "red", "yellow", "green"
    box: tuple[float, float, float, float]
    distance_m: float
    score: float


@dataclass(frozen=True)
class LightRules:
    light_score_threshold: float = 0.4
    light_max_lateral_m: float = 4.5  # our light hangs over the lane divider, within a lane of our axis
    light_line_tolerance_m: float = 5.0  # with the stop line measured, ours hangs where the design says, give or take
    light_box_pad_px: float = 1.0  # light boxes come out about a pixel taller than the housing (measured)


class OurLight:
    """Chooses our light among the frame's light detections (module docstring)."""

    def __init__(self, geometry: BoxGeometry, rules: LightRules, road: RoadDesign = ROAD) -> None:
        self.geometry = geometry
        self.rules = rules
        self.road = road  # where signal heads hang (height, housing, distance beyond the stop line)

    def distance(self, box: tuple[float, float, float, float]) -> float:
        """Ground distance (m) to a signal head from how far above the horizon its box's centre is (the head
        hangs at the design's height), or from its height in pixels when it is too near the horizon for that.
        Where the design's heads hang at heights that differ (a prior with a spread: mast arms and posts), the
        two readings are weighed by how sure each is: the height's spread against a pixel of the box."""
        x0, y0, x1, y1 = box
        k, camera, road = self.geometry.k, self.geometry.camera, self.road
        above_axis = math.atan((float(k[1, 2]) - 0.5 * (y0 + y1)) / self.geometry.f)
        elevation = above_axis + math.radians(camera.pitch_deg)
        rows = max(y1 - y0 - self.rules.light_box_pad_px, 1.0)
        by_size = self.geometry.f * road.signal_housing_height_m / rows
        if elevation <= math.radians(2.0):
            return by_size
        rise = road.signal_head_height_m - camera.mount_height_m
        by_height = rise / math.tan(elevation)
        return fused(by_height, by_height * road.signal_head_height_sd_m / rise, by_size, by_size / rows)

    def choose(self, lights: list[Detection], line: StopLineTrack, turned_rad: float) -> LightSeen | None:
        """Our light among ``lights``, given the tracked stop line and the heading change ``turned_rad`` since the
        car last drove along its lane; None when none qualifies."""
        best = None
        rules = self.rules
        expected = None
        road = self.road
        if line.stop_line_measured and line.stop_line is not None:
            expected = line.stop_line + line.config.camera_to_front_m + road.light_beyond_stop_line_m
        # The windows are the classic design's; a design whose heads stand elsewhere moves them by the difference
        # and widens them by twice its spread.
        line_tolerance = rules.light_line_tolerance_m + 2.0 * road.light_beyond_stop_line_sd_m
        lateral_shift = road.light_lateral_m - ROAD.light_lateral_m
        lateral_tolerance = rules.light_max_lateral_m + 2.0 * road.light_lateral_sd_m
        cos_t, sin_t = math.cos(turned_rad), math.sin(turned_rad)
        for d in lights:
            x0, y0, x1, y1 = d.box
            if d.score < rules.light_score_threshold or y1 - y0 < 2 or y0 <= 1.0:
                continue
            z_cam = self.distance(d.box)
            x_cam = self.geometry.lateral(0.5 * (x0 + x1), z_cam)
            lateral, z = x_cam * cos_t + z_cam * sin_t, z_cam * cos_t - x_cam * sin_t
            if abs(lateral - lateral_shift) > lateral_tolerance:
                continue
            if expected is not None and abs(z - expected) > line_tolerance:
                continue
            if best is None or z < best.distance_m:
                best = LightSeen(d.name.removeprefix("light_"), d.box, z, d.score)
        return best
