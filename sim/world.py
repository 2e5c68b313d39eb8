"""The simulated world: town, lights, NPC traffic, pedestrians and the ego, stepped in 2D.

The world is the ground truth. It knows nothing of cameras: the renderer reads
``object_snapshots()`` and ``lights.states``; the environment reads ``ego_state()`` and the
infractions. Every random choice comes from one seeded generator, so a seed and a list of
actions replay bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from highway_env.road.road import Road

from towndrive.sim.ego import EgoVehicle
from towndrive.sim.geometry import circle_polygon_intersect, polygons_intersect, rect_corners, wrap_to_pi
from towndrive.sim.lights import LightTiming, TrafficLights
from towndrive.sim.objects import CAR_COLORS, SIGN_ID_BASE, LightState, ObjectSnapshot, SemanticClass, snapshot_of
from towndrive.sim.path_filter import points_within
from towndrive.sim.pedestrians import PedestrianCrowd
from towndrive.sim.routes import command_at, edge_length, random_route, route_length, shortest_route
from towndrive.sim.rules import (
    GIVE_WAY_CONTROLS,
    STOP_CONTROLS,
    JunctionRules,
    VehicleAt,
    YieldCrossing,
    failed_to_yield_by,
    front_to_line,
    turn_after,
)
from towndrive.sim.spec import ROAD, STEP_S, STOP_SPEED_MPS, STOP_ZONE_M
from towndrive.sim.town import (
    Approach,
    Command,
    Control,
    Edge,
    Entry,
    LaneLocation,
    Sign,
    Town,
    TownConfig,
    generate_town,
)
from towndrive.sim.traffic import Agents, TownVehicle, step_vehicles

PEDESTRIAN_ID_BASE = 1000
EGO_ID = 999
ROUTE_ARRIVAL_M = 5.0  # the car has arrived when this close to the route's end (the episode ends)
PARKED_ID_BASE = 5000  # parked car k of the town is object PARKED_ID_BASE + k (below SIGN_ID_BASE)
PARKED_VIEW_M = 160.0  # parked cars this near the ego are in object_snapshots (the camera sees no further in towns)
SIGN_POST_RADIUS_M = 0.05  # a sign's post, for collisions (light poles are 0.15 m)
SPEEDING_TOLERANCE = 0.10  # over the posted limit by more than this share ...
SPEEDING_MIN_S = 1.0  # ... for this long is speeding; the stretch ends back at or under the limit


@dataclass(frozen=True)
class WorldConfig:
    """What lives in the town besides the roads. Defaults run out of the box."""

    town: TownConfig = field(default_factory=TownConfig)
    lights: LightTiming = field(default_factory=LightTiming)
    npc_count: int = 16
    truck_fraction: float = 0.2
    npc_speed_range_mps: tuple[float, float] = (7.0, 11.0)
    pedestrian_count: int = 24
    jaywalk_probability: float = 0.0  # per pedestrian per second of waiting
    enable_lane_change: bool = True
    dt_s: float = STEP_S
    npc_decision_every: int = 2  # NPCs decide at 10 Hz (staggered), integrate at 20 Hz, as highway-env does
    npc_far_decision_every: int = 4  # beyond npc_near_radius_m of the ego they decide at 5 Hz (cf. CARLA's hybrid mode)
    npc_near_radius_m: float = 60.0
    npc_jam_teleport_s: float = 10.0  # an NPC standing this long inside a junction (or crashed) is moved elsewhere
    npc_teleport_min_m: float = 50.0  # ... at least this far from the ego, out of its sight (0: never teleport)
    route_min_length_m: float = 300.0
    route_deviation_s: float = 2.0  # how long off the route before it counts


@dataclass(frozen=True)
class Infraction:
    """One ground-truth infraction of the ego."""

    kind: str  # collision_vehicle | collision_pedestrian | collision_static | off_road | wrong_way |
    #            red_light | route_deviation | stop_sign | failed_to_yield | speeding
    time_s: float
    x: float
    y: float
    other_id: int = 0  # the vehicle's or pedestrian's id; the approach index for a red light; the entry index
    #                    for a stop sign; the posted limit (km/h) for speeding
    other_kind: str = ""  # car | truck | pedestrian | static | traffic_light | stop_sign | speed_limit | "" (none)
    approach: int = -1  # the signalled approach (its light and stop bar) the infraction concerns, if any
    heading: float = 0.0  # the ego's heading, radians
    speed_mps: float = 0.0  # the ego's speed


TERMINAL_INFRACTIONS = {"collision_vehicle", "collision_pedestrian", "collision_static", "off_road"}


@dataclass(frozen=True)
class NextLight:
    approach: int
    state: LightState
    distance_m: float  # from the ego's front bumper to the stop bar's near edge


@dataclass(frozen=True)
class NextControl:
    """The next junction entry on the route and what controls it."""

    entry: int
    control: Control
    distance_m: float  # from the ego's front bumper to the stop or give-way line's near edge
    approach: int  # the signalled approach (Control.SIGNAL), else -1


# An evaluation cycles through a handful of towns; more would only hold memory. Measured: a cached town holds
# about 1.3 MB and saves about 65 ms of generation per reset into it (bench/README.md, bench_memory_soak.py).
TOWN_CACHE_SIZE = 8


@lru_cache(maxsize=TOWN_CACHE_SIZE)
def cached_town(config: TownConfig, seed: int) -> Town:
    """Towns are immutable once built; the last ``TOWN_CACHE_SIZE`` (config, seed) pairs are kept per process."""
    return generate_town(config, seed)


class StaticObstacles:
    """Buildings (rectangles) and poles/trunks (circles) in a spatial hash for collision tests."""

    CELL_M = 10.0
    CLEAR_M = 0.1  # shapes whose bounding boxes are this far apart cannot touch: no exact test needed

    def __init__(self, town: Town) -> None:
        self.grid: dict[tuple[int, int], list[tuple[str, np.ndarray, float, tuple[float, float, float, float]]]] = {}
        for b in town.buildings:
            lo, hi = b.footprint.min(axis=0), b.footprint.max(axis=0)
            self._add(("rect", b.footprint, 0.0), lo, hi)
        for p in town.poles:
            self._add(("circle", p, Town.POLE_RADIUS_M), p - 1, p + 1)
        for t in town.trees:
            self._add(("circle", t.position, Town.TRUNK_RADIUS_M), t.position - 1, t.position + 1)
        for g in town.signs:
            self._add(("circle", g.position, SIGN_POST_RADIUS_M), g.position - 1, g.position + 1)
        for c in town.parked_cars:
            rect = rect_corners(c.position, c.heading, c.length_m, c.width_m)
            self._add(("rect", rect, 0.0), rect.min(axis=0), rect.max(axis=0))

    def _add(self, item: tuple[str, np.ndarray, float], lo: np.ndarray, hi: np.ndarray) -> None:
        """File a shape under every cell its box [lo, hi] touches, with its exact bounding box."""
        kind, shape, r = item
        box_lo = shape.min(axis=0) if kind == "rect" else shape - r
        box_hi = shape.max(axis=0) if kind == "rect" else shape + r
        box = (float(box_lo[0]), float(box_lo[1]), float(box_hi[0]), float(box_hi[1]))
        c = self.CELL_M
        for i in range(int(math.floor(lo[0] / c)), int(math.floor(hi[0] / c)) + 1):
            for j in range(int(math.floor(lo[1] / c)), int(math.floor(hi[1] / c)) + 1):
                self.grid.setdefault((i, j), []).append((kind, shape, r, box))

    def hits(self, polygon: np.ndarray) -> bool:
        """Whether a convex polygon touches any building, pole or trunk."""
        c = self.CELL_M
        lo, hi = polygon.min(axis=0), polygon.max(axis=0)
        clear = self.CLEAR_M
        x0, y0, x1, y1 = float(lo[0]) - clear, float(lo[1]) - clear, float(hi[0]) + clear, float(hi[1]) + clear
        for i in range(int(math.floor(lo[0] / c)), int(math.floor(hi[0] / c)) + 1):
            for j in range(int(math.floor(lo[1] / c)), int(math.floor(hi[1] / c)) + 1):
                for kind, shape, r, box in self.grid.get((i, j), []):
                    if box[0] > x1 or box[2] < x0 or box[1] > y1 or box[3] < y0:
                        continue  # 10 cm or more apart on an axis: the exact tests below would say no
                    if kind == "rect" and polygons_intersect(polygon, shape):
                        return True
                    if kind == "circle" and circle_polygon_intersect(shape, r, polygon):
                        return True
        return False


def _maybe_within(items: list, positions: np.ndarray | None, centre: np.ndarray, radius_m: float) -> list:
    """The items that may lie within ``radius_m`` of a point, in order: a squared-distance test with
    1 cm to spare, so that only the exact test that follows decides. ``positions`` are the items'
    positions as an (N, 2) array if the caller has them (None: read ``item.position``)."""
    if not items:
        return []
    if positions is None:
        positions = np.concatenate([item.position for item in items]).reshape(-1, 2)
    keep = points_within(positions, float(centre[0]), float(centre[1]), (radius_m + 0.01) ** 2)
    return [item for item, k in zip(items, keep.tolist(), strict=True) if k]


class World:
    """One episode's world. Build it with a town, a config and a seed; step it with ego actions."""

    def __init__(self, town: Town, config: WorldConfig, seed: int, start: tuple[str, str, int] | None = None,
                 start_s: float = 8.0, goal: Edge | None = None, spawn_traffic: bool = True) -> None:
        self.town = town
        self.config = config
        self.rng = np.random.default_rng(seed)
        self.time_s = 0.0
        self.step_count = 0
        self.lights = TrafficLights(town, config.lights, self.rng)
        self.road = Road(network=town.network, vehicles=[], np_random=np.random.RandomState(seed % (2**32)))
        # Ego and its route.
        roads = town.road_lanes()
        if start is None:
            start = roads[int(self.rng.integers(len(roads)))]
        lane = town.lane(start)
        self.ego = EgoVehicle(self.road, lane.position(start_s, 0.0), lane.heading_at(start_s), 0.0)
        self.road.vehicles.append(self.ego)
        if goal is None:
            self.route = random_route(town, start[:2], self.rng, config.route_min_length_m)
        else:
            self.route = shortest_route(town, start[:2], goal)
        self.route_total_m = route_length(town, self.route)
        self._route_starts = np.concatenate([[0.0], np.cumsum([edge_length(town, e) for e in self.route])])
        self.route_index = 0
        self.route_s = start_s
        self._off_route_s = 0.0
        self.deviated = False
        self.npcs: list[TownVehicle] = []
        self._jam_s: dict[int, float] = {}  # how long each NPC has stood jammed (see _unjam_npcs)
        self._vsize: np.ndarray | None = None  # vehicles' half lengths and widths (fixed; a teleport keeps the car)
        self.crowd = PedestrianCrowd(town, config.pedestrian_count if spawn_traffic else 0, self.rng,
                                     PEDESTRIAN_ID_BASE, config.jaywalk_probability)
        if spawn_traffic:
            for _ in range(config.npc_count):
                self.spawn_npc()
        self.static = StaticObstacles(town)
        self.junctions = JunctionRules(town)  # arrival queues at stop signs, junction occupancy (sim.rules)
        self._unsignalled = any(e.control != Control.SIGNAL for e in town.entries)
        self._entry_visit: int | None = None  # the stop or give-way entry whose road the ego is on
        self._entry_stopped = False  # ... and whether it made a full stop at its line on this visit
        self._entry_to_line: float | None = None  # the front bumper's distance to that line a step ago
        self._yielding: YieldCrossing | None = None  # a give-way line crossed: the priority lanes not yet entered
        self._over_limit_s = 0.0  # how long the ego has been over the posted limit (plus tolerance)
        self._speeding = False  # a speeding stretch is on (charged once)
        assert len(town.parked_cars) < SIGN_ID_BASE - PARKED_ID_BASE
        self._parked = [snapshot_of(PARKED_ID_BASE + k, SemanticClass.CAR, float(c.position[0]), float(c.position[1]),
                                    float(c.heading), c.length_m, c.width_m, c.height_m, c.color)
                        for k, c in enumerate(town.parked_cars)]
        self._parked_xy = np.array([(p.x, p.y) for p in self._parked]).reshape(-1, 2)
        self.infractions: list[Infraction] = []
        self.new_infractions: list[Infraction] = []
        self._wrong_way = False
        self._contacts: set[tuple[str, int]] = set()  # ongoing collisions / off-road, counted once each
        self._previous_front: np.ndarray | None = None  # the front bumper a step ago (red-light runs)
        self._last_approach: int | None = None  # the approach the car came by, while in its junction
        self._charged_approach: int | None = None  # a red-light run charged at this approach on this visit
        self.ego_lane: tuple[tuple[str, str, int], float, float] | None = town.locate(self.ego.position, self.ego.heading)
        self.distance_m = 0.0
        self._snapshots: list[ObjectSnapshot] = []
        self._snapshots_key: tuple = ()
        self._command: tuple[list[Edge], int, int, float, Command] | None = None  # see command()

    # ---------------------------------------------------------------- population
    @property
    def pedestrians(self) -> list:
        return self.crowd.peds

    def spawn_npc(self, lane_index: tuple[str, str, int] | None = None, s: float | None = None,
                  kind: SemanticClass | None = None, color: tuple[float, float, float] | None = None,
                  target_speed: float | None = None, min_gap_m: float = 14.0) -> TownVehicle | None:
        """Add one NPC, at a random free place unless told where. Returns None if no room was found."""
        place = self._road_place(lane_index, s, min_gap_m, min_gap_m)
        if place is None:
            return None
        k = kind if kind is not None else (SemanticClass.TRUCK if self.rng.random() < self.config.truck_fraction
                                           else SemanticClass.CAR)
        col = color or CAR_COLORS[int(self.rng.integers(len(CAR_COLORS)))]
        speed = target_speed if target_speed is not None else float(self.rng.uniform(*self.config.npc_speed_range_mps))
        npc = TownVehicle(self.road, self.town, *place, 1 + len(self.npcs), k, col, speed, self.rng)
        self.npcs.append(npc)
        self._vsize = None
        self.road.vehicles.append(npc)
        return npc

    def _road_place(self, lane_index: tuple[str, str, int] | None, s: float | None, min_gap_m: float,
                    ego_clear_m: float, skip: TownVehicle | None = None) -> tuple[tuple[str, str, int], float] | None:
        """A place on a road lane: the given lane and ``s`` where given, else drawn at random until it is
        ``min_gap_m`` from every NPC but ``skip`` and ``ego_clear_m`` from the ego (50 tries; None if none is).
        A given lane is taken as it is."""
        roads = self.town.road_lanes()
        for _ in range(50):
            li = lane_index or roads[int(self.rng.integers(len(roads)))]
            lane = self.town.lane(li)
            ss = s if s is not None else float(self.rng.uniform(6.0, max(7.0, lane.length - 25.0)))
            if lane_index is not None:
                return li, ss
            pos = lane.position(ss, 0.0)
            if float(np.linalg.norm(pos - self.ego.position)) < ego_clear_m:
                continue
            if any(float(np.linalg.norm(pos - v.position)) < min_gap_m for v in self.npcs if v is not skip):
                continue
            return li, ss
        return None

    # ---------------------------------------------------------------- jams
    def _unjam_npcs(self, dt: float) -> bool:
        """SUMO's time-to-teleport, for NPCs: one that has stood still inside a junction (where only a
        deadlock holds anyone up for long: two cars each in the other's path) or stood crashed for
        ``npc_jam_teleport_s`` is moved to a free place on a road, out of the ego's sight."""
        if self.config.npc_teleport_min_m <= 0:
            return False
        moved = False
        lane_info, jam_s, limit = self.town.lane_info, self._jam_s, self.config.npc_jam_teleport_s
        for k, npc in enumerate(self.npcs):
            jammed = npc.speed < 0.1 and (npc.crashed or getattr(lane_info.get(npc.lane_index), "kind", None) == "connector")
            jam_s[npc.object_id] = jam_s.get(npc.object_id, 0.0) + dt if jammed else 0.0
            if jam_s[npc.object_id] >= limit:
                self._jam_s[npc.object_id] = 0.0
                self._teleport(k)
                moved = True
        return moved

    def _teleport(self, k: int) -> None:
        """Replace NPC ``k`` by the same car (id, kind, colour, cruise speed) on a free road lane far away."""
        old = self.npcs[k]
        place = self._road_place(None, None, 14.0, self.config.npc_teleport_min_m, skip=old)
        if place is None:
            return
        new = TownVehicle(self.road, self.town, *place, old.object_id, old.kind, old.color, old.target_speed, self.rng)
        self.npcs[k] = new
        self.road.vehicles[self.road.vehicles.index(old)] = new

    # ---------------------------------------------------------------- stepping
    def agents(self) -> Agents:
        """Everything that can block a path (ego, NPCs, pedestrians), as arrays for path searches."""
        vehicles = [self.ego] + self.npcs
        peds = self.crowd.peds
        n = len(vehicles) + len(peds)
        pos = np.concatenate([v.position for v in vehicles] + [p.position for p in peds]).astype(float).reshape(n, 2)
        head = np.array([v.heading for v in vehicles] + [p.heading for p in peds], dtype=float)
        spd = np.array([v.speed for v in vehicles] + [p.speed_mps if p.moving else 0.0 for p in peds], dtype=float)
        half = np.array([v.LENGTH / 2 for v in vehicles] + [p.RADIUS for p in peds], dtype=float)
        is_ped = np.arange(n) >= len(vehicles)
        crossing = np.array([False] * len(vehicles) + [p.state == "crossing" for p in peds], dtype=bool)
        ids = np.array([EGO_ID] + [v.object_id for v in self.npcs] + [p.object_id for p in peds], dtype=np.int64)
        left = np.zeros(n, dtype=bool)
        if self._unsignalled:  # the intents matter only where drivers give way by rule
            left[0] = turn_after(self.town, self.route, self.route_index) == Command.LEFT
            left[1:len(vehicles)] = [npc.next_turn() == Command.LEFT for npc in self.npcs]
        return Agents(pos, head, spd, half, is_ped, ids, crossing, left)

    def step(self, action: np.ndarray) -> list[Infraction]:
        """Advance one tick of ``config.dt_s`` with the ego's ``[steer, throttle_brake]``."""
        dt = self.config.dt_s
        self.time_s = round(self.time_s + dt, 9)
        self.step_count += 1
        self.lights.update(self.time_s)
        agents = self.agents()
        states = self.lights.states
        near_r2 = self.config.npc_near_radius_m ** 2
        # NPC positions are agents' rows 1.. (the same numbers); the same per-element arithmetic, for all at once.
        d = agents.positions[1:len(self.npcs) + 1] - self.ego.position
        far_all = (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] > near_r2).tolist()
        far_every, near_every = max(1, self.config.npc_far_decision_every), max(1, self.config.npc_decision_every)
        for npc, far in zip(self.npcs, far_all, strict=True):
            if (self.step_count + npc.object_id) % (far_every if far else near_every) == 0:
                npc.decide(agents, states, self.config.enable_lane_change, self.junctions if self._unsignalled else None)
        self.ego.apply(action)
        before = self.ego.position.copy()
        batch: list[TownVehicle | EgoVehicle] = []
        for v in self.road.vehicles:
            if (type(v) is TownVehicle or type(v) is EgoVehicle) and v.impact is None:
                batch.append(v)  # integrated together below
            else:
                v.step(dt)
        step_vehicles(batch, dt)
        self.distance_m += math.hypot(*(self.ego.position - before))
        vehicles = [self.ego] + self.npcs
        vpos = np.concatenate([v.position for v in vehicles]).reshape(-1, 2)
        vspd = np.array([v.speed for v in vehicles])
        vhead = np.array([v.heading for v in vehicles])
        if self._vsize is None:
            self._vsize = np.array([(v.LENGTH / 2, v.WIDTH / 2) for v in vehicles])
        self.crowd.step(dt, self.lights, vpos, vspd, vhead, self.step_count, self._vsize)
        if self._unjam_npcs(dt):  # someone was moved: the collision checks need the new places
            vpos = np.concatenate([v.position for v in [self.ego] + self.npcs]).reshape(-1, 2)
        self.new_infractions = self._check_ego(vpos[1:])
        self.infractions += self.new_infractions
        if self._unsignalled:
            self._update_junctions(dt)
        return self.new_infractions

    def _update_junctions(self, dt: float) -> None:
        """Tell the junction rules where every vehicle is (after the step): full stops, queues, occupants."""
        at: list[VehicleAt] = []
        ego_lane = self.ego_lane[0] if self.ego_lane is not None else None
        for vid, lane, v in [(EGO_ID, ego_lane, self.ego)] + [(n.object_id, n.lane_index, n) for n in self.npcs]:
            entry = self.town.entry_for_edge(lane[:2]) if lane is not None else None
            to_line = (front_to_line(entry, v.position, float(v.heading), v.LENGTH / 2)
                       if entry is not None and entry.control in STOP_CONTROLS else float("inf"))
            at.append(VehicleAt(vid, lane, to_line, float(v.speed)))
        self.junctions.update(self.time_s, dt, at)

    # ---------------------------------------------------------------- ground truth
    def _record(self, kind: str, other: int = 0, other_kind: str = "", approach: int = -1) -> Infraction:
        ego = self.ego
        return Infraction(kind, self.time_s, float(ego.position[0]), float(ego.position[1]), other, other_kind,
                          approach, float(ego.heading), float(ego.speed))

    def _check_ego(self, npc_positions: np.ndarray | None = None) -> list[Infraction]:
        """This step's new infractions. A contact (collision, off road) counts once when it starts,
        not on every step it lasts, so an episode that goes on after one counts it once."""
        ego = self.ego
        out: list[Infraction] = []
        contacts: set[tuple[str, int]] = set()
        kinds: dict[int, str] = {}  # the other party's kind, by id
        poly = rect_corners(ego.position, ego.heading, ego.LENGTH, ego.WIDTH)
        longest = max((v.LENGTH for v in self.npcs), default=0.0)
        for npc in _maybe_within(self.npcs, npc_positions, ego.position, (longest + ego.LENGTH) / 2 + 1.0):
            near = math.hypot(*(npc.position - ego.position)) < (npc.LENGTH + ego.LENGTH) / 2 + 1.0
            if near and polygons_intersect(poly, rect_corners(npc.position, npc.heading, npc.LENGTH, npc.WIDTH)):
                npc.crashed = True
                contacts.add(("collision_vehicle", npc.object_id))
                kinds[npc.object_id] = SemanticClass(npc.kind).name.lower()
        peds = self.crowd.peds
        for ped in _maybe_within(peds, None, ego.position, ego.LENGTH):
            if math.hypot(*(ped.position - ego.position)) < ego.LENGTH and circle_polygon_intersect(
                    ped.position, ped.RADIUS, poly):
                contacts.add(("collision_pedestrian", ped.object_id))
                kinds[ped.object_id] = "pedestrian"
        if self.static.hits(poly):
            contacts.add(("collision_static", 0))
        self.ego_lane, nearest = self.town.locate_both(ego.position, ego.heading)
        if self.ego_lane is None:
            contacts.add(("off_road", 0))
        for kind, other in sorted(contacts - self._contacts):
            out.append(self._record(kind, other, kinds.get(other, "static" if kind == "collision_static" else "")))
        self._contacts = contacts
        if self.ego_lane is not None:
            out += self._check_direction_and_route(nearest)
        out += self._check_red_light()
        if self._unsignalled:
            out += self._check_junction_rules()
        if self.town.speed_limits_kmh:
            out += self._check_speed()
        return out

    def put_back_on_route(self) -> None:
        """What a safety driver does after an intervention: the car back on the centre of its route
        lane, at a standstill, facing along the lane."""
        frm, to = self.route[self.route_index]
        lane_id = self.ego_lane[0][2] if self.ego_lane is not None and self.ego_lane[0][:2] == (frm, to) else 0
        lane = self.town.lane((frm, to, lane_id))
        s = float(np.clip(lane.local_coordinates(self.ego.position)[0], 0.0, lane.length))
        # Back off along the route (this edge, then the one before) until the car stands clear of
        # every other car and person; a car stalled in a junction is not the safety driver's to move.
        candidates = [(self.route_index, lane, s - back) for back in np.arange(0.0, s + 0.01, 1.0)]
        if self.route_index > 0:
            pfrm, pto = self.route[self.route_index - 1]
            plane = self.town.lane((pfrm, pto, min(lane_id, self.town.lane_count((pfrm, pto)) - 1)))
            candidates += [(self.route_index - 1, plane, plane.length - back) for back in np.arange(0.0, 40.0, 1.0)]
        for index, cand, cs in candidates:
            if cs < 0:
                continue
            pos = cand.position(cs, 0.0)
            poly = rect_corners(pos, cand.heading_at(cs), self.ego.LENGTH + 1.0, self.ego.WIDTH + 0.6)
            cars = any(polygons_intersect(poly, rect_corners(v.position, v.heading, v.LENGTH, v.WIDTH))
                       for v in self.npcs if math.hypot(*(v.position - pos)) < 10.0)
            people = any(circle_polygon_intersect(p.position, p.RADIUS + 0.5, poly)
                         for p in self.crowd.peds if math.hypot(*(p.position - pos)) < 6.0)
            if not (cars or people):
                lane, s = cand, float(cs)
                if index != self.route_index:
                    self.route_index, self.route_s = index, float(cs)
                break
        self.ego.position = lane.position(s, 0.0)
        self.ego.heading = lane.heading_at(s)
        self.ego.speed = 0.0
        for npc in self.npcs:
            if math.hypot(*(npc.position - self.ego.position)) < 6.0:
                npc.crashed = False
        self._off_route_s = 0.0
        self.deviated = False
        self._wrong_way = False
        self._previous_front = None  # the car was carried: it crossed no bar on the way
        self._entry_visit, self._entry_to_line, self._entry_stopped = None, None, False
        self._yielding = None
        self._over_limit_s, self._speeding = 0.0, False
        self.ego_lane = self.town.locate(self.ego.position, self.ego.heading)
        self._contacts = set()

    def _check_direction_and_route(self, nearest: LaneLocation | None) -> list[Infraction]:
        """Wrong-way driving (against the lane ``nearest`` the ego, whatever its heading) and route progress."""
        out: list[Infraction] = []
        assert self.ego_lane is not None
        wrong = False
        if nearest is not None and self.town.lane_info[nearest[0]].kind != "connector":
            lane = self.town.lane(nearest[0])
            wrong = abs(wrap_to_pi(lane.heading_at(nearest[1]) - self.ego.heading)) > math.radians(100)
        if wrong and not self._wrong_way:
            out.append(self._record("wrong_way"))
        self._wrong_way = wrong
        # Route progress: stay on the current edge or move on to one of the next two. Where lanes
        # overlap (connectors leave a stop line together) a route lane the car is on wins.
        edge, s = self.ego_lane[0][:2], self.ego_lane[1]
        window = self.route[self.route_index:self.route_index + 3]
        if edge not in window:
            on_route = self._route_lane_here(window)
            if on_route is not None:
                edge, s = on_route
        if edge in window:
            self.route_index += window.index(edge)
            self.route_s = max(s, self.route_s) if window.index(edge) == 0 else s
            self._off_route_s = 0.0
            self.deviated = False  # back on the route: a later departure is a new deviation
        else:
            self._off_route_s += self.config.dt_s
            if self._off_route_s >= self.config.route_deviation_s and not self.deviated:
                self.deviated = True
                out.append(self._record("route_deviation"))
        return out

    def _route_lane_here(self, window: list[Edge]) -> tuple[Edge, float] | None:
        """A lane of the route window the car is on (within its width, heading along it), if any."""
        half = self.town.lane_width / 2
        for frm, to in window:
            for lane in self.town.network.graph[frm][to]:
                s, lat = lane.local_coordinates(self.ego.position)
                if (-0.5 <= s <= lane.length + 0.5 and abs(lat) <= half
                        and abs(wrap_to_pi(lane.heading_at(s) - self.ego.heading)) < 0.6):
                    return (frm, to), float(s)
        return None

    def _check_red_light(self) -> list[Infraction]:
        """Red-light run: the front bumper, moving from where it was a step ago to where it is now, crosses
        the junction-side edge of the stop bar of the approach the car is on, within the bar's width,
        while that approach's light is red.

        The approach is found afresh every step from the lane the car's centre is on (its incoming road,
        or a connector of its junction just after the bumper crossed): nothing is carried from one
        junction to the next, so a far junction's light can never be charged, and the approach the car
        is on is always the one looked at. One run is charged once per visit to an approach."""
        ego = self.ego
        front = ego.position + ego.LENGTH / 2 * np.array([math.cos(ego.heading), math.sin(ego.heading)])
        previous, self._previous_front = self._previous_front, front
        approach = self._approach_here()
        if approach is None or self._charged_approach != approach.index:
            self._charged_approach = None
        if approach is None or previous is None:
            return []
        lane = self.town.network.graph[approach.edge[0]][approach.edge[1]][0]
        s0, lat0 = (float(v) for v in lane.local_coordinates(previous))
        s1, lat1 = (float(v) for v in lane.local_coordinates(front))
        if not s0 < lane.length <= s1:
            return []
        lateral = lat0 + (lat1 - lat0) * (lane.length - s0) / max(s1 - s0, 1e-9)
        half = self.town.lane_width / 2
        if not -half <= lateral <= 3 * half:  # the bar spans both incoming lanes (lane 0's centre at 0)
            return []
        if self.lights.state(approach.index) != LightState.RED or self._charged_approach == approach.index:
            return []
        self._charged_approach = approach.index
        return [self._record("red_light", approach.index, "traffic_light", approach.index)]

    def _check_junction_rules(self) -> list[Infraction]:
        """Stop signs and give-way lines (``sim.rules``): entering the junction (the front bumper past the line's
        far edge) from a STOP or ALL_WAY_STOP entry without a full stop at its line on this visit is a
        ``stop_sign``; having entered from a STOP or YIELD entry, entering a priority arm's lane in front of
        its traffic that would reach that point within ``YIELD_CONFLICT_S`` is ``failed_to_yield``. The entry is
        the one whose road the car's centre is on, found afresh each step."""
        out = self._check_yielding()
        ego = self.ego
        entry: Entry | None = None
        if self.ego_lane is not None:
            entry = self.town.entry_for_edge(self.ego_lane[0][:2])
        if entry is None or entry.control not in (Control.STOP, Control.ALL_WAY_STOP, Control.YIELD):
            self._entry_visit, self._entry_to_line, self._entry_stopped = None, None, False
            return out
        if entry.index != self._entry_visit:
            self._entry_visit, self._entry_to_line, self._entry_stopped = entry.index, None, False
        to_line = front_to_line(entry, ego.position, float(ego.heading), ego.LENGTH / 2)
        if ego.speed < STOP_SPEED_MPS and -0.5 <= to_line <= STOP_ZONE_M:
            self._entry_stopped = True
        previous, self._entry_to_line = self._entry_to_line, to_line
        inside = -ROAD.stop_bar_depth_m  # the line's far edge: the junction begins
        if previous is None or not (previous > inside >= to_line):
            return out
        if entry.control in STOP_CONTROLS and not self._entry_stopped:
            out.append(self._record("stop_sign", entry.index, "stop_sign"))
        if entry.control in GIVE_WAY_CONTROLS:
            turn = turn_after(self.town, self.route, self.route_index) if self.route[self.route_index] == entry.edge \
                else None
            self._yielding = YieldCrossing.start(self.town, entry, turn)
            out += self._check_yielding()
        return out

    def _check_yielding(self) -> list[Infraction]:
        """After a give-way line: ``failed_to_yield`` when the front bumper enters a priority arm's lanes in front
        of its traffic (``sim.rules.failed_to_yield_by``); each arm is judged once, as it is entered."""
        crossing = self._yielding
        if crossing is None:
            return []
        ego = self.ego
        front = ego.position + ego.LENGTH / 2 * np.array([math.cos(ego.heading), math.sin(ego.heading)])
        if not crossing.near(front):
            self._yielding = None
            return []
        entered = crossing.entering(self.town, front)
        npcs = self.npcs
        if not entered or not npcs:
            return []
        k = failed_to_yield_by(self.town, entered, front, np.array([n.position for n in npcs]),
                               np.array([float(n.heading) for n in npcs]), np.array([n.speed for n in npcs]),
                               np.array([n.LENGTH / 2 for n in npcs]))
        if k < 0:
            return []
        return [self._record("failed_to_yield", npcs[k].object_id, SemanticClass(npcs[k].kind).name.lower())]

    def speed_limit_here_kmh(self) -> int | None:
        """The posted limit of the road (or junction) the ego is on; None where nothing is posted."""
        return self.town.speed_limit_kmh(self.ego_lane[0][:2]) if self.ego_lane is not None else None

    def _check_speed(self) -> list[Infraction]:
        """Speeding: over the posted limit of the road the car is on by more than ``SPEEDING_TOLERANCE`` for
        ``SPEEDING_MIN_S``; charged once per stretch, which ends when the car is back at or under the limit."""
        limit = self.speed_limit_here_kmh()
        kmh = self.ego.speed * 3.6
        if limit is None or kmh <= limit:
            self._over_limit_s, self._speeding = 0.0, False
            return []
        if kmh <= limit * (1.0 + SPEEDING_TOLERANCE):
            self._over_limit_s = 0.0
            return []
        self._over_limit_s += self.config.dt_s
        if self._over_limit_s + 1e-9 < SPEEDING_MIN_S or self._speeding:
            return []
        self._speeding = True
        return [self._record("speeding", limit, "speed_limit")]

    def _approach_here(self) -> Approach | None:
        """The signalled approach whose stop bar the car is at: its incoming road when the car's centre is
        on it, else the approach it came by when the centre is on a connector of that approach's junction."""
        if self.ego_lane is None:
            return None
        index = self.ego_lane[0]
        approach = self.town.approach_for_edge(index[:2])
        if approach is not None:
            self._last_approach = approach.index
            return approach
        info = self.town.lane_info.get(index)
        if self._last_approach is not None and info is not None and info.kind == "connector":
            came_by = self.town.approaches[self._last_approach]
            if came_by.node == info.node:
                return came_by
        self._last_approach = None
        return None

    # ---------------------------------------------------------------- views for env, renderer, drivers
    @property
    def route_progress_m(self) -> float:
        return float(self._route_starts[self.route_index] + self.route_s)

    @property
    def route_completion(self) -> float:
        """The share of the route driven (0-1); 1 once the car has arrived (``route_done``), since the episode
        ends there, ``ROUTE_ARRIVAL_M`` short of the route's last point."""
        if self.route_done:
            return 1.0
        return min(1.0, max(0.0, self.route_progress_m / max(self.route_total_m, 1e-6)))

    @property
    def route_done(self) -> bool:
        return self.route_total_m - self.route_progress_m < ROUTE_ARRIVAL_M

    def command(self) -> Command:
        """The route command here (``command_at``). Kept while the route and the place on it stay the same:
        the env asks for it twice a step."""
        last = self._command
        if (last is not None and last[0] is self.route and last[1] == len(self.route) and last[2] == self.route_index
                and last[3] == self.route_s):
            return last[4]
        command = command_at(self.town, self.route, self.route_index, self.route_s)
        self._command = (self.route, len(self.route), self.route_index, self.route_s, command)
        return command

    def lane_band_offset_m(self) -> float:
        """How far the car is outside the band between its direction's lane centres (0 inside it, e.g.
        while changing lanes; nan off road). The safety driver's "off its lane" measure."""
        if self.ego_lane is None:
            return float("nan")
        lat0 = self.ego_lane[2] + self.ego_lane[0][2] * self.town.lane_width  # lateral from lane 0's centre
        band = (self.town.lane_count(self.ego_lane[0][:2]) - 1) * self.town.lane_width
        return float(max(0.0, -lat0, lat0 - band))

    def lane_offset_m(self) -> float:
        """Signed lateral offset from the current lane's centre (positive: right of it); nan off road."""
        return float(self.ego_lane[2]) if self.ego_lane is not None else float("nan")

    def _edges_ahead(self, horizon_m: float) -> Iterator[tuple[Edge, float]]:
        """The route's edges from the current one, each with the distance from the front bumper to its end,
        while that end lies within ``horizon_m`` (plus the stop bar's depth)."""
        along = -(self.route_s + self.ego.LENGTH / 2)
        for k in range(self.route_index, len(self.route)):
            along += edge_length(self.town, self.route[k])
            if along - ROAD.stop_bar_depth_m > horizon_m:
                return
            yield self.route[k], along

    def next_light(self, horizon_m: float = 150.0) -> NextLight | None:
        """The next signal on the route ahead and the distance to its stop line."""
        for edge, along in self._edges_ahead(horizon_m):
            ap = self.town.approach_for_edge(edge)
            if ap is not None and along > -ROAD.stop_bar_depth_m:
                return NextLight(ap.index, self.lights.state(ap.index), along - ROAD.stop_bar_depth_m)
        return None

    def next_control(self, horizon_m: float = 150.0) -> NextControl | None:
        """The next junction entry on the route ahead (signal, stop, all-way stop, give way or priority) and the
        distance to its line; as ``next_light``, the entry whose line the front bumper has not yet passed."""
        for edge, along in self._edges_ahead(horizon_m):
            entry = self.town.entry_for_edge(edge)
            if entry is not None and along > -ROAD.stop_bar_depth_m:
                return NextControl(entry.index, entry.control, along - ROAD.stop_bar_depth_m, entry.approach)
        return None

    def signs_near(self, radius_m: float = 60.0) -> list[tuple[Sign, float]]:
        """The signs within ``radius_m`` of the ego that face its way (their plates readable from here, ahead of
        the car), nearest first, with their distances."""
        ego = self.ego
        ahead = np.array([math.cos(ego.heading), math.sin(ego.heading)])
        out = []
        for g in self.town.signs:
            rel = g.position - ego.position
            d = float(math.hypot(rel[0], rel[1]))
            if d > radius_m or float(rel @ ahead) < 0.0:
                continue
            if abs(wrap_to_pi(g.facing - float(ego.heading))) > math.pi / 2:
                continue  # its back is to us
            out.append((g, d))
        return sorted(out, key=lambda gd: gd[1])

    def object_snapshots(self) -> list[ObjectSnapshot]:
        """Every moving object's pose and look, built once per step (the renderer and info share it), and the
        parked cars within ``PARKED_VIEW_M`` of the ego (static, ids ``PARKED_ID_BASE + k``)."""
        key = (self.step_count, len(self.npcs), id(self.crowd), len(self.crowd.peds))
        if self._snapshots_key != key:
            self._snapshots = [v.snapshot() for v in self.npcs] + [p.snapshot() for p in self.crowd.peds]
            if self._parked:
                near = points_within(self._parked_xy, float(self.ego.position[0]), float(self.ego.position[1]),
                                     PARKED_VIEW_M ** 2)
                self._snapshots += [p for p, k in zip(self._parked, near.tolist(), strict=True) if k]
            self._snapshots_key = key
        return self._snapshots

    def ego_route_polyline(self) -> np.ndarray:
        pts = []
        for frm, to in self.route[self.route_index:]:
            lane = self.town.network.graph[frm][to][0]
            for s in np.linspace(0, lane.length, max(2, int(lane.length / 4))):
                pts.append(lane.position(s, 0.0))
        return np.array(pts)
