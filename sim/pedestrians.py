"""Pedestrians who walk round junction corners and cross at zebra crossings.

A pedestrian waits at the kerb until the crossing's signal allows walking (the crossed arm's
traffic has red for long enough to get across) and no vehicle is on or about to enter the
crossing, then walks over; on the far kerb it turns the corner to the next crossing. Now and then
(configurable) one jaywalks: crosses without waiting for the signal, still not into a car.

At an unsignalled crossing (a zebra at a stop, give-way or priority junction) the pedestrian has the
right of way: it steps onto the zebra unless a vehicle is on it or could not stop before it
(``_cannot_stop``), and the vehicles stop for whoever is on it (``sim.traffic.crosswalk_gap``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba as nb
import numpy as np

from towndrive.sim.lights import TrafficLights
from towndrive.sim.objects import ObjectSnapshot, SemanticClass, snapshot_of
from towndrive.sim.town import ARM_VEC, Crosswalk, Town

STEP_AHEAD_M = 0.7  # how far ahead a pedestrian looks for a standing car's body
BODY_MARGIN_M = 0.5  # ... kept clear of it (the pedestrian's radius is 0.3 m)
FRONT_MARGIN_M = 2.0  # ... and of the space just ahead of its bumper, which its driver cannot see
DETOUR_AFTER_S = 1.5  # barred this long by a standing car, a pedestrian walks round its rear
DETOUR_CLEARANCE_M = 0.9  # distance kept from the car's end while walking round it
DEFAULT_HALF_SIZE = (2.3, 0.95)  # a car's half length and half width
MOVING_CAR_AHEAD_M = 1.2  # a moving car bars the way when it is near the point this far ahead of a pedestrian
MOVING_CAR_CLEAR_M2 = 2.8 ** 2  # ... within 2.8 m (squared)
ZEBRA_BRAKE_MPS2 = 3.0  # a driver stops for a pedestrian on a zebra at this deceleration or gentler
ZEBRA_REACTION_S = 0.5  # ... after this long
ZEBRA_MARGIN_M = 1.5  # ... this far short of the zebra
ZEBRA_TURN_S = 3.0  # a vehicle that has waited this long at an unsignalled zebra goes before newly arriving walkers
ZEBRA_WAIT_REACH_M = 14.0  # ... standing with its centre this near the zebra's centre, facing it (at a stop line too)
SHIRT_COLORS = [(0.80, 0.15, 0.15), (0.15, 0.35, 0.75), (0.95, 0.85, 0.20), (0.20, 0.60, 0.30),
                (0.90, 0.90, 0.90), (0.25, 0.25, 0.28), (0.85, 0.45, 0.10), (0.55, 0.25, 0.60)]


@dataclass
class Pedestrian:
    object_id: int
    position: np.ndarray
    heading: float
    speed_mps: float
    color: tuple[float, float, float]
    crosswalk: int  # the crossing it is at or on
    at_start: bool  # which kerb of it (start or end) it waits at or walks from
    state: str = "waiting"  # waiting | crossing | walking (round a corner)
    target: np.ndarray | None = None
    jaywalk: bool = False
    moving: bool = False
    blocked: bool = False  # a car stands in its way on the crossing
    yields: bool = True  # waits for cars in its way (scenarios can make one that does not)
    blocked_s: float = 0.0  # how long a standing car has barred the way
    detour: list[np.ndarray] = field(default_factory=list)  # waypoints round a standing car, then on to target

    LENGTH = 0.35
    WIDTH = 0.55
    HEIGHT = 1.75
    RADIUS = 0.3

    def snapshot(self) -> ObjectSnapshot:
        return snapshot_of(self.object_id, SemanticClass.PEDESTRIAN, float(self.position[0]),
                           float(self.position[1]), float(self.heading), self.LENGTH, self.WIDTH,
                           self.HEIGHT, self.color)


class PedestrianCrowd:
    """All pedestrians of a world and the rules they walk by."""

    def __init__(self, town: Town, count: int, rng: np.random.Generator, first_id: int,
                 jaywalk_probability: float = 0.0) -> None:
        self.town = town
        self.rng = rng
        self.jaywalk_probability = jaywalk_probability
        self.peds: list[Pedestrian] = []
        self._corner_next = self._link_corners()
        # Kerb-to-kerb length of each crossing (the same in both directions: hypot ignores signs).
        self._crossing_length = [math.hypot(*(cw.end - cw.start)) for cw in town.crosswalks]
        self._vehicle_waiting_since: dict[int, float] = {}  # unsignalled zebra -> when a vehicle began to wait at it
        crosswalks = town.crosswalks
        for k in range(count if crosswalks else 0):
            cw = crosswalks[int(rng.integers(len(crosswalks)))]
            at_start = bool(rng.random() < 0.5)
            pos = self._waiting_spot(cw, at_start, rng.uniform(0.0, 1.0, 2))
            self.peds.append(Pedestrian(first_id + k, pos, 0.0, float(rng.uniform(1.1, 1.6)),
                                        SHIRT_COLORS[int(rng.integers(len(SHIRT_COLORS)))], cw.index, at_start))

    @staticmethod
    def _waiting_spot(cw: Crosswalk, at_start: bool, jitter: np.ndarray) -> np.ndarray:
        """Where a newly placed pedestrian stands: at the crossing's kerb end, spread up to 0.6 m further
        onto the pavement and 0.8 m away from the junction, never towards the corner that turning cars cut."""
        here, there = (cw.start, cw.end) if at_start else (cw.end, cw.start)
        outward = (here - there) / max(float(np.linalg.norm(here - there)), 1e-6)
        return here + outward * 0.6 * jitter[0] + ARM_VEC[cw.arm] * 0.8 * jitter[1]

    def _link_corners(self) -> dict[tuple[int, bool], tuple[int, bool]]:
        """For each kerb end of a crossing, the nearest end of another crossing of the junction that can be
        walked to without setting foot on the road: the one round the same corner, or at a T-junction's far
        side the crossing of the other arm along the sidewalk. An end with none (there is always one) would send
        the pedestrian back over the same crossing."""
        ends = [(cw.index, s, cw.start if s else cw.end, cw.node) for cw in self.town.crosswalks for s in (True, False)]
        links: dict[tuple[int, bool], tuple[int, bool]] = {}
        for idx, s, p, node in ends:
            best = None
            for idx2, s2, p2, node2 in ends:
                if node2 != node or idx2 == idx:
                    continue
                d = float(np.linalg.norm(p2 - p))
                if (best is None or d < best[0]) and self._walkable(p, p2):
                    best = (d, (idx2, s2))
            links[(idx, s)] = best[1] if best else (idx, s)
        return links

    def _walkable(self, a: np.ndarray, b: np.ndarray) -> bool:
        """Whether the straight walk from a to b stays off the lanes (sampled every metre)."""
        n = max(2, int(np.linalg.norm(b - a)))
        return not any(self.town.on_road(a + (b - a) * t) for t in np.linspace(0.0, 1.0, n + 1)[1:-1])

    def walk_allowed(self, cw: Crosswalk, lights: TrafficLights, crossing_time_s: float) -> bool:
        """At a signalled crossing, while the traffic it crosses has red long enough to get across; at an
        unsignalled one always (the pedestrian still waits for a gap in the traffic, ``_vehicle_blocks``)."""
        if cw.approach < 0:
            return True
        return lights.red_remaining_s(cw.approach) > crossing_time_s

    @staticmethod
    def _vehicle_blocks(cw: Crosswalk, vehicles: np.ndarray, speeds: np.ndarray, headings: np.ndarray,
                        point: np.ndarray, radius_m: float) -> bool:
        """A vehicle on the crossing near the pedestrian's line, or about to drive onto it."""
        if len(vehicles) == 0:
            return False
        d = np.linalg.norm(vehicles - point, axis=1)
        if np.any(d < radius_m):
            return True
        centre = cw.polygon.mean(axis=0)
        to_cw = centre - vehicles
        dist = np.linalg.norm(to_cw, axis=1)
        heading_vec = np.stack([np.cos(headings), np.sin(headings)], axis=1)
        approaching = np.sum(heading_vec * to_cw, axis=1) > 0
        time_to = dist / np.maximum(speeds, 0.1)
        return bool(np.any(approaching & (dist < 25.0) & (time_to < 4.0) & (speeds > 0.5)))

    @staticmethod
    def _cannot_stop(cw: Crosswalk, vehicles: np.ndarray, speeds: np.ndarray, headings: np.ndarray,
                     point: np.ndarray, sizes: np.ndarray | None) -> bool:
        """At an unsignalled zebra: a moving vehicle right beside the pedestrian or on the zebra, or heading for
        it too fast to stop comfortably before it (the pedestrian has the right of way, not a death wish). A
        standing vehicle does not hold the pedestrian up: it is waiting for it, and a crossing pedestrian walks
        round a car that bars the way (``_look_out``)."""
        moving = speeds > 0.5
        if not np.any(moving):
            return False
        vehicles, speeds, headings = vehicles[moving], speeds[moving], headings[moving]
        sizes = sizes[moving] if sizes is not None else None
        if np.any(np.linalg.norm(vehicles - point, axis=1) < 3.0):
            return True
        centre = cw.polygon.mean(axis=0)
        along = cw.polygon[1] - cw.polygon[0]
        half_depth = float(np.linalg.norm(along)) / 2
        u = along / (2 * half_depth)
        across = np.array([-u[1], u[0]])
        half_width = float(np.linalg.norm(cw.polygon[2] - cw.polygon[1])) / 2
        half_length = sizes[:, 0] if sizes is not None else np.full(len(vehicles), DEFAULT_HALF_SIZE[0])
        d = vehicles - centre
        on = (np.abs(d @ u) < half_depth + half_length) & (np.abs(d @ across) < half_width + 0.5)
        if np.any(on):
            return True
        dist = np.linalg.norm(d, axis=1)
        heading_vec = np.stack([np.cos(headings), np.sin(headings)], axis=1)
        approaching = np.sum(heading_vec * -d, axis=1) > 0.3 * dist
        to_zebra = dist - half_depth - half_length
        stopping = speeds * speeds / (2 * ZEBRA_BRAKE_MPS2) + speeds * ZEBRA_REACTION_S + ZEBRA_MARGIN_M
        return bool(np.any(approaching & (dist < 45.0) & (to_zebra < stopping)))

    def _vehicles_turn(self, cw: Crosswalk, vehicles: np.ndarray, speeds: np.ndarray, headings: np.ndarray,
                       now_s: float) -> bool:
        """Whether a vehicle has stood waiting at an unsignalled zebra for ``ZEBRA_TURN_S``: then pedestrians
        who arrive let it go first, until it has gone over (a pedestrian would otherwise step out as soon as it
        starts to roll, slow enough to stop again). Without turns, pedestrians who keep arriving (or who walk back and forth
        round a T-junction's corners) would hold the vehicle for ever; with them, whoever is on the zebra
        still crosses first."""
        centre = cw.polygon.mean(axis=0)
        d = centre - vehicles
        dist = np.hypot(d[:, 0], d[:, 1])
        facing = np.cos(headings) * d[:, 0] + np.sin(headings) * d[:, 1] > 0.7 * dist
        near = (dist < ZEBRA_WAIT_REACH_M) & facing
        if not np.any(near):  # the vehicle has gone over (or none came): the turn is over
            self._vehicle_waiting_since.pop(cw.index, None)
            return False
        if np.any(near & (speeds < 0.3)):
            self._vehicle_waiting_since.setdefault(cw.index, now_s)
        since = self._vehicle_waiting_since.get(cw.index)
        return since is not None and now_s - since >= ZEBRA_TURN_S

    def step(self, dt: float, lights: TrafficLights, vehicles: np.ndarray, speeds: np.ndarray,
             headings: np.ndarray, tick: int = 0, sizes: np.ndarray | None = None) -> None:
        """Move everyone one tick. Waiting pedestrians look up at the signal every fourth tick (5 Hz).
        ``sizes`` holds each vehicle's half length and half width (default: a car's)."""
        if sizes is None:
            sizes = np.tile(DEFAULT_HALF_SIZE, (len(vehicles), 1))
        # Crossing pedestrians look out for cars at 10 Hz; all who look this tick do it in one go (each
        # looks from where it stands before its own step, which is where the loop below finds it).
        looking = [ped for ped in self.peds
                   if ped.state == "crossing" and ped.yields and (tick + ped.object_id) % 2 == 0]
        in_the_way: dict[int, tuple[bool, int]] = {}
        if looking:
            where = np.array([(ped.position[0], ped.position[1], ped.heading) for ped in looking], dtype=float)
            moving, standing = cars_in_the_way(where, vehicles, speeds, headings, sizes)
            in_the_way = dict(zip(map(id, looking), zip(moving.tolist(), standing.tolist(), strict=True),
                                  strict=True))
        if tick % 4 == 0 and len(vehicles):
            # A vehicle's wait at a zebra counts from when it stood there, not from when the next walker came to
            # ask (one who arrives and asks at once would otherwise always find the clock just started).
            for index in {ped.crosswalk for ped in self.peds if ped.state == "crossing" and not ped.jaywalk}:
                cw = self.town.crosswalks[index]
                if cw.approach < 0:
                    self._vehicles_turn(cw, vehicles, speeds, headings, tick * dt)
        for ped in self.peds:
            ped.moving = False
            if ped.state == "waiting":
                if (tick + ped.object_id) % 4:
                    continue
                cw = self.town.crosswalks[ped.crosswalk]
                there = cw.end if ped.at_start else cw.start
                crossing_time = self._crossing_length[ped.crosswalk] / ped.speed_mps + 1.0
                if not ped.jaywalk and self.jaywalk_probability > 0 and self.rng.random() < self.jaywalk_probability * dt:
                    ped.jaywalk = True
                go = ped.jaywalk or self.walk_allowed(cw, lights, crossing_time)
                if go and cw.approach < 0 and not ped.jaywalk:  # a zebra with the right of way
                    go = not self._cannot_stop(cw, vehicles, speeds, headings, ped.position, sizes)
                    go = go and not self._vehicles_turn(cw, vehicles, speeds, headings, tick * dt)
                elif go:
                    go = not self._vehicle_blocks(cw, vehicles, speeds, headings, ped.position, 7.0)
                if go:
                    ped.state, ped.target = "crossing", there.copy()
            elif ped.state == "crossing":
                if id(ped) in in_the_way:
                    self._look_out(ped, *in_the_way[id(ped)], vehicles, headings, sizes, 2 * dt)
                if ped.blocked:
                    continue  # a car is in the way: wait on the crossing
                if ped.detour:
                    if self._walk_to(ped, ped.detour[0], dt):
                        ped.detour.pop(0)
                    continue
                if self._advance(ped, dt):
                    ped.jaywalk = False
                    ped.at_start = not ped.at_start
                    nxt, nxt_start = self._corner_next[(ped.crosswalk, ped.at_start)]
                    nxt_cw = self.town.crosswalks[nxt]
                    ped.crosswalk, ped.at_start = nxt, nxt_start
                    ped.state, ped.target = "walking", (nxt_cw.start if nxt_start else nxt_cw.end).copy()
            elif ped.state == "walking" and self._advance(ped, dt):
                ped.state, ped.target = "waiting", None

    def _look_out(self, ped: Pedestrian, moving_car: bool, standing: int, vehicles: np.ndarray,
                  headings: np.ndarray, sizes: np.ndarray, dt: float) -> None:
        """Wait for a moving car close to where the next steps go, and for a standing car whose body bars
        them (one that stopped with its nose on the crossing); after ``DETOUR_AFTER_S`` of the latter, walk
        round its rear instead of waiting for ever (the car may be waiting for the pedestrian).
        ``moving_car`` and ``standing`` (a vehicle index, -1: none): ``cars_in_the_way``, worked out for all
        who look this tick at once."""
        ped.blocked = moving_car
        if ped.blocked or standing < 0:
            ped.blocked_s = 0.0
            return
        ped.blocked, ped.blocked_s = True, ped.blocked_s + dt
        if ped.blocked_s >= DETOUR_AFTER_S:
            ped.detour = self._detour(ped, vehicles[standing], float(headings[standing]), sizes[standing])
            ped.blocked, ped.blocked_s = False, 0.0

    @staticmethod
    def _detour(ped: Pedestrian, centre: np.ndarray, heading: float, half_size: np.ndarray) -> list[np.ndarray]:
        """Waypoints round a standing vehicle's rear: aside, along its side to clear of its back, then across to
        the other side; from there the crossing goes on. Behind, never in front: the car may drive off at any
        moment (it does not reverse), and its driver cannot see someone close to its front corner."""
        ex = np.array([math.cos(heading), math.sin(heading)])
        ey = np.array([-ex[1], ex[0]])
        rel = ped.position - centre
        x, y = float(rel @ ex), float(rel @ ey)
        side = math.copysign(max(abs(y), half_size[1] + DETOUR_CLEARANCE_M), y)  # step aside first if ahead of it
        back = -(half_size[0] + DETOUR_CLEARANCE_M)
        return [centre + ex * x + ey * side, centre + ex * back + ey * side, centre + ex * back - ey * side]

    @classmethod
    def _advance(cls, ped: Pedestrian, dt: float) -> bool:
        """Walk towards the target; True on arrival."""
        assert ped.target is not None
        return cls._walk_to(ped, ped.target, dt)

    @staticmethod
    def _walk_to(ped: Pedestrian, goal: np.ndarray, dt: float) -> bool:
        """Walk towards ``goal``; True on arrival. Plain floats: two-element arrays cost more
        in call overhead than in arithmetic (each coordinate goes through the same operations)."""
        px, py = float(ped.position[0]), float(ped.position[1])
        dx, dy = float(goal[0]) - px, float(goal[1]) - py
        dist = math.hypot(dx, dy)
        step = ped.speed_mps * dt
        if dist <= step:
            ped.position = goal.copy()
            return True
        ped.heading = math.atan2(dy, dx)
        ped.position = np.array([px + dx / dist * step, py + dy / dist * step])
        ped.moving = True
        return False


