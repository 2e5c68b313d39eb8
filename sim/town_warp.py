"""Bend a generated town: lean its columns and bow its streets, so that junctions are not all square
and streets curve between them.

Why: real junctions are seldom square and real streets seldom straight; a driver that has only seen
a square grid learns its one turn angle and its straight kerbs. The town is laid out square
(``generate_town``, which builds its columns ``1 / cos(skew)`` wider across x) and then mapped by

    x' = x + (y - yc) tan(skew) + bow_x sin(pi (y - y0) / H)
    y' = y + bow_y sin(pi (x - x0) / W)

over the node grid's extent W x H: the skew leans the columns, the bows arch the rows and the
columns by up to their amplitude in the middle of the town. Everything the town holds (lanes,
asphalt, markings, kerbs, buildings, signals, signs, parked cars) goes through the same map, so it
all still fits; headings go through its Jacobian. A pure skew is affine: straight lanes stay
straight and convex pieces convex. With a bow, lanes become sampled lanes along their mapped centre
lines (``sim.polyline_lane``) and the flat layers are re-cut into small convex pieces first (the
ground map fills convex polygons), with the kerbs kept as whole outlines.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from highway_env.road.lane import AbstractLane, LineType, StraightLane
from highway_env.road.road import RoadNetwork

from towndrive.sim.fillet_lane import FilletLane
from towndrive.sim.polyline_lane import PolylineLane

if TYPE_CHECKING:
    from towndrive.sim.town import Town

CURVE_SAMPLE_M = 1.0  # spacing of a mapped curve's samples
BOWED_SAMPLE_M = 4.0  # spacing of a bowed straight lane's samples (its radius is hundreds of metres)
PIECE_M = 6.0  # the flat layers of a bowed town are cut into convex pieces of at most this size
OUTLINE_STEP_M = 3.0  # kerb outlines are sampled this finely before they are bent


class TownWarp:
    """The map above. ``extent`` is the node grid's (x0, y0, x1, y1)."""

    def __init__(self, skew_deg: float, bow_x_m: float, bow_y_m: float, extent: tuple[float, float, float, float]) -> None:
        self.skew_deg = skew_deg
        self.tan = math.tan(math.radians(skew_deg))
        self.bow_x, self.bow_y = bow_x_m, bow_y_m
        self.x0, self.y0, x1, y1 = extent
        self.width, self.height = x1 - self.x0, y1 - self.y0
        self.yc = (self.y0 + y1) / 2

    @property
    def affine(self) -> bool:
        return self.bow_x == 0.0 and self.bow_y == 0.0

    def point(self, p: np.ndarray) -> np.ndarray:
        p = np.asarray(p, float)
        x, y = p[..., 0], p[..., 1]
        out = p.copy()
        out[..., 0] = x + (y - self.yc) * self.tan + self.bow_x * np.sin(np.pi * (y - self.y0) / self.height)
        out[..., 1] = y + self.bow_y * np.sin(np.pi * (x - self.x0) / self.width)
        return out

    def heading(self, heading: float, at: np.ndarray) -> float:
        """A direction at a point, mapped (through the Jacobian there)."""
        dx, dy = math.cos(heading), math.sin(heading)
        x, y = float(at[0]), float(at[1])
        dxdy = self.tan + self.bow_x * math.pi / self.height * math.cos(math.pi * (y - self.y0) / self.height)
        dydx = self.bow_y * math.pi / self.width * math.cos(math.pi * (x - self.x0) / self.width)
        return math.atan2(dy + dydx * dx, dx + dxdy * dy)

    def lane(self, lane: AbstractLane) -> AbstractLane:
        """A lane mapped: a straight one stays straight under a skew; a turn of a chosen radius (a junction's) is
        made again between its mapped ends on that radius, so that the map never tightens it; other curves are
        sampled along their mapped centre line (a bend must follow its mapped kerbs)."""
        if type(lane) is StraightLane and self.affine:
            return StraightLane(self.point(lane.start), self.point(lane.end), width=lane.width,
                                line_types=(LineType.NONE, LineType.NONE))
        if isinstance(lane, FilletLane) and lane.design_radius_m is not None:
            start, end = lane.position(0.0, 0.0), lane.position(lane.length, 0.0)
            return FilletLane(self.point(start), self.heading(lane.heading_at(0.0), start), self.point(end),
                              self.heading(lane.heading_at(lane.length), end), lane.width, lane.design_radius_m)
        step = BOWED_SAMPLE_M if type(lane) is StraightLane else CURVE_SAMPLE_M
        ss = np.linspace(0.0, lane.length, max(3, int(math.ceil(lane.length / step)) + 1))
        centre = np.array([lane.position(s, 0.0) for s in ss])
        headings = np.array([self.heading(lane.heading_at(s), c) for s, c in zip(ss, centre, strict=True)])
        return PolylineLane(self.point(centre), headings, lane.width)

    def pieces(self, polygon: np.ndarray) -> list[np.ndarray]:
        """A convex polygon mapped: itself if the map is affine, else its convex pieces of at most
        ``PIECE_M``, each mapped. A quad (asphalt strips, paint) is cut into a grid of smaller quads between
        points along its own sides, so that a thin line's pieces meet edge to edge; any other polygon is cut
        on the map's grid."""
        if self.affine:
            return [self.point(polygon)]
        lo, hi = polygon.min(axis=0), polygon.max(axis=0)
        if float(np.max(hi - lo)) <= PIECE_M:
            return [self.point(polygon)]
        if len(polygon) == 4:
            return [self.point(q) for q in _quad_grid(np.asarray(polygon, float))]
        out = []
        for x in np.arange(lo[0], hi[0], PIECE_M):
            for y in np.arange(lo[1], hi[1], PIECE_M):
                piece = _clip(polygon, x, y, min(x + PIECE_M, hi[0]), min(y + PIECE_M, hi[1]))
                if len(piece) >= 3:
                    out.append(self.point(piece))
        return out

    def outline(self, polygon: np.ndarray) -> np.ndarray:
        """A closed outline sampled every ``OUTLINE_STEP_M`` along its edges, mapped."""
        if self.affine:
            return self.point(polygon)
        points = []
        for a, b in zip(polygon, np.roll(polygon, -1, axis=0), strict=True):
            n = max(1, int(math.ceil(float(np.linalg.norm(b - a)) / OUTLINE_STEP_M)))
            points += [a + (b - a) * t for t in np.arange(n) / n]
        return self.point(np.array(points))


