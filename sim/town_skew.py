"""Lean a generated town's columns so that its streets meet at angles other than 90 degrees.

Why: real junctions are seldom square, and a driver that has only seen square ones learns their
one turn angle. The town is laid out square (``generate_town``, which builds its columns wider by
``1 / cos(skew)`` across x) and then sheared, x' = x + (y - y0) tan(skew): rows stay put, columns
lean, every street keeps its true width, and everything the town holds (lanes, asphalt, markings,
kerbs, buildings, signals, signs, parked cars) goes through the same map, so it all still fits.
Straight lanes stay straight; curved ones (junction turns, the corner bends) become sampled
lanes along their sheared centre lines (``sim.polyline_lane``).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from highway_env.road.lane import AbstractLane, LineType, StraightLane
from highway_env.road.road import RoadNetwork

from towndrive.sim.polyline_lane import PolylineLane

if TYPE_CHECKING:
    from towndrive.sim.town import Town

CURVE_SAMPLE_M = 1.0  # spacing of a sheared curve's samples


class Shear:
    """x' = x + (y - y0) * tan(angle); y' = y."""

    def __init__(self, degrees: float, y0: float) -> None:
        self.tan = math.tan(math.radians(degrees))
        self.y0 = y0

    def point(self, p: np.ndarray) -> np.ndarray:
        p = np.asarray(p, float)
        out = p.copy()
        out[..., 0] = p[..., 0] + (p[..., 1] - self.y0) * self.tan
        return out

    def heading(self, heading: float) -> float:
        dx, dy = math.cos(heading), math.sin(heading)
        return math.atan2(dy, dx + dy * self.tan)


def _lane(lane: AbstractLane, shear: Shear) -> AbstractLane:
    if type(lane) is StraightLane:
        return StraightLane(shear.point(lane.start), shear.point(lane.end), width=lane.width,
                            line_types=(LineType.NONE, LineType.NONE))
    ss = np.linspace(0.0, lane.length, max(3, int(math.ceil(lane.length / CURVE_SAMPLE_M)) + 1))
    points = shear.point(np.array([lane.position(s, 0.0) for s in ss]))
    return PolylineLane(points, np.array([shear.heading(lane.heading_at(s)) for s in ss]), lane.width)


def skew_town(town: Town, degrees: float) -> None:
    """Shear a freshly generated town in place (before its lanes are indexed)."""
    shear = Shear(degrees, float(town.ys[-1]) / 2)
    network = RoadNetwork()
    for frm, tos in town.network.graph.items():
        for to, lanes in tos.items():
            for lane in lanes:
                network.add_lane(frm, to, _lane(lane, shear))
    town.network = network
    town.skew_deg = degrees
    town.road_polygons = [shear.point(p) for p in town.road_polygons]
    town.slab_polygons = [shear.point(p) for p in town.slab_polygons]
    town.grass_polygons = [shear.point(p) for p in town.grass_polygons]
    town.markings = {kind: [shear.point(q) for q in quads] for kind, quads in town.markings.items()}
    town.poles = [shear.point(p) for p in town.poles]
    town.buildings = [replace(b, footprint=shear.point(b.footprint)) for b in town.buildings]
    town.trees = [replace(t, position=shear.point(t.position)) for t in town.trees]
    town.approaches = [replace(ap, stop_line_center=shear.point(ap.stop_line_center),
                               travel_heading=shear.heading(ap.travel_heading), light_pole=shear.point(ap.light_pole),
                               light_head=shear.point(ap.light_head)) for ap in town.approaches]
    town.entries = [replace(e, line_center=shear.point(e.line_center), travel_heading=shear.heading(e.travel_heading))
                    for e in town.entries]
    town.crosswalks = [replace(cw, start=shear.point(cw.start), end=shear.point(cw.end),
                               polygon=shear.point(cw.polygon)) for cw in town.crosswalks]
    town.signs = [replace(s, position=shear.point(s.position), facing=shear.heading(s.facing)) for s in town.signs]
    town.parked_cars = [replace(c, position=shear.point(c.position), heading=shear.heading(c.heading))
                        for c in town.parked_cars]
