"""NPC vehicles: highway-env IDM/MOBIL vehicles that follow routes and obey the town's signals.

highway-env gives the lane geometry, lane following (``steering_control``, ``follow_road``), the
bicycle model and MOBIL lane changes. On top of it, the longitudinal decision takes the closest of:
the vehicle ahead on the planned path (NPCs and the ego), a red or yellow stop line, and a
pedestrian in the path; each is fed to the IDM as a gap. highway-env's own neighbour search and
collision handling scan every vehicle and every lane, so they are replaced by a path search over
nearby agents only.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
from highway_env.road.lane import AbstractLane, CircularLane
from highway_env.road.road import Road
from highway_env.utils import not_zero
from highway_env.utils import wrap_to_pi as hwe_wrap_to_pi
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.kinematics import Vehicle

from towndrive.sim.ego import EgoVehicle
from towndrive.sim.geometry import wrap_to_pi
from towndrive.sim.idm import idm_acceleration as idm
from towndrive.sim.objects import LightState, ObjectSnapshot, SemanticClass, snapshot_of
from towndrive.sim.path_filter import BUMPER_SWING_M, clearly_nearest_lane, lanes_may_hold, path_candidates, path_rows, zone_holds
from towndrive.sim.routes import random_next_edge
from towndrive.sim.rules import PRIORITY_STANDING_M, STOP_CONTROLS, JunctionRules
from towndrive.sim.spec import (  # noqa: F401 (re-exported: the rules' shared numbers)
    CURVE_BRAKE_MPS2,
    CURVE_LATERAL_ACCEL_MPS2,
    YIELD_APPROACH_MPS,
)
from towndrive.sim.town import OPPOSITE, Approach, Command, Control, Entry, LaneIndex, Town, lanes_for


@dataclass(frozen=True)
class Agents:
    """Positions and shapes of everything that can block a path, gathered once per step."""

    positions: np.ndarray  # (N, 2)
    headings: np.ndarray
    speeds: np.ndarray
    half_lengths: np.ndarray
    is_pedestrian: np.ndarray
    ids: np.ndarray
    on_crossing: np.ndarray  # pedestrians out on the road (crossing), even while they stand still
    turning_left: np.ndarray | None = None  # vehicles whose next junction move is a left turn (None: unknown)

    @cached_property
    def crossing_positions(self) -> np.ndarray:
        """Positions of the pedestrians out on a crossing (every NPC's crosswalk check reads them)."""
        return self.positions[np.nonzero(self.is_pedestrian & self.on_crossing)[0]]


PEDESTRIAN_LOOKAHEAD_S = 1.5  # a walking pedestrian blocks a path it will step into within this time
CROSSING_CLEAR_M = 10.0  # a vehicle crossing the path nearer than this still blocks it
STANDING_VEHICLE_MPS = 1.0  # slower than this, a vehicle is an obstacle the car's swept front must clear
STANDING_PEDESTRIAN_LATERAL_M = 1.45  # on the sidewalk: car half width 0.95 + pedestrian radius 0.3 + 0.2 m


LIMIT_BRAKE_MPS2 = 2.0  # how hard one slows down ahead of a lower posted limit
ZEBRA_CLEAR_M = 10.0  # a stop-line driver does not leave the line for an occupied zebra this close beyond it
STOP_HOLD_M = 1.5  # within this of a stop point at a stop sign, at walking pace, brake to a standstill


def _clip(x: float, low: float, high: float) -> float:
    """``np.clip`` for one number: the same value (no arithmetic, NaN passes through), without the call overhead."""
    return min(max(x, low), high)


_TIGHTEST: weakref.WeakKeyDictionary[AbstractLane, tuple[float, float]] = weakref.WeakKeyDictionary()


def tightest_turn(lane: AbstractLane) -> tuple[float, float]:
    """A lane's smallest radius and where along it that part starts (inf for a straight lane): a circle's
    radius from its start; a fillet's arc after its lead-in; a sampled curve's tightest segment. Worked out once
    per lane (lanes never change; the path searches of every vehicle ask each step)."""
    hit = _TIGHTEST.get(lane)
    if hit is None:
        if isinstance(lane, CircularLane):
            hit = (lane.radius, 0.0)
        else:
            tightest = getattr(lane, "tightest_turn", None)
            hit = tightest() if tightest is not None else (math.inf, 0.0)
        _TIGHTEST[lane] = hit
    return hit


def front_sweep_m(lane: AbstractLane, my_half: float) -> float:
    """How far a car's front swings out of a lane's centre line in the lane's tightest turn: the car steers its
    rear along the path (the bicycle model's rear axle is its rear bumper; wheelbase = length), so its front
    bumper runs outside the arc by length^2 / (2 radius) (0.9 m for a 4.6 m car on a 12 m turn)."""
    radius, _ = tightest_turn(lane)
    return 0.0 if radius == math.inf else (2.0 * my_half) ** 2 / (2.0 * radius)


def outside_of_turn(lane: AbstractLane, s: float, point: np.ndarray) -> bool:
    """Whether a point beside a lane lies where a turning car's front swings: beside the lane itself (the front
    leaves the centre line only once the rear is in the turn, never before the lane starts) and on the outside
    of the turn (the body lies along the tangent from the rear, so it never cuts inside the arc)."""
    if s < 0.0:
        return False
    turn = wrap_to_pi(float(lane.heading_at(lane.length) - lane.heading_at(0.0)))
    h = float(lane.heading_at(min(s, lane.length)))
    base = lane.position(min(s, lane.length), 0.0)
    left = math.cos(h) * (point[1] - base[1]) - math.sin(h) * (point[0] - base[0])
    return left * turn < 0.0


def curve_speed_limit(path: list[tuple[AbstractLane, float]], my_s: float) -> float:
    """The highest speed from which every turn ahead on the path can be taken comfortably:
    v_turn = sqrt(a_lat * radius) in the turn, and at most sqrt(v_turn^2 + 2 b d) at distance d before it."""
    limit = math.inf
    for lane, offset in path:
        radius, turn_s = tightest_turn(lane)
        if radius == math.inf:
            continue
        v_turn = math.sqrt(CURVE_LATERAL_ACCEL_MPS2 * radius)
        distance = max(0.0, offset + turn_s - my_s)
        limit = min(limit, math.sqrt(v_turn * v_turn + 2.0 * CURVE_BRAKE_MPS2 * distance))
    return limit


def idm_acceleration(speed: float, target_speed: float, gap_m: float | None, closing_mps: float,
                     a_max: float = IDMVehicle.COMFORT_ACC_MAX, b: float = -IDMVehicle.COMFORT_ACC_MIN,
                     min_gap_m: float = 2.0, headway_s: float = 1.2, delta: float = IDMVehicle.DELTA) -> float:
    """Intelligent Driver Model with a bumper-to-bumper gap (``sim.idm``), highway-env's constants by default."""
    return idm(speed, target_speed, gap_m, closing_mps, a_max, b, min_gap_m, headway_s, delta)


def posted_speed_cap(town: Town, path: list[tuple[AbstractLane, float]], path_lanes: list[LaneIndex],
                     my_s: float) -> float:
    """The highest speed that keeps to every posted limit ahead on the path: the limit of each lane's road from
    where it starts, and at most sqrt(v_limit^2 + 2 b d) at distance d before it (inf where nothing is posted)."""
    cap = math.inf
    if not town.speed_limits_kmh:
        return cap
    for (_, offset), index in zip(path, path_lanes, strict=False):
        kmh = town.speed_limit_kmh(index[:2])
        if kmh is None:
            continue
        v = kmh / 3.6
        cap = min(cap, math.sqrt(v * v + 2.0 * LIMIT_BRAKE_MPS2 * max(0.0, offset - my_s)))
    return cap


def vehicle_rows(agents: Agents) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Positions, headings, speeds, half lengths and ids of the vehicles among the agents (for ``sim.rules``)."""
    keep = ~agents.is_pedestrian
    return (agents.positions[keep], agents.headings[keep], agents.speeds[keep], agents.half_lengths[keep],
            agents.ids[keep])


def path_gap(path: list[tuple[AbstractLane, float]], my_s: float, my_half: float, agents: Agents, skip_id: int,
             origin: np.ndarray, lookahead_m: float, vehicle_lateral_m: float = 2.2,
             pedestrian_lateral_m: float = 2.6) -> tuple[float | None, float]:
    """Bumper gap to the nearest agent on a path of lanes, and that agent's speed along it.

    ``path`` lists lanes with the path coordinate at which each starts. Moving vehicles count only
    when they head roughly along the path (crossing traffic is not a leader); a vehicle standing on
    the path counts whatever its heading; pedestrians always count.
    """
    if len(agents.positions) == 0:
        return None, 0.0
    # Only agents near the origin that could touch the path go on to the exact (slow) test below.
    path_heading = float(path[0][0].heading_at(my_s - path[0][1]))
    sweeps = [front_sweep_m(lane, my_half) for lane, _ in path]
    tolerances = _lateral_tolerances(vehicle_lateral_m + max(sweeps), pedestrian_lateral_m)  # the prefilter's bound
    rows = path_rows([lane for lane, _ in path])
    near = path_candidates(agents.positions, agents.ids, skip_id, float(origin[0]), float(origin[1]),
                           (lookahead_m + 8.0) ** 2, agents.headings, agents.speeds, agents.half_lengths,
                           agents.is_pedestrian, agents.on_crossing, rows, path_heading, tolerances,
                           PEDESTRIAN_LOOKAHEAD_S)
    best: float | None = None
    best_speed = 0.0
    for k in near:
        ped = bool(agents.is_pedestrian[k])
        half_k = float(agents.half_lengths[k])
        points = [(agents.positions[k], half_k)]
        h = float(agents.headings[k])
        ahead = np.array([math.cos(h), math.sin(h)])
        if ped and agents.speeds[k] > 0.1:  # a walking pedestrian counts where it will be soon, too
            points.append((agents.positions[k] + PEDESTRIAN_LOOKAHEAD_S * float(agents.speeds[k]) * ahead, half_k))
        elif not ped and half_k * abs(math.sin(h - path_heading)) > BUMPER_SWING_M:
            # A vehicle at an angle to the path (turning, crossing, a long truck leaving it) can poke a bumper
            # into the lane while its centre is a lane away: its two bumpers count as well.
            points += [(agents.positions[k] + half_k * ahead, 0.0), (agents.positions[k] - half_k * ahead, 0.0)]
        # A standing pedestrian (waiting at a kerb) blocks only what would brush it; a walking one
        # blocks the whole lane it is in or stepping into.
        walking = agents.speeds[k] > 0.1 or bool(agents.on_crossing[k])
        tol = (pedestrian_lateral_m if walking else STANDING_PEDESTRIAN_LATERAL_M) if ped else vehicle_lateral_m
        gap_k, speed_k = _gap_on_path(path, rows, points, ped, k, agents, my_s, my_half, tol, sweeps)
        if gap_k is not None and (best is None or gap_k < best):
            best, best_speed = gap_k, speed_k
    return best, best_speed


@lru_cache(maxsize=16)
def _lateral_tolerances(vehicle_lateral_m: float, pedestrian_lateral_m: float) -> np.ndarray:
    """``path_candidates``' tolerances (vehicle, walking pedestrian, standing pedestrian), built once per pair
    rather than on every call (read-only: the array is shared)."""
    tolerances = np.array([vehicle_lateral_m, pedestrian_lateral_m, STANDING_PEDESTRIAN_LATERAL_M])
    tolerances.setflags(write=False)
    return tolerances


def _gap_on_path(path: list[tuple[AbstractLane, float]], rows: np.ndarray, points: list[tuple[np.ndarray, float]],
                 ped: bool, k: int, agents: Agents, my_s: float, my_half: float,
                 tol: float, sweeps: list[float]) -> tuple[float | None, float]:
    """Bumper gap to agent ``k`` (at any of ``points``, each with its distance to the agent's bumper)
    along the path, and its speed along the path. ``rows``: the path's ``path_rows``; ``sweeps``: each path
    lane's ``front_sweep_m``, added to the tolerance for a standing vehicle where the front swings
    (``outside_of_turn``)."""
    best: float | None = None
    best_speed = 0.0
    pad = float(agents.half_lengths[k])
    standing = not ped and agents.speeds[k] < STANDING_VEHICLE_MPS
    sweeps = sweeps if standing else [0.0] * len(path)
    reach = tol + max(sweeps)
    for pos, half in points:
        # A lane the conservative compiled bound rules out fails the exact test below as well: skip its geometry.
        maybe = lanes_may_hold(float(pos[0]), float(pos[1]), rows, reach, pad).tolist()
        for (lane, offset), ok, sweep in zip(path, maybe, sweeps, strict=True):
            if not ok:
                continue
            s, lat = lane.local_coordinates(pos)
            if s < -agents.half_lengths[k] or s > lane.length + agents.half_lengths[k]:
                continue
            if abs(lat) > tol and (sweep == 0.0 or abs(lat) > tol + sweep or not outside_of_turn(lane, s, pos)):
                continue
            along = offset + s
            if along <= my_s:
                break
            gap = along - my_s - my_half - half
            # Crossing traffic on the move further ahead is not a leader (it will be gone); one standing
            # across the path, or still crossing it close ahead, is in the way.
            crossing = abs(wrap_to_pi(float(agents.headings[k]) - lane.heading_at(s))) > 1.0
            if not ped and crossing and agents.speeds[k] > 1.0 and gap > CROSSING_CLEAR_M:
                continue
            if best is None or gap < best:
                best = gap
                best_speed = 0.0 if ped else float(agents.speeds[k]) * math.cos(
                    wrap_to_pi(float(agents.headings[k]) - lane.heading_at(s)))
            break
    return best, best_speed


def crosswalk_gap(town: Town, path: list[tuple[AbstractLane, float]], path_lanes: list[tuple[str, str, int]],
                  my_s: float, my_half: float, agents: Agents, lookahead_m: float) -> float | None:
    """Gap from the front bumper to the first crosswalk ahead on the path that someone is crossing
    (or stepping onto): yield there, before the zebra, not next to the pedestrian."""
    crossing = agents.crossing_positions
    if len(crossing) == 0:
        return None
    frames = town.crosswalk_frames()
    for (_, offset), index in zip(path, path_lanes, strict=False):
        for cw, s_in, s_out in town.crosswalks_on(index):
            enter, leave = offset + s_in, offset + s_out
            if leave < my_s - my_half or enter - my_s > lookahead_m:
                continue
            if enter < my_s + my_half:
                continue  # already on it: clear it rather than stop on it
            centre, u, half_depth, half_width, across = frames[cw]
            # Someone in the zone (the crossing widened by 1 m)? A compiled test answers unless a person is
            # within MARGIN_M of the zone's edge; then the exact NumPy test below decides.
            held = zone_holds(crossing, float(centre[0]), float(centre[1]), float(u[0]), float(u[1]),
                              float(across[0]), float(across[1]), half_depth + 1.0, half_width + 1.0)
            if held < 0:
                d = crossing - centre
                held = int(((np.abs(d @ u) <= half_depth + 1.0) & (np.abs(d @ across) <= half_width + 1.0)).any())
            if held:
                return enter - my_s - my_half
    return None


def oncoming_conflict(town: Town, approach: Approach, agents: Agents, skip_id: int, horizon_s: float = 4.5) -> bool:
    """Whether traffic from the opposite approach is in the junction or would reach it within
    ``horizon_s``: an unprotected left turn from ``approach`` must wait for it."""
    opposite = town.approach_at(approach.node, OPPOSITE[approach.arm])
    if opposite is None:
        return False
    centre = town.node_position(approach.node)
    travel = np.array([math.cos(opposite.travel_heading), math.sin(opposite.travel_heading)])
    side = np.array([-travel[1], travel[0]])  # its right: its own lanes lie there
    rel = agents.positions - centre
    before = -(rel @ travel)  # metres still to go to the junction centre
    lateral = rel @ side
    heading_ok = np.abs((agents.headings - opposite.travel_heading + np.pi) % (2 * np.pi) - np.pi) < 0.7
    candidates = (~agents.is_pedestrian) & (agents.ids != skip_id) & heading_ok & (before > -2.0) & (before < 70.0)
    candidates &= (lateral > -0.5) & (lateral < 8.0)
    lane = town.lane((*opposite.edge, 0))  # the opposite stop line's distance from the centre (its lanes' end)
    setback = float((centre - lane.position(lane.length, 0.0)) @ travel)
    for k in np.nonzero(candidates)[0]:
        if before[k] < setback + 1.0:
            return True  # already in the junction
        if (before[k] - setback) / max(float(agents.speeds[k]), 0.5) < horizon_s and agents.speeds[k] > 0.5:
            return True
    return False


def oncoming_priority_conflict(town: Town, entry: Entry, agents: Agents, skip_id: int, horizon_s: float = 4.5) -> bool:
    """``oncoming_conflict`` at an unsignalled junction: whether traffic from the opposite arm, when that arm has
    the same control as ``entry`` (both priority streets, or both give-way lines), is in the junction or would
    reach its line within ``horizon_s``; a left turn from ``entry`` waits for it. Oncoming vehicles that turn
    left themselves are left out: the two left turns pass in front of each other, and two left-turners waiting
    for each other would wait for ever."""
    opposite = next((e for e in town.entries_at(entry.node) if e.arm == OPPOSITE[entry.arm]), None)
    if opposite is None or opposite.control != entry.control:
        return False
    travel = np.array([math.cos(opposite.travel_heading), math.sin(opposite.travel_heading)])
    side = np.array([-travel[1], travel[0]])
    centre = town.node_position(entry.node)
    rel = agents.positions - opposite.line_center
    before = -(rel @ travel) - agents.half_lengths  # front bumper to its line
    lateral = rel @ side
    inside = float((centre - opposite.line_center) @ travel)  # line to junction centre
    heading_ok = np.abs((agents.headings - opposite.travel_heading + np.pi) % (2 * np.pi) - np.pi) < 0.7
    candidates = (~agents.is_pedestrian) & (agents.ids != skip_id) & heading_ok & (before > -inside) & (before < 70.0)
    candidates &= np.abs(lateral) < opposite.lane_count * town.lane_width / 2 + 0.6
    if agents.turning_left is not None:
        candidates &= ~(agents.turning_left & (before > 0.0))  # once in the junction it is in the way, whatever it does
    for k in np.nonzero(candidates)[0]:
        if before[k] < PRIORITY_STANDING_M:
            return True  # at its line (about to go) or already in the junction
        if agents.speeds[k] > 0.5 and before[k] / float(agents.speeds[k]) < horizon_s:
            return True
    return False


def junction_gap(town: Town, rules: JunctionRules | None, vehicle_id: int, entry: Entry, turn: Command | None,
                 gap: float, agents: Agents, zebra: float | None) -> float | None:
    """At an unsignalled entry: the gap to its line if the vehicle must stop there (``sim.rules``: a full stop
    first, its turn, a free junction, a gap in the priority traffic, no one on the zebra just beyond), else
    None. On a priority street only a left turn waits, for oncoming priority traffic; at a give-way line a left
    turn also waits for oncoming traffic from the opposite give-way line (``oncoming_priority_conflict``)."""
    if turn == Command.LEFT and entry.control in (Control.PRIORITY, Control.YIELD) and oncoming_priority_conflict(
            town, entry, agents, vehicle_id):
        return max(gap, 0.0)
    if entry.control == Control.PRIORITY:
        return None
    if rules is None:
        return None
    if zebra is not None and zebra < gap + ZEBRA_CLEAR_M and gap > -0.5:
        return max(gap, 0.0)
    if rules.may_go(vehicle_id, entry, *vehicle_rows(agents), turn):
        return None
    return max(gap, 0.0)


class TownVehicle(IDMVehicle):
    """An NPC car or van/truck driving a random never-ending route through the town."""

    LANE_CHANGE_DELAY = 2.0

    def __init__(self, road: Road, town: Town, lane_index: tuple[str, str, int], s: float, object_id: int,
                 kind: SemanticClass, color: tuple[float, float, float], target_speed: float,
                 rng: np.random.Generator) -> None:
        lane = town.lane(lane_index)
        self.town = town
        self.object_id = object_id
        self.kind = kind
        self.color = color
        self.rng = rng
        if kind == SemanticClass.TRUCK:
            self.LENGTH, self.WIDTH, self.HEIGHT = 6.8, 2.3, 2.8
        else:
            self.LENGTH, self.WIDTH, self.HEIGHT = 4.5, 1.9, 1.5
        self._coords: dict[int, tuple[float, float]] | None = None
        self._stop_hold = False  # this decision: waiting at a stop sign (brake to a full stop near the line)
        self._yield_gap: float | None = None  # this decision: the gap to a give-way line ahead
        super().__init__(road, lane.position(s, 0.0), lane.heading_at(s), speed=target_speed * 0.5,
                         target_lane_index=lane_index, target_speed=target_speed,
                         route=[(lane_index[0], lane_index[1], None)])
        self._locate()
        self._extend_route()

    # highway-env looks up the closest lane among all lanes on every state update. Only ``decide``
    # reads the lane, so it is located there, among the target edge's two lanes.
    def on_state_update(self) -> None:
        """Nothing per integration step; see ``_locate``."""

    def _lane_coords(self, lane: AbstractLane) -> tuple[float, float]:
        """``lane.local_coordinates`` of the vehicle's position. During ``decide`` the vehicle does not
        move, and one decision asks for the same lane up to six times, so the answers are kept."""
        if self._coords is None:
            return lane.local_coordinates(self.position)
        hit = self._coords.get(id(lane))
        if hit is None:
            hit = lane.local_coordinates(self.position)
            self._coords[id(lane)] = hit
        return hit

    def _locate(self) -> None:
        """The lane of the target edge whose centre line is nearest (the first of equals). The exact lateral
        offsets are compared only when the cheap bound cannot tell (mid lane change): the nearest lane's
        coordinates are asked for later anyway, the other lane's mostly not."""
        frm, to, _ = self.target_lane_index
        lanes = self.town.network.graph[frm][to]
        k = clearly_nearest_lane(float(self.position[0]), float(self.position[1]), path_rows(lanes))
        if k < 0:
            lats = [abs(self._lane_coords(lane)[1]) for lane in lanes]
            k = lats.index(min(lats))
        self.lane_index = (frm, to, k)
        self.lane = lanes[k]

    def _extend_route(self) -> None:
        while len(self.route) < 4:
            last = self.route[-1]
            frm, to = random_next_edge(self.town, (last[0], last[1]), self.rng)
            self.route.append((frm, to, None))

    def path(self, lookahead_m: float) -> tuple[list[tuple[AbstractLane, float]], float]:
        """Lanes ahead along the route (same lane id) and the vehicle's coordinate on the first."""
        lanes, s0 = self.path_with_indices(lookahead_m)
        return [(lane, offset) for lane, offset, _ in lanes], s0

    def path_with_indices(self, lookahead_m: float) -> tuple[list[tuple[AbstractLane, float, tuple[str, str, int]]], float]:
        frm, to, k = self.target_lane_index
        lane = self.town.lane(self.target_lane_index)
        s0 = float(self._lane_coords(lane)[0])
        path = [(lane, 0.0, (frm, to, k))]
        total = lane.length
        started = False
        index = (frm, to, k)
        for rf, rt, _ in self.route:
            if (rf, rt) == (frm, to):
                started = True
                continue
            if not started or total - s0 > lookahead_m:
                continue
            index = self.town.next_lane(index, (rf, rt))
            nxt = self.town.lane(index)
            path.append((nxt, total, index))
            total += nxt.length
        return path, s0

    def _next_move(self) -> tuple[int, Command] | None:
        """Index in the route and command of the junction move after the current road, if any."""
        frm, to, _ = self.target_lane_index
        for k, (rf, rt, _) in enumerate(self.route):
            if (rf, rt) != (frm, to) and rf == to:
                return k, self.town.lane_info[(rf, rt, 0)].command
        return None

    def change_lane_policy(self) -> None:
        """Get into a lane the next junction move may start from; MOBIL only where any lane will do.

        Far from the stop line the vehicle changes lane when the target lane is clear; within 30 m it
        picks a move its lane allows instead. No lane changes inside junctions."""
        frm, to, k = self.target_lane_index
        if self.town.lane_info[self.target_lane_index].kind != "road":
            return
        lane = self.town.lane(self.target_lane_index)
        remaining = lane.length - self._lane_coords(lane)[0]
        move = self._next_move()
        count = self.town.lane_count((frm, to))
        allowed = lanes_for(move[1], count) if move is not None else tuple(range(count))
        if k in allowed:
            if len(allowed) > 1 and remaining >= 30.0 and self.enable_lane_change:
                super().change_lane_policy()
            return
        if remaining >= 30.0:
            if self._lane_clear((frm, to, allowed[0])):
                self.target_lane_index = (frm, to, allowed[0])
            return
        assert move is not None
        index = move[0]
        options = sorted(self.town.network.graph[to].keys())
        fits = [o for o in options if k in lanes_for(self.town.lane_info[(to, o, 0)].command, count)]
        self.route[index] = (to, fits[int(self.rng.integers(len(fits)))], None)
        del self.route[index + 1:]
        self._extend_route()

    def _lane_clear(self, lane_index: tuple[str, str, int]) -> bool:
        """No vehicle within 9 m along a lane of where this one would be."""
        lane = self.town.lane(lane_index)
        s0 = self._lane_coords(lane)[0]
        for v in self.road.vehicles:
            if v is self or math.hypot(*(v.position - self.position)) > 15.0:
                continue
            s, lat = lane.local_coordinates(v.position)
            if abs(lat) < 2.0 and abs(s - s0) < 9.0:
                return False
        return True

    def follow_road(self) -> None:
        """highway-env's ``follow_road``, with the lane coordinates of ``_lane_coords``."""
        lane = self.road.network.get_lane(self.target_lane_index)
        if lane.after_end(self.position, self._lane_coords(lane)[0]):
            self.target_lane_index = self.road.network.next_lane(self.target_lane_index, route=self.route,
                                                                 position=self.position,
                                                                 np_random=self.road.np_random)

    def steering_control(self, target_lane_index: tuple[str, str, int]) -> float:
        """highway-env's lane-following steering (same operations, same order), with the lane
        coordinates of ``_lane_coords`` and scalar clips (``np.clip`` on one number costs microseconds)."""
        target_lane = self.road.network.get_lane(target_lane_index)
        lane_coords = self._lane_coords(target_lane)
        lane_next_coords = lane_coords[0] + self.speed * self.TAU_PURSUIT
        lane_future_heading = target_lane.heading_at(lane_next_coords)
        lateral_speed_command = -self.KP_LATERAL * lane_coords[1]
        heading_command = np.arcsin(_clip(lateral_speed_command / not_zero(self.speed), -1, 1))
        heading_ref = lane_future_heading + _clip(heading_command, -np.pi / 4, np.pi / 4)
        heading_rate_command = self.KP_HEADING * hwe_wrap_to_pi(heading_ref - self.heading)
        slip_angle = np.arcsin(_clip(self.LENGTH / 2 / not_zero(self.speed) * heading_rate_command, -1, 1))
        steering_angle = np.arctan(2 * np.tan(slip_angle))
        steering_angle = _clip(steering_angle, -self.MAX_STEERING_ANGLE, self.MAX_STEERING_ANGLE)
        return float(steering_angle)

    def decide(self, agents: Agents, lights_state: list[LightState], enable_lane_change: bool,
               rules: JunctionRules | None = None) -> None:
        """Set this step's steering and acceleration (highway-env action dict). ``rules``: the world's
        junction rules (stop signs, give-way lines); without them unsignalled junctions are driven through."""
        if self.crashed:
            return
        self._coords = {}
        try:
            self._decide(agents, lights_state, enable_lane_change, rules)
        finally:
            self._coords = None

    def _decide(self, agents: Agents, lights_state: list[LightState], enable_lane_change: bool,
                rules: JunctionRules | None = None) -> None:
        self._locate()
        self.follow_road()
        self._extend_route()
        self.enable_lane_change = enable_lane_change
        self.change_lane_policy()
        limit = self.MAX_STEERING_ANGLE
        steering = min(limit, max(-limit, float(self.steering_control(self.target_lane_index))))
        lookahead = 12.0 + 3.0 * self.speed
        indexed, s0 = self.path_with_indices(lookahead)
        path = [(lane, offset) for lane, offset, _ in indexed]
        half = self.LENGTH / 2
        gap, lead_speed = path_gap(path, s0, half, agents, self.object_id, self.position, lookahead)
        zebra = crosswalk_gap(self.town, path, [i for _, _, i in indexed], s0, half, agents, lookahead)
        if zebra is not None and (gap is None or zebra < gap):
            gap, lead_speed = zebra, 0.0
        cruise = min(self.target_speed, curve_speed_limit(path, s0))
        if self.town.speed_limits_kmh:
            cruise = min(cruise, posted_speed_cap(self.town, path, [i for _, _, i in indexed], s0))
        self._stop_hold, self._yield_gap = False, None
        stop = self._stop_line_gap(path, s0, lights_state, agents, rules, zebra)
        if self._yield_gap is not None:  # approach a give-way line slowly enough to stop at it after a last look
            cruise = min(cruise, math.sqrt(YIELD_APPROACH_MPS ** 2 + 2.0 * CURVE_BRAKE_MPS2 * self._yield_gap))
        acc = idm_acceleration(self.speed, cruise, gap, self.speed - lead_speed)
        if stop is not None:
            acc = min(acc, idm_acceleration(self.speed, self.target_speed, stop, self.speed, min_gap_m=0.5))
            if self._stop_hold and stop < STOP_HOLD_M and self.speed < 1.5:
                acc = -8.0  # a full stop at the stop line, not a creep towards it
        acc = min(self.COMFORT_ACC_MAX, max(-8.0, float(acc)))
        Vehicle.act(self, {"steering": steering, "acceleration": acc})

    def _stop_line_gap(self, path: list[tuple[AbstractLane, float]], s0: float,
                       lights_state: list[LightState], agents: Agents, rules: JunctionRules | None = None,
                       zebra: float | None = None) -> float | None:
        """Gap to a stop line ahead whose light says stop (yellow only if a comfortable stop is possible), or
        at an unsignalled junction where the rules say wait (``junction_gap``)."""
        frm, to, _ = self.target_lane_index
        edges = [(frm, to)] + [(r[0], r[1]) for r in self.route if (r[0], r[1]) != (frm, to)]
        along = 0.0
        for (lane, offset), edge in zip(path, edges, strict=False):
            approach = self.town.approach_for_edge(edge)
            along = offset + lane.length
            if approach is None:
                entry = self.town.entry_for_edge(edge)
                if entry is None:
                    continue
                gap = along - 0.5 - s0 - self.LENGTH / 2
                if gap < -0.5:
                    return None
                k = edges.index(edge) + 1
                turn = self.town.lane_info[(*edges[k], 0)].command if k < len(edges) else None
                wait = junction_gap(self.town, rules, self.object_id, entry, turn, gap, agents, zebra)
                self._stop_hold = wait is not None and entry.control in STOP_CONTROLS
                if entry.control == Control.YIELD and rules is not None:
                    self._yield_gap = max(gap, 0.0)
                return wait
            state = lights_state[approach.index]
            gap = along - 0.5 - s0 - self.LENGTH / 2
            if gap < -0.5:
                return None
            if state == LightState.RED:
                return max(gap, 0.0)
            if state == LightState.YELLOW and self.speed ** 2 / (2 * max(gap, 0.1)) < 3.5:
                return max(gap, 0.0)
            turn = edges.index(edge) + 1
            if (turn < len(edges) and self.town.lane_info[(*edges[turn], 0)].command == Command.LEFT
                    and oncoming_conflict(self.town, approach, agents, self.object_id)):
                return max(gap, 0.0)  # unprotected left: wait for the oncoming traffic
            return None
        return None

    def next_turn(self) -> Command | None:
        """The command of the next junction move on this vehicle's route (the one it is on, inside a junction)."""
        frm, to, _ = self.target_lane_index
        info = self.town.lane_info.get((frm, to, 0))
        if info is not None and info.kind == "connector":
            return info.command
        following = next(((r[0], r[1]) for r in self.route if (r[0], r[1]) != (frm, to)), None)
        return None if following is None else self.town.lane_info[(*following, 0)].command

    def step(self, dt: float) -> None:
        super().step(dt)
        self.speed = max(self.speed, 0.0)

    def snapshot(self) -> ObjectSnapshot:
        return snapshot_of(self.object_id, self.kind, float(self.position[0]), float(self.position[1]),
                           float(self.heading), self.LENGTH, self.WIDTH, self.HEIGHT, self.color)


def step_vehicles(vehicles: list[TownVehicle | EgoVehicle], dt: float) -> None:
    """``step`` of many NPCs (``TownVehicle``) and the ego (``EgoVehicle``) in one go (highway-env's bicycle model).

    The per-vehicle NumPy calls on single numbers cost more than the arithmetic, so the trigonometry
    runs once over all vehicles. Each value goes through the same operations in the same order as
    in ``Vehicle.step``, and NumPy's ufuncs give an element of an array what they give one number,
    so every state stays bit for bit what the one-by-one step gave; the types stay too (heading a
    NumPy float, speed a Python float, the position array updated in place). Then each kind finishes as
    its own ``step`` does: an NPC counts its decision timer and never reverses; the ego clamps its speed.
    """
    if not vehicles:
        return
    for v in vehicles:
        v.clip_actions()
    speed = np.array([v.speed for v in vehicles], dtype=float)
    heading = np.array([v.heading for v in vehicles], dtype=float)
    steering = np.array([v.action["steering"] for v in vehicles], dtype=float)
    half_length = np.array([v.LENGTH / 2 for v in vehicles], dtype=float)
    beta = np.arctan(1 / 2 * np.tan(steering))
    course = heading + beta
    position = np.array([v.position for v in vehicles], dtype=float)
    position += np.stack([speed * np.cos(course), speed * np.sin(course)], axis=1) * dt
    heading += speed * np.sin(beta) / half_length * dt
    for v, (x, y), h in zip(vehicles, position.tolist(), heading, strict=True):
        v.position[0], v.position[1] = x, y  # Python floats hold the float64 values exactly
        v.heading = h
        if type(v) is EgoVehicle:  # EgoVehicle.step: Vehicle.step, then its speed clamp
            v.speed = min(v.MAX_SPEED, max(0.0, float(v.speed + v.action["acceleration"] * dt)))
        else:  # TownVehicle.step: IDMVehicle's timer, Vehicle.step, then no reversing
            v.timer += dt
            v.speed = max(v.speed + v.action["acceleration"] * dt, 0.0)
