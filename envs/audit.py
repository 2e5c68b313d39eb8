"""An independent audit of the world's infraction detectors, from an episode's recorded ground truth.

Every driving score rests on ``sim.world``'s infraction checks, which carry state from step to step and
lean on the lane model's look-ups. This module recomputes the same infractions from what an episode
recorded (the ego's pose and speed, every light's state, the boxes of the cars and people near the
ego) with separate code that is simple enough to check by eye, and compares the two lists:

- red light: the front bumper's centre, moving from one step to the next, crosses the junction-side
  edge of a painted stop bar (``town.markings["stop_line"]``) in the bar's direction of travel while
  the light of the approach the bar belongs to is red;
- vehicle collision: the ego's rectangle overlaps a car's or truck's rectangle (separating axes);
  pedestrian collision: a person's circle touches the ego's rectangle; static collision: a building's
  footprint, a parked car, a light pole, a sign post or a tree trunk touches it; each counted when the
  contact starts;
- off road: no lane of the network (brute force over the lanes nearby) holds the ego's centre within
  half a lane width; counted when it starts;
- wrong way: the ego's heading is more than 100 degrees from the nearest lane holding its centre,
  unless that lane is inside a junction; counted when it starts.

Route deviation is the route tracker's judgement, not a rule of the road; it is not audited. Nor, yet, are
the rules of unsignalled towns (``stop_sign``, ``failed_to_yield``, ``speeding``).

A safety driver's take-over carries the car elsewhere: nothing is counted across it, and contacts
start afresh after it, as in the world.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from towndrive.sim.objects import LightState
from towndrive.sim.town import Town
from towndrive.sim.world import SIGN_POST_RADIUS_M, World

AUDITED = ("red_light", "collision_vehicle", "collision_pedestrian", "collision_static", "off_road", "wrong_way")
MATCH_S = 0.5  # a reported and a recomputed infraction of the same kind and party this close in time agree
NEAR_VEHICLE_M = 12.0  # cars and trucks recorded around the ego
NEAR_PEDESTRIAN_M = 6.0
WRONG_WAY_RAD = math.radians(100.0)


@dataclass
class AuditTrace:
    """The ground truth the audit needs, one entry per step (filled by ``record`` after each env step)."""

    ego: list[tuple[float, float, float, float]] = field(default_factory=list)  # x, y, heading, speed
    lights: list[np.ndarray] = field(default_factory=list)  # every approach's LightState
    vehicles: list[list[tuple[int, float, float, float, float, float]]] = field(default_factory=list)
    pedestrians: list[list[tuple[int, float, float, float]]] = field(default_factory=list)
    carried: list[bool] = field(default_factory=list)  # a take-over moved the car before this step
    times: list[float] = field(default_factory=list)
    ego_size: tuple[float, float] = (0.0, 0.0)  # length, width

    def record(self, world: World, carried: bool) -> None:
        ego = world.ego
        x, y = float(ego.position[0]), float(ego.position[1])
        self.ego_size = (float(ego.LENGTH), float(ego.WIDTH))
        self.ego.append((x, y, float(ego.heading), float(ego.speed)))
        self.lights.append(np.array([int(s) for s in world.lights.states], np.int8))
        self.vehicles.append([(v.object_id, float(v.position[0]), float(v.position[1]), float(v.heading),
                               float(v.LENGTH), float(v.WIDTH)) for v in world.npcs
                              if math.hypot(v.position[0] - x, v.position[1] - y) < NEAR_VEHICLE_M])
        self.pedestrians.append([(p.object_id, float(p.position[0]), float(p.position[1]), float(p.RADIUS))
                                 for p in world.pedestrians
                                 if math.hypot(p.position[0] - x, p.position[1] - y) < NEAR_PEDESTRIAN_M])
        self.carried.append(carried)
        self.times.append(float(world.time_s))


# ------------------------------------------------------------------------------------------ geometry
def _rectangle(x: float, y: float, heading: float, length: float, width: float) -> np.ndarray:
    c, s = math.cos(heading), math.sin(heading)
    along, across = np.array([c, s]) * length / 2, np.array([-s, c]) * width / 2
    centre = np.array([x, y])
    return np.array([centre + along + across, centre + along - across, centre - along - across, centre - along + across])


def _overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two convex polygons overlap: no edge normal of either separates them."""
    for poly in (a, b):
        for k in range(len(poly)):
            edge = poly[(k + 1) % len(poly)] - poly[k]
            normal = np.array([-edge[1], edge[0]])
            pa, pb = a @ normal, b @ normal
            if pa.max() < pb.min() or pb.max() < pa.min():
                return False
    return True