def _quad_grid(quad: np.ndarray) -> list[np.ndarray]:
    """A quad (corners a, b, c, d in order) cut into nu x nv quads of at most ``PIECE_M`` a side, bilinearly."""
    a, b, c, d = quad
    nu = max(1, int(math.ceil(max(np.linalg.norm(b - a), np.linalg.norm(c - d)) / PIECE_M)))
    nv = max(1, int(math.ceil(max(np.linalg.norm(d - a), np.linalg.norm(c - b)) / PIECE_M)))

    def at(i: int, j: int) -> np.ndarray:
        u, v = i / nu, j / nv
        return (1 - u) * (1 - v) * a + u * (1 - v) * b + u * v * c + (1 - u) * v * d

    return [np.array([at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)]) for i in range(nu) for j in range(nv)]


def _clip(polygon: np.ndarray, x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    """A convex polygon cut to an axis-aligned rectangle (Sutherland-Hodgman)."""
    pts = [np.asarray(p, float) for p in polygon]
    for axis, bound, keep_below in ((0, x0, False), (0, x1, True), (1, y0, False), (1, y1, True)):
        if not pts:
            break
        out = []
        for k, cur in enumerate(pts):
            prev = pts[k - 1]
            cur_in = cur[axis] <= bound if keep_below else cur[axis] >= bound
            prev_in = prev[axis] <= bound if keep_below else prev[axis] >= bound
            if cur_in != prev_in:
                t = (bound - prev[axis]) / (cur[axis] - prev[axis])
                out.append(prev + t * (cur - prev))
            if cur_in:
                out.append(cur)
        pts = out
    return np.array(pts)


def warp_town(town: Town, warp: TownWarp) -> None:
    """Map a freshly generated town in place (before its lanes are indexed)."""
    network = RoadNetwork()
    for frm, tos in town.network.graph.items():
        for to, lanes in tos.items():
            for lane in lanes:
                network.add_lane(frm, to, warp.lane(lane))
    town.network = network
    town.warp = warp
    town.kerb_outlines = [warp.outline(p) for p in town.slab_polygons]
    town.road_polygons = [q for p in town.road_polygons for q in warp.pieces(p)]
    town.slab_polygons = [q for p in town.slab_polygons for q in warp.pieces(p)]
    town.grass_polygons = [q for p in town.grass_polygons for q in warp.pieces(p)]
    town.markings = {kind: [q for p in quads for q in warp.pieces(p)] for kind, quads in town.markings.items()}
    town.poles = [warp.point(p) for p in town.poles]
    town.buildings = [replace(b, footprint=warp.point(b.footprint)) for b in town.buildings]
    town.trees = [replace(t, position=warp.point(t.position)) for t in town.trees]
    town.approaches = [replace(ap, stop_line_center=warp.point(ap.stop_line_center),
                               travel_heading=warp.heading(ap.travel_heading, ap.stop_line_center),
                               light_pole=warp.point(ap.light_pole), light_head=warp.point(ap.light_head))
                       for ap in town.approaches]
    town.entries = [replace(e, line_center=warp.point(e.line_center),
                            travel_heading=warp.heading(e.travel_heading, e.line_center)) for e in town.entries]
    town.crosswalks = [replace(cw, start=warp.point(cw.start), end=warp.point(cw.end), polygon=warp.point(cw.polygon))
                       for cw in town.crosswalks]
    town.signs = [replace(s, position=warp.point(s.position), facing=warp.heading(s.facing, s.position))
                  for s in town.signs]
    town.parked_cars = [replace(c, position=warp.point(c.position), heading=warp.heading(c.heading, c.position))
                        for c in town.parked_cars]
