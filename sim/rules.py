"""Right of way at unsignalled junctions: stop lines, all-way stops, give-way lines and who goes first.

Why a module of its own: the same rules are obeyed by the NPCs (``sim.traffic``), charged to the ego
(``sim.world``'s ``stop_sign`` and ``failed_to_yield``) and followed by the privileged autopilot; written
once here, the three cannot drift apart. The world keeps one ``JunctionRules`` and updates it every
step with where every vehicle is, so that an all-way stop's arrival order is one list that every driver
reads.

The rules:

- **Full stop.** At a STOP or ALL_WAY_STOP entry a vehicle has stopped when its speed fell under
  ``STOP_SPEED_MPS`` with its front bumper at most ``STOP_ZONE_M`` before the line (and not past it).
  A stop further back (behind a queue) does not count: the vehicle stops again at the line.
- **Arrival order.** Stopped vehicles queue per junction in the order they stopped (ids break ties).
  Only the first may go at an all-way stop (or at a two-way stop, among the stop-side vehicles), so
  four arms waiting at once cannot deadlock: the earliest arrival goes. A first in line that does not go
  within ``TURN_TIMEOUT_S`` of a free junction (a pedestrian on its crossing, a driver that waits) goes to
  the back of the queue.
- **Junction free.** Nobody goes while another vehicle is inside the junction (on one of its connectors).
- **Priority.** At STOP and YIELD entries, a vehicle goes only when no vehicle on a PRIORITY arm would
  reach its own line within the accepted gap (``YIELD_GAP_S``) or stands at it. Turning right, traffic
  arriving from the right does not conflict (it keeps to the far side of the road).
- **Failed to yield (the ego's infraction)**, sharply: having crossed the line of a STOP or YIELD entry,
  when the ego's front bumper enters a lane of a priority arm's traffic (``in_priority_lane``), a vehicle
  in it, heading into the junction, moving faster than ``CONFLICT_MIN_SPEED_MPS``, has its front bumper 0 to
  ``PRIORITY_LOOK_M`` before that point and would reach it within ``YIELD_CONFLICT_S``: it would have to brake
  for the ego, or hit it. Charged where the paths meet, not at our line: where buildings stand at the
  corner, a driver sees the cross street only after edging past the line towards it, as the rules of the road
  expect, and a car that stops short of the priority traffic's lane has yielded. Drivers accept gaps of
  ``YIELD_GAP_S`` (longer), so a driver that yields never comes near the line of the infraction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from towndrive.sim.geometry import right_of
from towndrive.sim.spec import (  # noqa: F401 (STOP_SPEED_MPS, STOP_ZONE_M re-exported: the world's full stop)
    STOP_SPEED_MPS,
    STOP_ZONE_M,
    YIELD_GAP_S,
)
from towndrive.sim.town import Command, Control, Edge, Entry, LaneIndex, Town

YIELD_CONFLICT_S = 3.0  # the failed-to-yield threshold: a priority vehicle this close in time had to brake
CONFLICT_MIN_SPEED_MPS = 1.0  # ... and moving at least this fast
PRIORITY_LOOK_M = 70.0  # how far up a priority arm drivers look
PRIORITY_STANDING_M = 3.0  # a priority vehicle standing this near its line (about to turn) is waited for
TURN_TIMEOUT_S = 4.0  # a first in line that does not go in this long (the junction free) goes to the back
HEADING_TOLERANCE_RAD = 0.7  # a vehicle heads into a junction by an arm within this of the arm's travel
STOP_CONTROLS = (Control.STOP, Control.ALL_WAY_STOP)
GIVE_WAY_CONTROLS = (Control.STOP, Control.YIELD)


def travel_vector(entry: Entry) -> np.ndarray:
    return np.array([math.cos(entry.travel_heading), math.sin(entry.travel_heading)])


def front_to_line(entry: Entry, position: np.ndarray, heading: float, half_length: float) -> float:
    """Distance from a vehicle's front bumper to an entry's line (its near edge), along the entry's travel;
    negative once the bumper is past it."""
    t = travel_vector(entry)
    front = position + half_length * np.array([math.cos(heading), math.sin(heading)])
    return float((entry.line_center - front) @ t)


def priority_arms(town: Town, entry: Entry, turn: Command | None) -> list[Entry]:
    """The priority arms of ``entry``'s junction whose traffic crosses or joins our way; turning right, arms
    whose traffic comes from the right are left out (it keeps to the far side)."""
    if entry.control not in GIVE_WAY_CONTROLS:
        return []
    mine = travel_vector(entry)
    return [other for other in town.entries_at(entry.node) if other.control == Control.PRIORITY
            and not (turn == Command.RIGHT and float(travel_vector(other) @ right_of(mine)) < -0.5)]


def _lateral(arm: Entry, points: np.ndarray) -> np.ndarray:
    """Across ``arm``'s travel (positive to its right), from the middle of its incoming lanes."""
    return (points - arm.line_center) @ right_of(travel_vector(arm))


