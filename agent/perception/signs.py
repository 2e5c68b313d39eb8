"""Road signs the detector found, measured: which sign, how far ahead and how far to the side.

A sign plate has the road design's size (``RoadDesign.sign_plate_size_m``, about square: an octagon, a triangle or
a disc), so its distance is ``f x size / box size`` (the larger of the box's sides, since a plate seen at an angle
narrows but keeps its height). Only plates that face the car and stand on its side of the road address it: a
plate seen edge-on (narrow for its height) faces the cross street, and one left of the car's axis stands by the
oncoming lanes (their signs are seen from the back, which the detector does not take for a sign).
"""

from __future__ import annotations

from dataclasses import dataclass

from towndrive.agent.perception.box_geometry import BoxGeometry
from towndrive.agent.perception.classes import LIMIT_OF_CLASS, SIGN_CLASSES
from towndrive.agent.perception.detections import Detection
from towndrive.sim.spec import ROAD, RoadDesign

SIGN_KIND = {"stop_sign": "stop", "yield_sign": "yield", "speed_limit_30": "limit", "speed_limit_50": "limit"}


@dataclass(frozen=True)
class SignSeen:
    """One sign addressing the car this frame."""

    kind: str  # "stop", "yield" or "limit"
    distance_m: float  # forward, camera to the plate
    lateral_m: float  # the plate's centre, right of the camera axis
    limit_kmh: int = 0  # speed limits: the posted value
    score: float = 1.0


@dataclass(frozen=True)
class SignRules:
    score_threshold: float = 0.4
    max_distance_m: float = 40.0
    lateral_m: tuple[float, float] = (0.0, 12.0)  # right of the camera axis: our side of the road
    min_aspect: float = 0.5  # width over height below this: the plate is seen edge-on (it faces a cross street)


class SignLocator:
    """Detections in, the signs that address the car out (module docstring)."""

    def __init__(self, geometry: BoxGeometry, rules: SignRules | None = None, road: RoadDesign = ROAD) -> None:
        self.geometry = geometry
        self.rules = rules or SignRules()
        self.road = road

    def distance(self, box: tuple[float, float, float, float]) -> float:
        x0, y0, x1, y1 = box
        return self.geometry.f * self.road.sign_plate_size_m / max(x1 - x0, y1 - y0, 1.0)

    def read(self, detections: list[Detection]) -> list[SignSeen]:
        rules, out = self.rules, []
        for d in detections:
            if d.name not in SIGN_CLASSES or d.score < rules.score_threshold:
                continue
            x0, y0, x1, y1 = d.box
            if (x1 - x0) < rules.min_aspect * max(y1 - y0, 1e-6):
                continue
            z = self.distance(d.box)
            x = self.geometry.lateral(0.5 * (x0 + x1), z)
            if z > rules.max_distance_m or not rules.lateral_m[0] <= x <= rules.lateral_m[1]:
                continue
            out.append(SignSeen(SIGN_KIND[d.name], z, x, LIMIT_OF_CLASS.get(d.name, 0), d.score))
        return sorted(out, key=lambda s: s.distance_m)
