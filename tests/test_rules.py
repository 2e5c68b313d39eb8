"""The rules of unsignalled towns: stop signs, all-way stops, give-way lines, posted limits, zebras with the
right of way, the ego's new infractions, parked cars and signs as world objects, and their ground truth.

Each test sets up the one situation its rule is about on a development town (style seeds 1000+) and checks
what happened, so that it fails if the rule is taken away.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from towndrive.envs.metrics import PENALTY
from towndrive.sim.objects import SemanticClass
from towndrive.sim.pedestrians import PedestrianCrowd
from towndrive.sim.rules import STOP_ZONE_M, front_to_line, in_priority_lane, lane_offsets
from towndrive.sim.town import Control, Entry, SignKind, Town, TownConfig
from towndrive.sim.world import PARKED_ID_BASE, World, WorldConfig, cached_town

SUBURB = TownConfig.of_style("suburb")
QUIET = WorldConfig(town=SUBURB, npc_count=0, pedestrian_count=0)


def _town(seed: int = 1000) -> Town:
    return cached_town(SUBURB, seed)


def _entry(town: Town, control: Control, min_length_m: float = 50.0) -> Entry:
    """The first entry with that control whose road is long enough to arrive at speed."""
    for e in town.entries:
        if e.control == control and town.lane((*e.edge, 0)).length >= min_length_m:
            return e
    raise AssertionError(f"no {control.name} entry in town {town.seed}")


def _world(town: Town, entry: Entry, start_s_from_end: float = 40.0, goal_straight: bool = True) -> World:
    lane = town.lane((*entry.edge, 0))
    goal = None
    for frm, tos in town.network.graph.items():
        if frm != entry.edge[1]:
            continue
        for to in tos:
            if town.lane_info[(frm, to, 0)].command.name == "STRAIGHT" or not goal_straight:
                goal = next(iter((to, t) for t in town.network.graph[to]))
    return World(town, QUIET, seed=0, start=(*entry.edge, 0), start_s=lane.length - start_s_from_end, goal=goal,
                 spawn_traffic=False)


def _drive(world: World, seconds: float, speed: float | None = None, throttle: float = 0.0) -> list[str]:
    """Step the world; the ego straight ahead at ``speed`` (held) or with ``throttle``. Returns the infractions."""
    kinds: list[str] = []
    for _ in range(round(seconds / world.config.dt_s)):
        if speed is not None:
            world.ego.speed = speed
        kinds += [i.kind for i in world.step(np.array([0.0, throttle]))]
    return kinds


# ------------------------------------------------------------------------------------------ NPCs
def _npc_through(town: Town, entry: Entry, target: float = 9.0) -> tuple[list[float], list[float]]:
    """An NPC driving through ``entry`` alone: its speeds and front-to-line distances until it is past the line."""
    world = _world(town, _entry(town, Control.PRIORITY), 60.0)
    world.ego.position = world.ego.position + 500.0  # out of the way
    lane = town.lane((*entry.edge, 0))
    npc = world.spawn_npc((*entry.edge, 0), lane.length - 45.0, SemanticClass.CAR, target_speed=target)
    assert npc is not None
    speeds, lines = [], []
    for _ in range(600):
        world.step(np.zeros(2))
        d = front_to_line(entry, npc.position, float(npc.heading), npc.LENGTH / 2)
        speeds.append(npc.speed)
        lines.append(d)
        if d < -3.0:
            break
    return speeds, lines


def test_npc_makes_a_full_stop_at_a_stop_sign_then_goes():
    town = _town()
    speeds, lines = _npc_through(town, _entry(town, Control.STOP))
    assert lines[-1] < -3.0, "the NPC never went on after its stop"
    stops = [d for v, d in zip(speeds, lines, strict=True) if v < 0.1 and d >= -0.5]
    assert stops and 0.0 <= min(stops) <= STOP_ZONE_M


def test_npc_keeps_to_the_posted_limit():
    town, edge = next((t, e) for t in map(_town, range(1000, 1020)) for e, kmh in t.speed_limits_kmh.items()
                      if kmh == 30 and t.lane((*e, 0)).length > 80 and t.lane_info[(*e, 0)].kind == "road")
    world = _world(town, _entry(town, Control.PRIORITY), 60.0)
    world.ego.position = world.ego.position + 500.0
    npc = world.spawn_npc((*edge, 0), 2.0, SemanticClass.CAR, target_speed=14.0)
    assert npc is not None
    top = 0.0
    for _ in range(160):
        world.step(np.zeros(2))
        if npc.lane_index[:2] == edge:
            top = max(top, npc.speed)
    assert 7.0 < top <= 30 / 3.6 + 1e-6


def _all_way_junction(town: Town) -> list[Entry]:
    nodes: dict[tuple[int, int], list[Entry]] = {}
    for e in town.entries:
        if e.control == Control.ALL_WAY_STOP:
            nodes.setdefault(e.node, []).append(e)
    return max(nodes.values(), key=len)


def test_all_way_stop_four_arms_at_once_go_one_by_one_in_arrival_order():
    town = _town(1000)
    arms = _all_way_junction(town)
    assert len(arms) >= 3
    world = _world(town, _entry(town, Control.PRIORITY), 60.0)
    world.ego.position = world.ego.position + 500.0
    npcs = []
    for k, e in enumerate(arms):  # staggered a little: the arrival order is known
        lane = town.lane((*e.edge, 0))
        npc = world.spawn_npc((*e.edge, 0), lane.length - 14.0 - 2.0 * k, SemanticClass.CAR, target_speed=6.0)
        assert npc is not None
        npc.speed = 4.0
        npcs.append(npc)
    entered: dict[int, float] = {}
    most_inside = 0
    for _ in range(round(60.0 / world.config.dt_s)):
        world.step(np.zeros(2))
        inside = world.junctions.occupants.get(arms[0].node, set())
        most_inside = max(most_inside, len(inside))
        for npc, e in zip(npcs, arms, strict=True):
            if npc.object_id not in entered and front_to_line(e, npc.position, float(npc.heading), npc.LENGTH / 2) < -1.0:
                entered[npc.object_id] = world.time_s
        if len(entered) == len(npcs):
            break
    assert len(entered) == len(npcs), f"deadlock: only {len(entered)} of {len(npcs)} went"
    assert most_inside == 1, "two vehicles were in the all-way-stop junction at once"
    order = sorted(entered, key=entered.get)
    assert order == [n.object_id for n in npcs], "not first come, first served"


def test_yield_entry_waits_for_priority_traffic():
    town = _town(1000)
    entry = _entry(town, Control.YIELD, 30.0)
    priority = next(e for e in town.entries_at(entry.node) if e.control == Control.PRIORITY
                    and town.lane((*e.edge, 0)).length > 60)
    world = _world(town, _entry(town, Control.PRIORITY), 60.0)
    world.ego.position = world.ego.position + 500.0
    lane_y = town.lane((*entry.edge, 0))
    minor = world.spawn_npc((*entry.edge, 0), lane_y.length - 20.0, SemanticClass.CAR, target_speed=8.0)
    lane_p = town.lane((*priority.edge, 0))
    major = world.spawn_npc((*priority.edge, 0), lane_p.length - 45.0, SemanticClass.CAR, target_speed=9.0)
    assert minor is not None and major is not None
    minor.speed, major.speed = 6.0, 9.0
    minor_in = major_in = None
    for _ in range(400):
        world.step(np.zeros(2))
        if minor_in is None and front_to_line(entry, minor.position, float(minor.heading), minor.LENGTH / 2) < -0.5:
            minor_in = world.time_s
        if major_in is None and front_to_line(priority, major.position, float(major.heading), major.LENGTH / 2) < -0.5:
            major_in = world.time_s
    assert major_in is not None and minor_in is not None
    assert minor_in > major_in, "the give-way car went before the priority car"


# ------------------------------------------------------------------------------------------ pedestrians
def test_pedestrian_has_the_right_of_way_on_an_unsignalled_zebra():
    town = _town()
    cw = next(c for c in town.crosswalks if c.approach < 0)
    centre = cw.polygon.mean(axis=0)
    heading = math.atan2(*(centre - cw.start)[::-1]) + math.pi / 2  # some car heading for the zebra
    direction = np.array([math.cos(heading), math.sin(heading)])
    far = (centre - 22.0 * direction)[None, :]
    near = (centre - 9.0 * direction)[None, :]
    speed, head = np.array([8.0]), np.array([heading])
    # 22 m away at 8 m/s it can stop: the pedestrian goes (a signalled crossing's gap rule would wait)
    assert not PedestrianCrowd._cannot_stop(cw, far, speed, head, cw.start, None)
    assert PedestrianCrowd._vehicle_blocks(cw, far, speed, head, cw.start, 7.0)
    # 9 m away at 8 m/s it cannot: the pedestrian waits
    assert PedestrianCrowd._cannot_stop(cw, near, speed, head, cw.start, None)
    # a car standing at the zebra waits for the pedestrian: it does not hold the pedestrian up
    assert not PedestrianCrowd._cannot_stop(cw, near, np.array([0.0]), head, cw.start, None)


def _car_facing_a_zebra() -> tuple[Town, PedestrianCrowd, object, np.ndarray, float]:
    """An empty crowd, an unsignalled zebra, and a car 6 m before it facing it: (town, crowd, zebra, car, heading)."""
    town = _town()
    crowd = PedestrianCrowd(town, 0, np.random.default_rng(0), 1000)
    cw = next(c for c in town.crosswalks if c.approach < 0)
    centre = cw.polygon.mean(axis=0)
    heading = math.atan2(*(centre - cw.start)[::-1]) + math.pi / 2
    car = (centre - 6.0 * np.array([math.cos(heading), math.sin(heading)]))[None, :]
    return town, crowd, cw, car, heading


def test_a_vehicle_that_has_waited_at_an_unsignalled_zebra_gets_its_turn():
    """Pedestrians who keep arriving would otherwise hold a waiting car for ever (two walking back and forth
    round a T-junction's corners did, for 150 s): after ZEBRA_TURN_S, new arrivals let it go first, until it
    has gone over."""
    from towndrive.sim.pedestrians import ZEBRA_TURN_S

    town, crowd, cw, car, heading = _car_facing_a_zebra()
    standing, moving, head = np.array([0.0]), np.array([2.0]), np.array([heading])
    assert not crowd._vehicles_turn(cw, car, standing, head, 10.0)  # it has only just stopped
    assert crowd._vehicles_turn(cw, car, standing, head, 10.0 + ZEBRA_TURN_S)  # it has waited: its turn
    assert crowd._vehicles_turn(cw, car, moving, head, 11.0 + ZEBRA_TURN_S)  # rolling off: still its turn
    gone = car + 30.0
    assert not crowd._vehicles_turn(cw, gone, moving, head, 12.0 + ZEBRA_TURN_S)  # gone over: walkers again
    assert not crowd._vehicles_turn(cw, car, standing, head, 13.0 + ZEBRA_TURN_S)  # a new wait starts afresh


def test_a_vehicles_wait_counts_from_when_it_stood_not_from_the_next_walkers_arrival():
    """A car stands at a zebra while one walker crosses; the next walker arrives after ZEBRA_TURN_S: it lets the
    car go first. Before, the car's clock started only when a waiting walker first asked, so a walker who
    arrived and asked at once always found it just started and stepped out (a car inside a junction waited
    23 s for one walker after another)."""
    from towndrive.sim.lights import LightTiming, TrafficLights
    from towndrive.sim.pedestrians import ZEBRA_TURN_S, Pedestrian

    town, crowd, cw, car, heading = _car_facing_a_zebra()
    first = Pedestrian(1000, cw.start.copy(), 0.0, 0.3, (0.5, 0.5, 0.5), cw.index, True, state="crossing",
                       target=cw.end.copy())
    crowd.peds = [first]
    lights = TrafficLights(town, LightTiming(), np.random.default_rng(0))
    dt, tick = 0.05, 0
    for _ in range(round((ZEBRA_TURN_S + 1.0) / dt)):
        crowd.step(dt, lights, car, np.array([0.0]), np.array([heading]), tick)
        tick += 1
    assert first.state == "crossing"  # still on the zebra: the car still waits
    second = Pedestrian(1001, cw.start.copy(), 0.0, 1.3, (0.5, 0.5, 0.5), cw.index, True)
    crowd.peds = [second]
    for _ in range(8):
        crowd.step(dt, lights, car, np.array([0.0]), np.array([heading]), tick)
        tick += 1
    assert second.state == "waiting"


@pytest.mark.parametrize("style", ["classic", "suburb", "downtown"])
def test_pedestrians_turn_the_corner_to_another_crossing_on_foot(style):
    """Every kerb end of a crossing leads to another crossing of the junction, walked without stepping on a
    lane; sent back over the same crossing, walkers at wide corners and T-junctions crossed to and fro."""
    town = cached_town(TownConfig.of_style(style), 4005)
    crowd = PedestrianCrowd(town, 0, np.random.default_rng(0), 1000)
    for (idx, at_start), (nxt, nxt_start) in crowd._corner_next.items():
        assert nxt != idx
        cw, cw2 = town.crosswalks[idx], town.crosswalks[nxt]
        a, b = (cw.start if at_start else cw.end), (cw2.start if nxt_start else cw2.end)
        assert crowd._walkable(a, b) and cw.node == cw2.node


# ------------------------------------------------------------------------------------------ the ego
def test_stop_sign_run_is_charged_a_full_stop_is_not():
    town = _town()
    entry = _entry(town, Control.STOP)
    world = _world(town, entry, 30.0)
    assert _drive(world, 5.0, speed=7.0).count("stop_sign") == 1
    world = _world(town, entry, 30.0)
    lane = town.lane((*entry.edge, 0))
    while front_to_line(entry, world.ego.position, float(world.ego.heading), world.ego.LENGTH / 2) > 4.0:
        _drive(world, 0.05, speed=5.0)
    kinds = _drive(world, 1.0, throttle=-1.0)  # a full stop at the line
    assert world.ego.speed < 0.1
    kinds += _drive(world, 4.0, speed=5.0)
    assert "stop_sign" not in kinds
    assert lane.length > 0


def _priority_setup(gap_m: float) -> tuple[World, Entry, Entry, object]:
    town = _town(1000)
    entry = _entry(town, Control.YIELD, 30.0)
    priority = next(e for e in town.entries_at(entry.node) if e.control == Control.PRIORITY
                    and town.lane((*e.edge, 0)).length > 60)
    world = _world(town, entry, 12.0)
    lane_p = town.lane((*priority.edge, 0))
    major = world.spawn_npc((*priority.edge, 0), lane_p.length - gap_m - major_half(), SemanticClass.CAR,
                            target_speed=0.0)
    assert major is not None
    return world, entry, priority, major


def _in_lanes_of(world: World, arm: Entry, point: np.ndarray) -> bool:
    return any(in_priority_lane(world.town, arm, offset, point) for offset in lane_offsets(world.town, arm))


def test_failed_to_yield_in_front_of_priority_traffic():
    """Charged as the front bumper enters a priority lane with a car in it under YIELD_CONFLICT_S away; the
    same car farther off, or gone by before we get there, is no infraction."""
    for gap_m, charged in ((30.0, True), (70.0, False), (8.0, False)):
        world, entry, priority, major = _priority_setup(gap_m)
        kinds, entered = [], False
        for _ in range(100):  # the ego's front bumper 21 m past its line
            major.speed = 8.0  # the priority car keeps coming (it would have to brake)
            major.target_speed = 8.0
            kinds += _drive(world, 0.05, speed=6.0)
            ego = world.ego
            front = ego.position + ego.LENGTH / 2 * np.array([math.cos(ego.heading), math.sin(ego.heading)])
            entered = entered or _in_lanes_of(world, priority, front)
        assert entered
        assert ("failed_to_yield" in kinds) == charged, (gap_m, kinds)


def test_edging_past_the_give_way_line_to_look_is_no_failure_to_yield():
    """A car that crosses its give-way line and stops short of the priority lanes while priority traffic goes by
    has yielded (where buildings stand at the corner, that is where the cross street can be seen from)."""
    world, entry, priority, major = _priority_setup(40.0)
    kinds: list[str] = []
    ego = world.ego
    while front_to_line(entry, ego.position, float(ego.heading), ego.LENGTH / 2) > -2.0:
        major.speed = major.target_speed = 8.0
        kinds += _drive(world, 0.05, speed=3.0)
    assert 0.0 < front_to_line(priority, major.position, float(major.heading), major.LENGTH / 2) < 3.0 * 8.0
    for _ in range(100):
        major.speed = major.target_speed = 8.0
        kinds += _drive(world, 0.05, speed=0.0)
    front = ego.position + ego.LENGTH / 2 * np.array([math.cos(ego.heading), math.sin(ego.heading)])
    assert not _in_lanes_of(world, priority, front)
    assert front_to_line(priority, major.position, float(major.heading), major.LENGTH / 2) < -10.0  # gone by
    kinds += _drive(world, 3.0, speed=5.0)
    assert "failed_to_yield" not in kinds


def major_half() -> float:
    return 4.5 / 2


def test_speeding_once_per_stretch_and_a_tolerance():
    town = _town()
    edge = next(e for e, kmh in town.speed_limits_kmh.items() if kmh == 30 and town.lane((*e, 0)).length > 65
                and town.lane_info[(*e, 0)].kind == "road")
    entry = town.entry_for_edge(edge)
    assert entry is not None
    world = _world(town, entry, town.lane((*edge, 0)).length - 2.0)
    assert world.speed_limit_here_kmh() == 30
    assert "speeding" not in _drive(world, 1.5, speed=30 / 3.6 * 1.05)  # within the tolerance
    kinds = _drive(world, 2.0, speed=12.0)
    assert kinds.count("speeding") == 1
    kinds = _drive(world, 0.5, speed=8.0) + _drive(world, 1.5, speed=12.0)
    assert kinds.count("speeding") == 1  # a new stretch


def test_classic_towns_have_no_posted_limits_stop_signs_or_parked_cars():
    town = cached_town(TownConfig(), 0)
    assert not town.speed_limits_kmh and not town.parked_cars
    assert {e.control for e in town.entries} == {Control.SIGNAL}
    world = World(town, WorldConfig(npc_count=0, pedestrian_count=0), 0, spawn_traffic=False)
    assert world.speed_limit_here_kmh() is None
    assert not world._unsignalled


def test_penalties_of_the_new_infractions():
    assert PENALTY["stop_sign"] == 0.80
    assert 0 < PENALTY["failed_to_yield"] < 1 and PENALTY["stop_sign"] < PENALTY["speeding"] < 1


# ------------------------------------------------------------------------------------------ world objects
def test_parked_cars_are_objects_and_obstacles():
    town = _town()
    car = town.parked_cars[0]
    world = World(town, QUIET, 0, spawn_traffic=False)
    world.ego.position = car.position + np.array([30.0, 0.0])
    world.step_count += 1
    snaps = {s.object_id: s for s in world.object_snapshots()}
    parked = [s for oid, s in snaps.items() if oid >= PARKED_ID_BASE]
    assert parked and all(s.kind == SemanticClass.CAR for s in parked)
    assert any(math.hypot(s.x - car.position[0], s.y - car.position[1]) < 1e-6 for s in parked)
    from towndrive.sim.geometry import rect_corners

    assert world.static.hits(rect_corners(car.position + np.array([0.3, 0.3]), car.heading, 4.0, 1.8))
    sign = town.signs[0]
    assert world.static.hits(rect_corners(sign.position, 0.0, 0.6, 0.6))


def test_info_has_the_next_control_signs_and_the_limit():
    from towndrive.envs.drive_env import DriveConfig, DriveEnv

    town = _town()
    entry = _entry(town, Control.STOP)
    world = _world(town, entry, 30.0)
    env = DriveEnv(DriveConfig(world=replace(QUIET, town=SUBURB), render_camera=False))
    try:
        _, info = env.reset(seed=0, options={"world": world})
        nc = info["next_control"]
        assert nc["kind"] == "stop" and nc["entry"] == entry.index and 25.0 < nc["distance_m"] < 30.0
        stop_signs = [g for g in info["signs"] if g["kind"] == "stop"]
        assert stop_signs and stop_signs[0]["distance_m"] < 35.0
        assert info["speed_limit_kmh"] == town.speed_limit_kmh(entry.edge)
        assert any(g.kind == SignKind.SPEED_LIMIT for g in town.signs)
    finally:
        env.close()


@pytest.mark.parametrize("style", ["suburb", "downtown"])
def test_world_determinism_with_rules(style: str):
    def run() -> list[tuple[float, float]]:
        town = cached_town(TownConfig.of_style(style), 1001)
        world = World(town, WorldConfig(town=TownConfig.of_style(style)), 3)
        out = []
        for _ in range(200):
            world.step(np.array([0.0, 0.3]))
            out += [(float(n.position[0]), float(n.position[1])) for n in world.npcs]
        return out

    assert run() == run()


NEW_SCENARIOS = ["stop_sign_cross_traffic", "t_junction_priority_turn", "speed_limit_change", "parked_door_zone",
                 "pedestrian_unsignalled"]


@pytest.mark.parametrize("name", NEW_SCENARIOS)
def test_autopilot_passes_the_scenarios_of_unsignalled_towns(name: str):
    from towndrive.agent.autopilot import Autopilot
    from towndrive.envs.drive_env import DriveConfig
    from towndrive.envs.scenarios import run_scenario

    result = run_scenario(name, Autopilot(), DriveConfig(render_camera=False))
    assert result.passed, result.detail


def test_autopilot_waits_for_the_turning_lane_rather_than_turn_across_the_other():
    """Announced a right turn in the inner lane with a car alongside in the outer one, the autopilot holds
    short of the junction until it can change lanes; it used to turn from the inner lane, across the car."""
    from towndrive.agent.drivers import make_driver
    from towndrive.envs.drive_env import DriveConfig, DriveEnv
    from towndrive.sim.town import Command

    town = cached_town(TownConfig(), 4000)
    right = next(k for k, i in town.lane_info.items() if i.kind == "connector" and i.command == Command.RIGHT
                 and k[2] == 1 and town.lane_info[(*_edge_into(town, k[0]), 0)].kind == "road")
    road = _edge_into(town, right[0])
    goal = (right[1], next(iter(town.network.graph[right[1]])))
    lane = town.lane((*road, 0))
    world = World(town, WorldConfig(npc_count=0, pedestrian_count=0), seed=0, start=(*road, 0),
                  start_s=lane.length - 45.0, goal=goal, spawn_traffic=False)
    npc = world.spawn_npc((*road, 1), lane.length - 45.0, SemanticClass.CAR, target_speed=7.0, min_gap_m=0.0)
    assert npc is not None
    env = DriveEnv(DriveConfig(render_camera=False))
    driver = make_driver("autopilot")
    obs, _ = env.reset(seed=0, options={"world": world})
    driver.reset(env)
    entered = None
    for _ in range(1200):  # it waits beside the car at the junction's red light, then changes lanes
        obs, _, term, trunc, info = env.step(driver.act(obs))
        if entered is None and world.route[world.route_index][:2] == right[:2]:
            entered = world.ego_lane[0] if world.ego_lane is not None else None
        if term or trunc or world.route_index > world.route.index(right[:2]):
            break
    env.close()
    assert entered is not None and entered[2] == 1, entered
    assert not info["infraction_counts"]


def _edge_into(town: Town, node: str) -> tuple[str, str]:
    return next((frm, to) for frm, tos in town.network.graph.items() for to in tos if to == node)


def test_a_truck_leaving_the_path_still_blocks_it_with_its_rear():
    """A truck turning off the path at 0.45 rad has its centre 2.9 m beside the lane but its rear bumper in it:
    the path search counts its bumpers whenever they swing more than BUMPER_SWING_M out of its centre's line
    (before, only beyond 0.5 rad, and a car going straight on rear-ended such a truck)."""
    from highway_env.road.lane import StraightLane

    from towndrive.sim.traffic import Agents, path_gap

    lane = StraightLane(np.array([0.0, 0.0]), np.array([100.0, 0.0]), width=3.5)
    heading = 0.45  # turning right (y down) off the path
    centre = np.array([30.0 + 3.4 * math.cos(heading), 1.45 + 3.4 * math.sin(heading)])  # rear bumper in the lane
    agents = Agents(positions=centre[None, :], headings=np.array([heading]), speeds=np.array([0.5]),
                    half_lengths=np.array([3.4]), is_pedestrian=np.array([False]), ids=np.array([7]),
                    on_crossing=np.array([False]))
    gap, _ = path_gap([(lane, 0.0)], 5.0, 2.3, agents, skip_id=999, origin=np.array([5.0, 0.0]), lookahead_m=60.0)
    assert gap is not None and gap == pytest.approx(30.0 - 5.0 - 2.3, abs=0.5)


def _opposite_give_way_pair() -> tuple[Town, Entry, Entry]:
    for seed in range(1000, 1040):
        town = _town(seed)
        for e in town.entries:
            if e.control != Control.YIELD:
                continue
            other = next((o for o in town.entries_at(e.node) if o.control == Control.YIELD and o.arm != e.arm
                          and abs(math.remainder(o.travel_heading - e.travel_heading, 2 * math.pi)) > 3.0), None)
            if other is not None:
                return town, e, other
    raise AssertionError("no junction with two opposite give-way lines")


@pytest.mark.parametrize("oncoming_turns_left", [False, True])
def test_a_left_turn_from_a_give_way_line_waits_for_the_oncoming_give_way_traffic(oncoming_turns_left: bool):
    """Two give-way lines face each other across a priority street: the left turn waits for the car coming the
    other way (before, both saw a free junction in the same step, went, and collided in the exit lane), unless
    that car turns left too (the two pass in front of each other; waiting for each other would be for ever)."""
    from towndrive.sim.rules import JunctionRules
    from towndrive.sim.town import Command
    from towndrive.sim.traffic import Agents, junction_gap

    town, mine, other = _opposite_give_way_pair()
    lane = town.lane((*other.edge, 0))
    pos = lane.position(lane.length - 20.0, 0.0)  # 20 m before its line, on its lane, heading in at 6 m/s
    agents = Agents(positions=pos[None, :], headings=np.array([other.travel_heading]), speeds=np.array([6.0]),
                    half_lengths=np.array([2.25]), is_pedestrian=np.array([False]), ids=np.array([7]),
                    on_crossing=np.array([False]), turning_left=np.array([oncoming_turns_left]))
    rules = JunctionRules(town)
    wait_left = junction_gap(town, rules, 1, mine, Command.LEFT, 0.3, agents, None)
    wait_straight = junction_gap(town, rules, 1, mine, Command.STRAIGHT, 0.3, agents, None)
    assert wait_straight is None
    assert (wait_left is None) == oncoming_turns_left


@pytest.mark.parametrize(("lateral_m", "blocks"), [(2.5, True), (3.3, False)])
def test_a_turning_cars_swept_front_is_kept_clear_of_a_standing_vehicle(lateral_m: float, blocks: bool):
    """The car steers its rear along the path, so in a turn its front runs outside the arc by length^2 / (2 R)
    (0.88 m on a 12 m turn): a truck standing 2.5 m from a turn's centre line (centre points count within
    2.2 m on a straight) is in the way (a turning car clipped one standing at the exit), one 3.3 m away is not."""
    from towndrive.sim.traffic import front_sweep_m

    lane = _quarter_turn()
    assert front_sweep_m(lane, 2.3) == pytest.approx(4.6 ** 2 / 24.0)
    assert (_turn_gap(lane, 12.0, lateral_m, outside=True) is not None) == blocks


def _quarter_turn():
    from highway_env.road.lane import CircularLane

    return CircularLane(np.array([0.0, 0.0]), 12.0, 0.0, math.pi / 2, clockwise=True, width=3.5)


def _turn_gap(lane, s: float, lateral_m: float, outside: bool, half_length_m: float = 3.4) -> float | None:
    """``path_gap`` of a car at s = 2 m on the lane to a truck standing at s, lateral_m off the centre line on
    the outside or the inside of the turn."""
    from towndrive.sim.traffic import Agents, path_gap

    side = [lane.position(s, sign * lateral_m) for sign in (1.0, -1.0)]
    point = max(side, key=lambda p: np.hypot(*p)) if outside else min(side, key=lambda p: np.hypot(*p))
    agents = Agents(positions=point[None, :], headings=np.array([lane.heading_at(max(s, 0.0))]),
                    speeds=np.array([0.0]), half_lengths=np.array([half_length_m]), is_pedestrian=np.array([False]),
                    ids=np.array([7]), on_crossing=np.array([False]))
    gap, _ = path_gap([(lane, 0.0)], 2.0, 2.3, agents, skip_id=999, origin=lane.position(2.0, 0.0), lookahead_m=40.0)
    return gap


def test_the_swept_front_is_only_outside_the_turn_and_beside_it():
    """The front swings out only on the outside of the arc and only once the car is in the turn: a car
    standing 2.8 m off the centre line on the inside of the turn, or beside the lane just before the turn
    starts (a car waiting in the next lane at the line while this one turns away), is not in the way. Before,
    the sweep counted on both sides and before the turn, and a car turning right waited behind the line for
    one standing in the next lane until that one left."""
    lane = _quarter_turn()
    assert _turn_gap(lane, 12.0, 2.8, outside=True, half_length_m=2.3) is not None
    assert _turn_gap(lane, 12.0, 2.8, outside=False, half_length_m=2.3) is None
    assert _turn_gap(lane, -1.5, 2.8, outside=True, half_length_m=2.3) is None