def _circle_touches(rect: np.ndarray, centre: np.ndarray, radius: float) -> bool:
    """Whether a circle touches a rectangle given by its four corners in order."""
    origin, u, v = rect[2], rect[1] - rect[2], rect[3] - rect[2]
    d = centre - origin
    a = float(np.clip(d @ u / (u @ u), 0.0, 1.0))
    b = float(np.clip(d @ v / (v @ v), 0.0, 1.0))
    return float(np.linalg.norm(origin + a * u + b * v - centre)) <= radius


def _segments_cross(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> bool:
    """Whether segment p0-p1 crosses segment q0-q1 (touching at p1 counts: the bumper reached the line)."""
    def side(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
        return float((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))

    d1, d2 = side(q0, q1, p0), side(q0, q1, p1)
    d3, d4 = side(p0, p1, q0), side(p0, p1, q1)
    return d1 * d2 <= 0 and d1 != 0 and d3 * d4 <= 0


# ------------------------------------------------------------------------------------------ the town's rules
@dataclass(frozen=True)
class StopBar:
    approach: int
    edge: tuple[np.ndarray, np.ndarray]  # the junction-side edge of the painted bar
    travel: np.ndarray  # unit vector: the direction traffic crosses it


def stop_bars(town: Town) -> list[StopBar]:
    """The painted stop bars of signalled approaches, each with its approach (the one whose stop-line centre is its
    near edge's middle); the bars of stop signs have no light and are left out."""
    centres = np.array([ap.stop_line_center for ap in town.approaches])
    bars = []
    for quad in town.markings["stop_line"]:
        far_inner, near_inner, near_outer, far_outer = (np.asarray(p, float) for p in quad)
        middle = (near_inner + near_outer) / 2
        if not len(centres) or float(np.min(np.linalg.norm(centres - middle, axis=1))) > 0.5:
            continue  # a stop sign's bar
        approach = int(np.argmin(np.linalg.norm(centres - middle, axis=1)))
        travel = far_inner - near_inner
        bars.append(StopBar(approach, (far_inner, far_outer), travel / np.linalg.norm(travel)))
    return bars


class _LaneTable:
    """Every lane's start, end and length, to test only the lanes that could hold a point."""

    def __init__(self, town: Town) -> None:
        self.town = town
        self.indices = list(town.lane_info)
        lanes = [town.lane(i) for i in self.indices]
        self.lanes = lanes
        self.start = np.array([lane.position(0.0, 0.0) for lane in lanes])
        self.length = np.array([lane.length for lane in lanes])

    def holding(self, point: np.ndarray) -> list[tuple[float, int]]:
        """(|lateral offset|, k) of each lane that holds the point within half a lane width (plus 5 cm)."""
        near = np.nonzero(np.linalg.norm(self.start - point, axis=1) < self.length + 5.0)[0]
        half = self.town.lane_width / 2 + 0.05
        out = []
        for k in near.tolist():
            s, lat = self.lanes[k].local_coordinates(point)
            if -0.5 <= s <= self.lanes[k].length + 0.5 and abs(lat) <= half:
                out.append((abs(float(lat)), k))
        return out


# ------------------------------------------------------------------------------------------ the audit
def recompute(town: Town, trace: AuditTrace) -> list[dict[str, Any]]:
    """Every audited infraction, recomputed from the trace: kind, time, place and the other party."""
    bars = stop_bars(town)
    bar_middles = np.array([(b.edge[0] + b.edge[1]) / 2 for b in bars]) if bars else np.zeros((0, 2))
    table = _LaneTable(town)
    static_rects = [b.footprint for b in town.buildings]
    static_centres = np.array([b.footprint.mean(axis=0) for b in town.buildings]) if static_rects else np.zeros((0, 2))
    static_rects += [_rectangle(float(c.position[0]), float(c.position[1]), c.heading, c.length_m, c.width_m)
                     for c in town.parked_cars]
    static_centres = np.array([r.mean(axis=0) for r in static_rects]) if static_rects else np.zeros((0, 2))
    circles = [(np.asarray(p, float), Town.POLE_RADIUS_M) for p in town.poles]
    circles += [(np.asarray(g.position, float), SIGN_POST_RADIUS_M) for g in town.signs]
    circles += [(np.asarray(t.position, float), Town.TRUNK_RADIUS_M) for t in town.trees]
    circle_centres = np.array([c for c, _ in circles]) if circles else np.zeros((0, 2))
    length, width = trace.ego_size
    out: list[dict[str, Any]] = []
    contacts: set[tuple[str, int]] = set()
    wrong = False
    previous_front: np.ndarray | None = None
    for k, (x, y, heading, _) in enumerate(trace.ego):
        t = trace.times[k]
        if trace.carried[k]:
            contacts, wrong, previous_front = set(), False, None
        centre = np.array([x, y])
        front = centre + length / 2 * np.array([math.cos(heading), math.sin(heading)])
        rect = _rectangle(x, y, heading, length, width)
        now: set[tuple[str, int]] = set()
        for oid, vx, vy, vh, vl, vw in trace.vehicles[k]:
            if _overlap(rect, _rectangle(vx, vy, vh, vl, vw)):
                now.add(("collision_vehicle", oid))
        for oid, px, py, radius in trace.pedestrians[k]:
            if _circle_touches(rect, np.array([px, py]), radius):
                now.add(("collision_pedestrian", oid))
        near_b = np.nonzero(np.linalg.norm(static_centres - centre, axis=1) < 40.0)[0] if len(static_centres) else []
        near_c = np.nonzero(np.linalg.norm(circle_centres - centre, axis=1) < 4.0)[0] if len(circle_centres) else []
        if any(_overlap(rect, static_rects[j]) for j in near_b) or any(
                _circle_touches(rect, circles[j][0], circles[j][1]) for j in near_c):
            now.add(("collision_static", 0))
        holding = table.holding(centre)
        if not holding:
            now.add(("off_road", 0))
        for kind, other in sorted(now - contacts):
            out.append({"kind": kind, "time_s": t, "x": x, "y": y, "other_id": other})
        contacts = now
        if holding:  # off the road the world keeps its last judgement, and so does the audit
            lane_index = table.indices[min(holding)[1]]
            is_wrong = False
            if town.lane_info[lane_index].kind != "connector":  # in a junction there is no wrong way
                lane = town.lane(lane_index)
                s = float(lane.local_coordinates(centre)[0])
                is_wrong = abs((lane.heading_at(s) - heading + math.pi) % (2 * math.pi) - math.pi) > WRONG_WAY_RAD
            if is_wrong and not wrong:
                out.append({"kind": "wrong_way", "time_s": t, "x": x, "y": y, "other_id": 0})
            wrong = is_wrong
        if previous_front is not None:
            close = np.nonzero(np.linalg.norm(bar_middles - front, axis=1) < 15.0)[0] if len(bars) else []
            for bar in (bars[j] for j in close):
                if (trace.lights[k][bar.approach] == int(LightState.RED)
                        and float((front - previous_front) @ bar.travel) > 0
                        and _segments_cross(previous_front, front, *bar.edge)):
                    out.append({"kind": "red_light", "time_s": t, "x": x, "y": y, "other_id": bar.approach})
        previous_front = front
    return out


def compare(reported: list[dict[str, Any]], recomputed: list[dict[str, Any]]) -> dict[str, Any]:
    """Match reported against recomputed infractions (same kind and party, within ``MATCH_S``):
    per kind, how many were confirmed, and the events reported but not confirmed, and missed."""
    left = list(recomputed)
    result: dict[str, Any] = {kind: {"confirmed": 0, "unconfirmed": [], "missed": []} for kind in AUDITED}
    for inf in reported:
        kind = inf["kind"]
        if kind not in result:
            continue
        other = inf.get("approach", inf.get("other_id", 0)) if kind == "red_light" else inf.get("other_id", 0)
        match = next((r for r in left if r["kind"] == kind and r["other_id"] == other
                      and abs(r["time_s"] - inf["time_s"]) <= MATCH_S), None)
        if match is None:
            result[kind]["unconfirmed"].append({"time_s": inf["time_s"], "x": inf["x"], "y": inf["y"], "other_id": other})
        else:
            left.remove(match)
            result[kind]["confirmed"] += 1
    for r in left:
        result[r["kind"]]["missed"].append({k: r[k] for k in ("time_s", "x", "y", "other_id")})
    return result


def audit_episode(town: Town, trace: AuditTrace, reported: list[dict[str, Any]]) -> dict[str, Any]:
    """``compare`` of the world's infractions with the recomputed ones."""
    return compare(reported, recompute(town, trace))


def merge(audits: list[dict[str, Any]]) -> dict[str, dict[str, int]]:
    """Totals over episodes: per kind, confirmed, unconfirmed and missed counts."""
    total = {kind: {"confirmed": 0, "unconfirmed": 0, "missed": 0} for kind in AUDITED}
    for a in audits:
        for kind in AUDITED:
            total[kind]["confirmed"] += a[kind]["confirmed"]
            total[kind]["unconfirmed"] += len(a[kind]["unconfirmed"])
            total[kind]["missed"] += len(a[kind]["missed"])
    return total