def lane_offsets(town: Town, arm: Entry) -> list[float]:
    """The middles of ``arm``'s incoming lanes across its travel, as ``_lateral`` measures."""
    n = arm.lane_count
    return [(k - (n - 1) / 2) * town.lane_width for k in range(n)]


def in_priority_lane(town: Town, arm: Entry, offset: float, points: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
    """Whether ``points`` (one, or rows) lie in one of ``arm``'s incoming lanes (the one ``offset`` across), carried
    on through the junction, widened by ``margin_m`` either side."""
    return np.abs(_lateral(arm, points) - offset) < town.lane_width / 2 + margin_m


def _on_arm(town: Town, arm: Entry, positions: np.ndarray, headings: np.ndarray) -> np.ndarray:
    """Which of the vehicles (rows) head into the junction by ``arm`` within the band of its incoming lanes."""
    heading_ok = np.abs((headings - arm.travel_heading + np.pi) % (2 * np.pi) - np.pi) < HEADING_TOLERANCE_RAD
    return heading_ok & (np.abs(_lateral(arm, positions)) < arm.lane_count * town.lane_width / 2 + 0.6)


def priority_vehicles(town: Town, entry: Entry, positions: np.ndarray, headings: np.ndarray, half_lengths: np.ndarray,
                      turn: Command | None) -> list[tuple[int, float]]:
    """For the vehicles given (rows of the arrays), those on a priority arm of ``entry``'s junction heading into
    it (``priority_arms``), laterally within that arm's incoming lanes: (row, front bumper's distance before that
    arm's line)."""
    if len(positions) == 0:
        return []
    out: list[tuple[int, float]] = []
    for other in priority_arms(town, entry, turn):
        before = -((positions - other.line_center) @ travel_vector(other)) - half_lengths
        keep = _on_arm(town, other, positions, headings) & (before > -half_lengths) & (before < PRIORITY_LOOK_M)
        out += [(int(k), float(before[k])) for k in np.nonzero(keep)[0]]
    return out


def priority_conflict(town: Town, entry: Entry, positions: np.ndarray, headings: np.ndarray, speeds: np.ndarray,
                      half_lengths: np.ndarray, turn: Command | None, gap_s: float = YIELD_GAP_S) -> bool:
    """Whether priority traffic forbids going from ``entry`` now: a vehicle on a priority arm that would reach
    its line within ``gap_s``, or stands at it (see ``priority_vehicles``)."""
    for k, before in priority_vehicles(town, entry, positions, headings, half_lengths, turn):
        v = float(speeds[k])
        if before < PRIORITY_STANDING_M or (v > 0.5 and before / v < gap_s):
            return True
    return False


def failed_to_yield_by(town: Town, lanes: list[tuple[Entry, float]], point: np.ndarray, positions: np.ndarray,
                       headings: np.ndarray, speeds: np.ndarray, half_lengths: np.ndarray) -> int:
    """The row of a priority vehicle in one of ``lanes`` (arm, lane offset) the ego failed to yield to, its front
    bumper entering that lane at ``point`` now (see the module docstring), or -1: one whose front bumper is 0 to
    ``PRIORITY_LOOK_M`` before that point and would reach it within ``YIELD_CONFLICT_S``."""
    if len(positions) == 0:
        return -1
    for arm, offset in lanes:
        to_point = (point - positions) @ travel_vector(arm) - half_lengths
        in_lane = in_priority_lane(town, arm, offset, positions, margin_m=0.3)
        keep = _on_arm(town, arm, positions, headings) & in_lane & (to_point >= 0.0) & (to_point < PRIORITY_LOOK_M)
        for k in np.nonzero(keep)[0]:
            v = float(speeds[k])
            if v > CONFLICT_MIN_SPEED_MPS and to_point[k] / v < YIELD_CONFLICT_S:
                return int(k)
    return -1


@dataclass
class YieldCrossing:
    """The ego past a give-way line: the priority arms' lanes it has not entered yet, judged as it enters
    each (``failed_to_yield_by``); over once its front bumper leaves the circle of the junction's lines."""

    pending: list[tuple[Entry, float]]  # (arm, lane offset)
    centre: np.ndarray
    reach_m: float

    @classmethod
    def start(cls, town: Town, entry: Entry, turn: Command | None) -> YieldCrossing:
        centre = town.node_position(entry.node)
        reach = max(float(np.linalg.norm(e.line_center - centre)) for e in town.entries_at(entry.node))
        lanes = [(arm, offset) for arm in priority_arms(town, entry, turn) for offset in lane_offsets(town, arm)]
        return cls(lanes, centre, reach + 1.0)

    def near(self, front: np.ndarray) -> bool:
        return bool(self.pending) and float(np.linalg.norm(front - self.centre)) <= self.reach_m

    def entering(self, town: Town, front: np.ndarray) -> list[tuple[Entry, float]]:
        """The priority lanes the front bumper is in now and was not before (each is given once)."""
        entered = [lane for lane in self.pending if bool(in_priority_lane(town, *lane, front))]
        self.pending = [lane for lane in self.pending if all(lane is not e for e in entered)]
        return entered


@dataclass
class VehicleAt:
    """Where one vehicle is, for the junction rules: its id, the lane it is on (None off the network),
    its front bumper's distance to the line of the entry its edge leads to, and its speed."""

    vehicle_id: int
    lane: LaneIndex | None
    to_line_m: float
    speed: float


@dataclass
class JunctionRules:
    """The world's arrival queues and junction occupancy (see the module docstring)."""

    town: Town
    queues: dict[tuple[int, int], list[tuple[float, int]]] = field(default_factory=dict)  # node -> (stopped at, id)
    stopped: dict[int, int] = field(default_factory=dict)  # vehicle id -> the entry it made its full stop at
    occupants: dict[tuple[int, int], set[int]] = field(default_factory=dict)  # node -> ids on its connectors
    _head_free_s: dict[tuple[int, int], float] = field(default_factory=dict)

    def update(self, time_s: float, dt: float, vehicles: list[VehicleAt]) -> None:
        """Take in where every vehicle is after a step: full stops join their junction's queue; vehicles that
        left their entry's road leave it; a first in line that lets a free junction go by goes to the back."""
        town = self.town
        occupants: dict[tuple[int, int], set[int]] = {}
        present: set[int] = set()
        for v in vehicles:
            present.add(v.vehicle_id)
            if v.lane is None:
                continue
            info = town.lane_info.get(v.lane)
            if info is not None and info.kind == "connector" and info.node is not None:
                occupants.setdefault(info.node, set()).add(v.vehicle_id)
            entry = town.entry_for_edge(v.lane[:2])
            at = self.stopped.get(v.vehicle_id)
            if at is not None and (entry is None or entry.index != at):
                self._leave(v.vehicle_id)
                at = None
            if (at is None and entry is not None and entry.control in STOP_CONTROLS and v.speed < STOP_SPEED_MPS
                    and -0.5 <= v.to_line_m <= STOP_ZONE_M):
                self.stopped[v.vehicle_id] = entry.index
                self.queues.setdefault(entry.node, []).append((time_s, v.vehicle_id))
        for vid in [vid for vid in self.stopped if vid not in present]:
            self._leave(vid)
        self.occupants = occupants
        for node, queue in self.queues.items():
            if not queue or occupants.get(node):
                self._head_free_s[node] = 0.0
                continue
            waited = self._head_free_s.get(node, 0.0) + dt
            if waited >= TURN_TIMEOUT_S and len(queue) > 1:
                queue.append((time_s, queue.pop(0)[1]))
                waited = 0.0
            self._head_free_s[node] = waited

    def _leave(self, vehicle_id: int) -> None:
        entry = self.town.entries[self.stopped.pop(vehicle_id)]
        queue = self.queues.get(entry.node, [])
        if queue and queue[0][1] == vehicle_id:
            self._head_free_s[entry.node] = 0.0
        self.queues[entry.node] = [q for q in queue if q[1] != vehicle_id]

    def has_stopped(self, vehicle_id: int, entry: Entry) -> bool:
        return self.stopped.get(vehicle_id) == entry.index

    def first_in_line(self, vehicle_id: int, entry: Entry) -> bool:
        queue = self.queues.get(entry.node, [])
        return bool(queue) and queue[0][1] == vehicle_id

    def junction_free(self, node: tuple[int, int], vehicle_id: int) -> bool:
        """No vehicle but this one inside the junction."""
        return not (self.occupants.get(node, set()) - {vehicle_id})

    def may_go(self, vehicle_id: int, entry: Entry, positions: np.ndarray, headings: np.ndarray, speeds: np.ndarray,
               half_lengths: np.ndarray, ids: np.ndarray, turn: Command | None) -> bool:
        """Whether a vehicle at ``entry`` may enter the junction now (signals and priority arms: always; their
        own rules apply). The arrays describe the other road users (pedestrians are skipped)."""
        if entry.control in STOP_CONTROLS and not (self.has_stopped(vehicle_id, entry)
                                                   and self.first_in_line(vehicle_id, entry)):
            return False
        if entry.control not in (*STOP_CONTROLS, Control.YIELD):
            return True
        if not self.junction_free(entry.node, vehicle_id):
            return False
        others = ids != vehicle_id
        return not priority_conflict(self.town, entry, positions[others], headings[others], speeds[others],
                                     half_lengths[others], turn)


def turn_after(town: Town, route: list[Edge], index: int) -> Command | None:
    """The command of the junction move that follows route edge ``index`` (None where the route ends)."""
    if index + 1 >= len(route):
        return None
    return town.lane_info[(*route[index + 1], 0)].command
