"""The scenario suite: seed 004's eight test cases (section 3.11), plus a yellow light too close to
stop for, a turn by command, and a turn announced while a car overtakes in the lane the turn needs.
Each scenario is deterministic (fixed town, placement, seed) and has a pass/fail rule checked on what happened.

The original ones take place on the same approach to a four-way junction of the default town: the ego starts
on lane 0, ``START_BEFORE_STOP_M`` before the stop line, with no other traffic unless the scenario adds it.
The rules of unsignalled towns (issue 30) need other places: those scenarios name a town style and a
``Place`` (which entry of which development town, found by a fixed search, so always the same one) and start
the ego on that entry's road.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from towndrive.envs.drive_env import DriveConfig, DriveEnv
from towndrive.sim.ego import EgoVehicle
from towndrive.sim.geometry import rect_corners
from towndrive.sim.objects import LightState, SemanticClass
from towndrive.sim.pedestrians import PedestrianCrowd
from towndrive.sim.routes import shortest_route
from towndrive.sim.rules import front_to_line
from towndrive.sim.town import OPPOSITE, Approach, Arm, Command, Control, Edge, Entry, Town, TownConfig
from towndrive.sim.traffic import TownVehicle
from towndrive.sim.world import World, cached_town

if TYPE_CHECKING:
    from towndrive.envs.parallel import Worker

START_BEFORE_STOP_M = 55.0
APPROACH_NODE = (1, 1)
APPROACH_ARM = Arm.W  # traffic arrives from the west arm, driving east
OVERTAKER_BEHIND_M = 6.0  # centre to centre: without a look in the mirror, PilotNet moves into it


@dataclass
class ScenarioResult:
    name: str
    passed: bool
    detail: str
    time_s: float


@dataclass
class Log:
    """Per-step record a scenario's rule reads."""

    t: list[float] = field(default_factory=list)
    speed: list[float] = field(default_factory=list)
    light_distance: list[float] = field(default_factory=list)
    progress: list[float] = field(default_factory=list)
    lead_gap: list[float] = field(default_factory=list)
    infractions: list[str] = field(default_factory=list)
    edges: list[Edge] = field(default_factory=list)

    def before(self, time_s: float) -> Log:
        """The steps before a time (the infractions stay: they are counted over the whole run)."""
        n = sum(t < time_s for t in self.t)
        return Log(self.t[:n], self.speed[:n], self.light_distance[:n], self.progress[:n], self.lead_gap[:n],
                   self.infractions, self.edges[:n])


@dataclass(frozen=True)
class Place:
    """Where a scenario of a styled town happens: the first entry (over development town seeds
    ``PLACE_SEEDS``, in order) that ``fits``; the ego starts ``before_m`` before its line and takes ``turn``."""

    style: str
    fits: Callable[[Town, Entry], bool]
    turn: Command = Command.STRAIGHT
    before_m: float = 45.0


PLACE_SEEDS = range(1000, 1040)  # development towns (the test split is never searched)


@dataclass
class Scenario:
    description: str
    duration_s: float
    setup: Callable[[World, Approach], dict[str, Any]]
    check: Callable[[Log, dict[str, Any]], tuple[bool, str]]
    weather: str = "noon"
    turn: Command = Command.STRAIGHT
    hook: Callable[[World, dict[str, Any]], None] | None = None
    place: Place | None = None  # None: the default town's approach (APPROACH_NODE, APPROACH_ARM)


def exit_edge(town: Town, node: tuple[int, int], arm: Arm) -> Edge:
    frm = f"{node[0]}-{node[1]}{arm.name}o"
    return frm, next(iter(town.network.graph[frm]))


def find_place(place: Place) -> tuple[Town, Entry]:
    """The town and entry of a ``Place`` (the same every time: a fixed search)."""
    for seed in PLACE_SEEDS:
        town = cached_town(TownConfig.of_style(place.style), seed)
        for entry in town.entries:
            if (town.lane((*entry.edge, 0)).length >= place.before_m + 10.0 and place.fits(town, entry)
                    and move_goal(town, entry, place.turn) is not None):
                return town, entry
    raise LookupError(f"no place for the scenario in {place.style} towns {PLACE_SEEDS.start}-{PLACE_SEEDS.stop - 1}")