@nb.njit(cache=True, nogil=True)
def cars_in_the_way(peds: np.ndarray, vehicles: np.ndarray, speeds: np.ndarray, headings: np.ndarray,
                    sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What bars each pedestrian's next steps; ``peds`` rows are (x, y, heading).

    Returns, per pedestrian: whether a moving car (over 0.5 m/s) is within 2.8 m of the point
    ``MOVING_CAR_AHEAD_M`` ahead of it; and the index of the first standing vehicle (0.5 m/s or less) within
    8 m of the point ``STEP_AHEAD_M`` ahead whose body (``sizes``: half length, half width) plus
    ``BODY_MARGIN_M`` all round, ``FRONT_MARGIN_M`` ahead of its bumper, holds that point (-1: none).
    One compiled loop for all pedestrians who look in a tick: the per-pedestrian NumPy calls on a few
    dozen numbers cost more than the arithmetic. Every value goes through the operations of the NumPy
    formulation it replaced (``tests/test_world_speed_parity.py`` keeps that as the oracle), in the same
    order, with libm's cos and sin as ``math`` has them.
    """
    n, m = peds.shape[0], vehicles.shape[0]
    moving = np.zeros(n, np.bool_)
    standing = np.full(n, -1, np.int64)
    for i in range(n):
        c, s = math.cos(peds[i, 2]), math.sin(peds[i, 2])
        mx, my = peds[i, 0] + MOVING_CAR_AHEAD_M * c, peds[i, 1] + MOVING_CAR_AHEAD_M * s
        sx, sy = peds[i, 0] + STEP_AHEAD_M * c, peds[i, 1] + STEP_AHEAD_M * s
        for k in range(m):
            if speeds[k] > 0.5:
                dx, dy = vehicles[k, 0] - mx, vehicles[k, 1] - my
                if dx * dx + dy * dy < MOVING_CAR_CLEAR_M2:
                    moving[i] = True
                    break
        for k in range(m):
            dx, dy = sx - vehicles[k, 0], sy - vehicles[k, 1]
            if not (dx * dx + dy * dy < 64.0 and speeds[k] <= 0.5):
                continue
            ck, sk = math.cos(headings[k]), math.sin(headings[k])
            along, across = dx * ck + dy * sk, -dx * sk + dy * ck
            front = FRONT_MARGIN_M if along > 0 else BODY_MARGIN_M
            if -sizes[k, 0] - BODY_MARGIN_M < along < sizes[k, 0] + front and abs(across) < sizes[k, 1] + BODY_MARGIN_M:
                standing[i] = k
                break
    return moving, standing