def move_goal(town: Town, entry: Entry, turn: Command) -> Edge | None:
    """The road after ``entry``'s junction that the move ``turn`` leads to (None if the junction has no such move)."""
    for out in town.network.graph[entry.edge[1]]:
        if town.lane_info[(entry.edge[1], out, 0)].command == turn:
            return out, next(iter(town.network.graph[out]))
    return None


def build_place_world(config: DriveConfig, place: Place) -> tuple[World, Entry]:
    town, entry = find_place(place)
    goal = move_goal(town, entry, place.turn)
    assert goal is not None
    lane = town.lane((*entry.edge, 0))
    world_cfg = replace(config.world, town=town.config, npc_count=0, pedestrian_count=0)
    world = World(town, world_cfg, seed=0, start=(*entry.edge, 0), start_s=lane.length - place.before_m, goal=goal,
                  spawn_traffic=False)
    return world, entry


def build_world(config: DriveConfig, scenario: Scenario) -> tuple[World, Approach]:
    town = cached_town(config.world.town, config.town_seed)
    ap = town.approach_at(APPROACH_NODE, APPROACH_ARM)
    assert ap is not None
    travel_arm = OPPOSITE[APPROACH_ARM]  # straight on
    if scenario.turn == Command.LEFT:
        travel_arm = Arm.N
    elif scenario.turn == Command.RIGHT:
        travel_arm = Arm.S
    goal = shortest_route(town, ap.edge, exit_edge(town, APPROACH_NODE, travel_arm))[-1]
    lane = town.network.graph[ap.edge[0]][ap.edge[1]][0]
    world_cfg = replace(config.world, npc_count=0, pedestrian_count=0)
    world = World(town, world_cfg, seed=0, start=(ap.edge[0], ap.edge[1], 0),
                  start_s=lane.length - 0.5 - START_BEFORE_STOP_M - EgoVehicle.LENGTH / 2, goal=goal,
                  spawn_traffic=False)
    world.lights.force(ap.index, LightState.GREEN, until_s=1e9)
    return world, ap


# ---------------------------------------------------------------------------- the scenarios
def _lead_car(color: tuple[float, float, float]) -> Callable[[World, Approach], dict[str, Any]]:
    def setup(world: World, ap: Approach) -> dict[str, Any]:
        lane_index = (ap.edge[0], ap.edge[1], 0)
        s = world.town.lane(lane_index).local_coordinates(world.ego.position)[0] + 30.0
        npc = world.spawn_npc(lane_index, s, SemanticClass.CAR, color=color, target_speed=0.0)
        assert npc is not None
        npc.speed = 0.0
        return {"lead": npc}
    return setup


def _check_stop_behind(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    stopped = [g for v, g in zip(log.speed, log.lead_gap, strict=True) if v < 0.1 and math.isfinite(g)]
    if log.infractions:
        return False, f"infractions: {log.infractions}"
    if not stopped:
        return False, f"never stopped (min speed {min(log.speed):.2f} m/s)"
    gap = stopped[-1]
    return 1.0 <= gap <= 8.0, f"stopped {gap:.1f} m behind the car (want 1-8 m)"


def _drive_away_hook(world: World, ctx: dict[str, Any]) -> None:
    if world.time_s >= ctx.setdefault("go_at_s", 10.0):
        ctx["lead"].target_speed = 9.0


def _check_resume(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    before = log.before(ctx["go_at_s"])
    if not (before.speed and min(before.speed) < 0.1):
        return False, "did not stop behind the car before it left"
    moved = log.progress[-1] - log.progress[len(before.t)] if len(log.t) > len(before.t) else 0.0
    return (moved >= 20.0 and not log.infractions, f"moved {moved:.0f} m after the car left (want >= 20 m); "
            f"infractions: {log.infractions or 'none'}")


def _red(world: World, ap: Approach) -> dict[str, Any]:
    world.lights.force(ap.index, LightState.RED, until_s=1e9)
    return {"ap": ap}


def _check_stop_line(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    if "red_light" in log.infractions:
        return False, "ran the red light"
    stops = [d for v, d in zip(log.speed, log.light_distance, strict=True) if v < 0.1 and math.isfinite(d)]
    if not stops:
        return False, f"never stopped (min speed {min(log.speed):.2f} m/s)"
    return 0.0 <= stops[-1] <= 2.0, f"stopped {stops[-1]:.2f} m before the stop line (want 0-2 m)"


def _red_then_green(world: World, ap: Approach) -> dict[str, Any]:
    world.lights.force(ap.index, LightState.RED, until_s=12.0)
    return {"ap": ap, "green_at_s": 12.0}


def _green_after_hook(world: World, ctx: dict[str, Any]) -> None:
    if world.time_s >= ctx["green_at_s"] and not ctx.get("turned"):
        world.lights.force(ctx["ap"].index, LightState.GREEN, until_s=1e9)
        ctx["turned"] = True


def _check_red_then_green(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    ok, detail = _check_stop_line(log.before(ctx["green_at_s"]), ctx)
    if not ok:
        return False, detail
    crossed = log.edges[-1] != ctx["ap"].edge
    return crossed and not log.infractions, f"{detail}; drove on after green: {crossed}"


def _quiet(world: World, ap: Approach) -> dict[str, Any]:
    return {}


def _check_clean_progress(min_m: float) -> Callable[[Log, dict[str, Any]], tuple[bool, str]]:
    def check(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
        moved = log.progress[-1] - log.progress[0]
        return (moved >= min_m and not log.infractions,
                f"drove {moved:.0f} m along the route (want >= {min_m:.0f}); infractions: {log.infractions or 'none'}")
    return check


def _passing_cars(world: World, ap: Approach) -> dict[str, Any]:
    town = world.town
    ego_s = town.lane((ap.edge[0], ap.edge[1], 0)).local_coordinates(world.ego.position)[0]
    # a faster car overtaking in the next lane of our direction, and one coming the other way
    world.spawn_npc((ap.edge[0], ap.edge[1], 1), max(ego_s - 15.0, 2.0), SemanticClass.CAR,
                    color=(0.1, 0.2, 0.6), target_speed=12.0)
    node, west = APPROACH_NODE, (APPROACH_NODE[0] - 1, APPROACH_NODE[1])
    opposite = (f"{node[0]}-{node[1]}Wo", f"{west[0]}-{west[1]}Ei", 0)  # the same road, the other way
    world.spawn_npc(opposite, 5.0, SemanticClass.TRUCK, color=(0.9, 0.9, 0.9), target_speed=9.0)
    return {}


def _check_no_stop(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    t = np.array(log.t)
    cruising = np.array(log.speed)[t > 5.0]
    low = float(cruising.min()) if cruising.size else 0.0
    return low > 5.0 and not log.infractions, f"lowest speed after 5 s {low:.1f} m/s (want > 5: no stop)"


def _pedestrian(world: World, ap: Approach) -> dict[str, Any]:
    town = world.town
    lane = town.lane((ap.edge[0], ap.edge[1], 0))
    s = lane.local_coordinates(world.ego.position)[0] + 22.0
    kerb = lane.position(s, 1.5 * town.lane_width + 0.4)  # on our kerb (lane 0's centre is half a lane in)
    far = lane.position(s, -2.5 * town.lane_width - 0.4)  # the far kerb
    world.crowd = PedestrianCrowd(town, 1, np.random.default_rng(0), 1000)
    ped = world.crowd.peds[0]
    ped.position, ped.heading, ped.state, ped.target = kerb.copy(), 0.0, "crossing", far.copy()
    ped.speed_mps = 1.1
    ped.yields = False  # it walks on whatever comes: the car must stop
    return {"ped": ped}


def _check_pedestrian(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    if "collision_pedestrian" in log.infractions:
        return False, "hit the pedestrian"
    stopped = min(log.speed) < 0.1
    moved = log.progress[-1] - log.progress[int(np.argmin(log.speed))]
    return (stopped and moved > 10.0 and not log.infractions,
            f"stopped for the pedestrian: {stopped}; drove {moved:.0f} m after (want > 10)")


def _yellow_close(world: World, ap: Approach) -> dict[str, Any]:
    world.ego.speed = 8.0
    return {"ap": ap, "switched_at": None}


def _yellow_hook(world: World, ctx: dict[str, Any]) -> None:
    light = world.next_light()
    if ctx["switched_at"] is None and light is not None and light.distance_m < 7.0:
        world.lights.force(ctx["ap"].index, LightState.YELLOW, until_s=1e9)
        ctx["switched_at"] = world.time_s
        ctx["red_at"] = world.time_s + 3.0
    if ctx.get("red_at") is not None and world.time_s >= ctx["red_at"]:
        world.lights.force(ctx["ap"].index, LightState.RED, until_s=1e9)


def _check_yellow(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    if ctx["switched_at"] is None:
        return False, "never came within 7 m of the stop line"
    if "red_light" in log.infractions:
        return False, "ran the red light"
    went = log.edges[-1] != ctx["ap"].edge
    return went, f"went on through the yellow (too close to stop comfortably): {went}"


def _overtaken(world: World, ap: Approach) -> dict[str, Any]:
    """A faster car in the next lane (the one a right turn needs), a little behind us: it comes alongside as
    the route announces the turn, out of the forward camera's view."""
    town = world.town
    ego_s = town.lane((ap.edge[0], ap.edge[1], 0)).local_coordinates(world.ego.position)[0]
    npc = world.spawn_npc((ap.edge[0], ap.edge[1], 1), max(ego_s - OVERTAKER_BEHIND_M, 2.0), SemanticClass.CAR,
                          color=(0.85, 0.85, 0.8), target_speed=9.0)
    assert npc is not None
    npc.speed = 8.0
    world.ego.speed = 7.0
    return {"lead": npc}


def _check_turn(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    goal = ctx["goal"]
    reached = goal in log.edges
    return reached and not log.infractions, f"took the turn onto {goal}: {reached}; infractions: {log.infractions or 'none'}"


# ---------------------------------------------------------------------------- unsignalled towns (issue 30)
def _priority_arms(town: Town, entry: Entry) -> list[Entry]:
    return [e for e in town.entries_at(entry.node) if e.control == Control.PRIORITY and town.lane((*e.edge, 0)).length > 60]


def _stop_with_cross_traffic(town: Town, entry: Entry) -> bool:
    return entry.control == Control.STOP and len(_priority_arms(town, entry)) == 2 and len(town.entries_at(entry.node)) == 4


def _t_junction_side_road(town: Town, entry: Entry) -> bool:
    return (entry.control in (Control.STOP, Control.YIELD) and len(town.entries_at(entry.node)) == 3
            and len(_priority_arms(town, entry)) == 2 and move_goal(town, entry, Command.LEFT) is not None)


def _limit_drops(town: Town, entry: Entry) -> bool:
    """A 50 km/h priority street with a right turn into a 30 km/h street (no stop on the way: a street keeps its
    limit straight on, so the limit changes where the route turns)."""
    goal = move_goal(town, entry, Command.RIGHT)
    return (entry.control == Control.PRIORITY and town.speed_limit_kmh(entry.edge) == 50 and goal is not None
            and town.speed_limit_kmh(goal) == 30 and town.lane((*goal, 0)).length > 70)


def _parked_street(town: Town, entry: Entry) -> bool:
    """A residential road with at least three parked cars along our kerb in the last 45 m before the junction."""
    if town.lane_count(entry.edge) != 1 or entry.control == Control.SIGNAL:
        return False
    return len(_parked_along(town, entry.edge, 45.0)) >= 3


def _parked_along(town: Town, edge: Edge, last_m: float) -> list[int]:
    lane = town.lane((*edge, 0))
    out = []
    for k, car in enumerate(town.parked_cars):
        s, lat = lane.local_coordinates(car.position)
        if lane.length - last_m <= s <= lane.length and 0.0 < lat < town.lane_width + 2.0:
            out.append(k)
    return out


def _unsignalled_zebra(town: Town, entry: Entry) -> bool:
    return entry.control == Control.PRIORITY and any(cw.node == entry.node and cw.arm == entry.arm and cw.approach < 0
                                                     for cw in town.crosswalks)


def _cross_traffic(world: World, ap: Any) -> dict[str, Any]:
    """Cars coming along the priority street from both sides, the first about to reach the junction as we do."""
    entry = ap
    town = world.town
    for k, prio in enumerate(_priority_arms(town, entry)):
        lane = town.lane((*prio.edge, 0))
        for back in (38.0 + 8.0 * k, 62.0 + 8.0 * k):
            npc = world.spawn_npc((*prio.edge, 0), lane.length - back, SemanticClass.CAR, target_speed=8.0)
            assert npc is not None
            npc.speed = 8.0
    return {"entry": entry}


def _speed_up(world: World, ap: Any) -> dict[str, Any]:
    world.ego.speed = 13.0  # 47 km/h on the 50 road
    return {"entry": ap}


def _parked(world: World, ap: Any) -> dict[str, Any]:
    world.ego.speed = 7.0
    return {"entry": ap, "parked": _parked_along(world.town, ap.edge, 45.0), "clearance": math.inf, "passing": []}


def _parked_hook(world: World, ctx: dict[str, Any]) -> None:
    """The least distance between the ego's body and a parked car's (a door opening needs about 0.8 m; the
    scenario asks for the clearance a careful driver keeps in a narrow street, 0.4 m)."""
    ego = world.ego
    if front_to_line(ctx["entry"], ego.position, float(ego.heading), ego.LENGTH / 2) > 8.0:
        ctx["passing"].append(float(ego.speed))  # along the parked cars (the junction's own rules come after)
    mine = rect_corners(ego.position, ego.heading, ego.LENGTH, ego.WIDTH)
    for k in ctx["parked"]:
        car = world.town.parked_cars[k]
        theirs = rect_corners(car.position, car.heading, car.length_m, car.width_m)
        gap = min(float(np.min(np.linalg.norm(theirs - p, axis=1))) for p in mine)
        gap = min(gap, min(_point_rect_distance(p, theirs) for p in mine), min(_point_rect_distance(q, mine) for q in theirs))
        ctx["clearance"] = min(ctx["clearance"], gap)


def _point_rect_distance(p: np.ndarray, rect: np.ndarray) -> float:
    origin, u, v = rect[0], rect[1] - rect[0], rect[3] - rect[0]
    a = float(np.clip((p - origin) @ u / (u @ u), 0.0, 1.0))
    b = float(np.clip((p - origin) @ v / (v @ v), 0.0, 1.0))
    return float(np.linalg.norm(origin + a * u + b * v - p))


def _zebra_walker(world: World, ap: Any) -> dict[str, Any]:
    """A pedestrian waiting at the unsignalled zebra beyond the line: it steps out while we can still stop."""
    town = world.town
    cw = next(c for c in town.crosswalks if c.node == ap.node and c.arm == ap.arm and c.approach < 0)
    world.crowd = PedestrianCrowd(town, 1, np.random.default_rng(0), 1000)
    ped = world.crowd.peds[0]
    lane = town.lane((*ap.edge, 0))
    near_kerb_start = float(lane.local_coordinates(cw.start)[1]) > 0  # the start kerb is on our right
    ped.crosswalk, ped.at_start = cw.index, near_kerb_start
    ped.position = (cw.start if near_kerb_start else cw.end).copy()
    ped.state, ped.speed_mps = "waiting", 1.2
    return {"entry": ap, "ped": ped, "ped_start": ped.position.copy(), "walked": 0.0}


def _walker_hook(world: World, ctx: dict[str, Any]) -> None:
    ctx["walked"] = max(ctx["walked"], float(np.linalg.norm(ctx["ped"].position - ctx["ped_start"])))


def _check_through(min_m: float, stop_at_line: bool = False) -> Callable[[Log, dict[str, Any]], tuple[bool, str]]:
    def check(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
        moved = log.progress[-1] - log.progress[0]
        reached = ctx["goal"] in log.edges
        stopped = any(v < 0.1 for v in log.speed)
        ok = moved >= min_m and reached and not log.infractions and (stopped or not stop_at_line)
        return ok, (f"drove {moved:.0f} m (want >= {min_m:.0f}), reached {ctx['goal']}: {reached}"
                    + (f", stopped: {stopped}" if stop_at_line else "") + f"; infractions: {log.infractions or 'none'}")
    return check


def _check_parked(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    low = min(ctx["passing"], default=0.0)
    ok = ctx["clearance"] >= 0.4 and not log.infractions and low > 3.0
    return ok, (f"passed {len(ctx['parked'])} parked cars with {ctx['clearance']:.2f} m clearance (want >= 0.4), "
                f"lowest speed passing them {low:.1f} m/s (want > 3: no needless stop); "
                f"infractions: {log.infractions or 'none'}")


def _check_zebra(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    if "collision_pedestrian" in log.infractions:
        return False, "hit the pedestrian"
    stopped = min(log.speed) < 0.1
    moved = log.progress[-1] - log.progress[int(np.argmin(log.speed))]
    walked = ctx["walked"]
    return (stopped and moved > 10.0 and walked > 3.0 and not log.infractions,
            f"stopped for the pedestrian: {stopped} (it walked {walked:.0f} m); drove {moved:.0f} m after (want > 10); "
            f"infractions: {log.infractions or 'none'}")


SCENARIOS: dict[str, Scenario] = {
    "car_ahead": Scenario("a stopped car ahead in our lane: stop 1-8 m behind it", 20.0,
                          _lead_car((0.75, 0.08, 0.08)), _check_stop_behind),
    "car_drives_away": Scenario("the car ahead drives away after 10 s: resume", 28.0, _lead_car((0.08, 0.2, 0.6)),
                                _check_resume, hook=_drive_away_hook),
    "red_light": Scenario("a red light: stop 0-2 m before the stop line", 20.0, _red, _check_stop_line),
    "red_then_green": Scenario("the red light turns green at 12 s: drive on", 24.0, _red_then_green,
                               _check_red_then_green, hook=_green_after_hook),
    "night": Scenario("night driving: follow the route through the junction", 16.0, _quiet,
                      _check_clean_progress(80.0), weather="night"),
    "car_other_lane": Scenario("cars passing in the other lanes: do not stop", 14.0, _passing_cars, _check_no_stop),
    "unusual_colour_car": Scenario("a stopped car of an unusual colour (pink): stop behind it", 20.0,
                                   _lead_car((1.0, 0.25, 0.85)), _check_stop_behind),
    "pedestrian_crossing": Scenario("a pedestrian crosses our road ahead: stop, then go on", 28.0, _pedestrian,
                                    _check_pedestrian),
    "yellow_too_close": Scenario("the light turns yellow 7 m before the stop line at 8 m/s: go on", 12.0,
                                 _yellow_close, _check_yellow, hook=_yellow_hook),
    "turn_left": Scenario("a left turn at the junction, by command", 20.0, _quiet, _check_turn, turn=Command.LEFT),
    "overtaken_before_turn": Scenario("a right turn from the inner lane while a faster car overtakes in the outer one: "
                                      "no collision", 24.0, _overtaken, _check_turn, turn=Command.RIGHT),
    "stop_sign_cross_traffic": Scenario("a stop sign with cars coming along the priority street from both sides: "
                                        "a full stop, then through a gap", 40.0, _cross_traffic, _check_through(60.0, True),
                                        place=Place("suburb", _stop_with_cross_traffic)),
    "t_junction_priority_turn": Scenario("a left turn from a T-junction's side road onto the priority street with "
                                         "traffic both ways", 45.0, _cross_traffic, _check_through(50.0),
                                         turn=Command.LEFT, place=Place("suburb", _t_junction_side_road, Command.LEFT)),
    "speed_limit_change": Scenario("at 47 km/h on a 50 km/h street, a right turn into a 30 km/h one: slow down in "
                                   "time", 20.0, _speed_up, _check_through(80.0), turn=Command.RIGHT,
                                   place=Place("suburb", _limit_drops, Command.RIGHT, before_m=50.0)),
    "parked_door_zone": Scenario("a residential street with parked cars along the kerb: pass them, clear of "
                                 "their doors", 10.0, _parked, _check_parked, hook=_parked_hook,
                                 place=Place("suburb", _parked_street)),
    "pedestrian_unsignalled": Scenario("a pedestrian at an unsignalled zebra steps out: stop, then go on", 35.0,
                                       _zebra_walker, _check_zebra, hook=_walker_hook,
                                       place=Place("suburb", _unsignalled_zebra)),
}


def run_scenario(name: str, driver: Any, config: DriveConfig, out: Path | None = None, video: bool = False) -> ScenarioResult:
    """Run one scenario with a driver; returns whether it passed and why."""
    scenario = SCENARIOS[name]
    config = replace(config, weather=scenario.weather, max_time_s=scenario.duration_s,
                     terminate_on_route_deviation=False)
    if scenario.place is not None:
        world, where = build_place_world(config, scenario.place)
        ctx = scenario.setup(world, where)  # type: ignore[arg-type]  # the place's Entry stands for the approach
        ap_index = -1
    else:
        world, ap = build_world(config, scenario)
        ctx = scenario.setup(world, ap)
        ap_index = ap.index
    ctx["goal"] = world.route[-1]
    env = DriveEnv(config, render_mode="rgb_array")
    writer = None
    if video and out is not None:
        from towndrive.envs.evaluation import video_writer

        out.mkdir(parents=True, exist_ok=True)
        writer = video_writer(out / f"{name}.mp4", env.metadata["render_fps"])
    log = Log()
    try:
        obs, info = env.reset(seed=0, options={"world": world})
        driver.reset(env)
        lead = ctx.get("lead")
        done = False
        while not done:
            if scenario.hook is not None:
                scenario.hook(world, ctx)
            obs, _, terminated, truncated, info = env.step(driver.act(obs))
            done = terminated or truncated
            log.t.append(info["time_s"])
            log.speed.append(info["ego"]["speed_mps"])
            light = info["next_light"]
            log.light_distance.append(light["distance_m"] if light and light["approach"] == ap_index else math.nan)
            log.progress.append(info["route"]["progress_m"])
            log.lead_gap.append(_bumper_gap(world, lead) if isinstance(lead, TownVehicle) else math.nan)
            log.infractions += [inf["kind"] for inf in info["infractions"]]
            log.edges.append(tuple(info["lane_index"][:2]) if info["lane_index"] else ("", ""))
            if writer is not None:
                from towndrive.envs.evaluation import video_frame

                writer.append_data(video_frame(env, driver, info, name))
    finally:
        if writer is not None:
            writer.close()
        env.close()
    passed, detail = scenario.check(log, ctx)
    return ScenarioResult(name, bool(passed), detail, log.t[-1] if log.t else 0.0)


@dataclass(frozen=True)
class ScenarioItem:
    """One scenario as a work item (``envs.parallel``): the scenario's name, the config and where its video goes."""

    index: int
    name: str
    config: DriveConfig
    out: Path | None = None
    video: bool = False

    def run(self, worker: Worker) -> ScenarioResult:
        return run_scenario(self.name, worker.driver, self.config, self.out, self.video)

    def failed(self, error: str) -> ScenarioResult:
        return ScenarioResult(self.name, False, f"could not be run: {error}", 0.0)


def run_scenarios(names: list[str], driver: Any, config: DriveConfig, out: Path | None = None, video: bool = False,
                  workers: int = 1, ray: str | None = None) -> list[ScenarioResult]:
    """Run scenarios in order: here with ``driver``, or on ``workers`` processes or Ray (``driver`` a ``DriverSpec``)."""
    from towndrive.envs.parallel import DriverSpec, run_items

    items = [ScenarioItem(k, name, config, out, video) for k, name in enumerate(names)]
    if workers > 1 or ray is not None:
        if not isinstance(driver, DriverSpec):
            raise ValueError("run_scenarios(workers > 1) builds a driver in each worker: give a DriverSpec.")
        return run_items(items, driver, workers, f"scenarios ({workers} workers)", ray=ray)
    return [run_scenario(name, driver.build() if isinstance(driver, DriverSpec) else driver, config, out, video)
            for name in names]  # a spec: a fresh driver per scenario, as the command line has always done


def _bumper_gap(world: World, npc: TownVehicle) -> float:
    ego = world.ego
    return float(math.hypot(*(npc.position - ego.position)) - (npc.LENGTH + ego.LENGTH) / 2)


def format_results(driver: str, results: list[ScenarioResult]) -> str:
    lines = [f"Scenarios with driver {driver}:", "", "| scenario | result | detail |", "|---|---|---|"]
    for r in results:
        lines.append(f"| {r.name} | {'PASS' if r.passed else 'FAIL'} | {r.detail} |")
    lines.append("")
    lines.append(f"{sum(r.passed for r in results)} passed, {sum(not r.passed for r in results)} failed")
    return "\n".join(lines)
