"""The infraction detectors keep no stale state, and the audit recomputes what the world reports.

The red-light cases are the ones an evaluator gets wrong when it keeps watching a junction the car has
left: a parallel street's junction crossed on green while the old one is red (an invented run), and a
red crossed on the street the car is really on (a missed one). There is no turn on red in towndrive.
"""

from __future__ import annotations

import numpy as np
import pytest

from towndrive.envs.audit import AuditTrace, audit_episode
from towndrive.sim.objects import LightState
from towndrive.sim.world import World, WorldConfig

CFG = WorldConfig()


def quiet_world(town, start, start_s) -> World:
    return World(town, CFG, 0, start=start, start_s=start_s, spawn_traffic=False)


def run(world: World, action, seconds: float, truth: AuditTrace | None = None) -> list[dict]:
    out = []
    for _ in range(int(round(seconds / CFG.dt_s))):
        out += [dict(i.__dict__) for i in world.step(np.asarray(action, float))]
        if truth is not None:
            truth.record(world, False)
    return out


def parallel_pair(town):
    """Two approaches from the same side into junctions next to each other across the street grid:
    parallel streets, the same direction of travel, stop bars level with each other."""
    for a in town.approaches:
        for b in town.approaches:
            if a.arm == b.arm and a.node[0] == b.node[0] and abs(a.node[1] - b.node[1]) == 1 and a.arm.name in "WE":
                return a, b
            if a.arm == b.arm and a.node[1] == b.node[1] and abs(a.node[0] - b.node[0]) == 1 and a.arm.name in "NS":
                return a, b
    raise AssertionError("the default town has no parallel approaches")


def lane_of(town, approach, k=0):
    index = (approach.edge[0], approach.edge[1], k)
    return index, town.lane(index)


def place(world: World, index, s: float, speed: float) -> None:
    lane = world.town.lane(index)
    world.ego.position = lane.position(s, 0.0)
    world.ego.heading = lane.heading_at(s)
    world.ego.speed = speed
    world.step(np.array([0.0, 0.0]))  # the world sees the car there before it moves on


def stop_at_red_then_carry_to(town, red: LightState, green: LightState):
    """The car waits at approach A's red, then (carried, as if it had driven round) approaches the
    parallel junction B; A's light is ``red``, B's is ``green``. Returns B and the infractions."""
    a, b = parallel_pair(town)
    index_a, lane_a = lane_of(town, a)
    world = quiet_world(town, index_a, lane_a.length - 4.0)
    world.lights.force(a.index, red, until_s=60.0)
    world.lights.force(b.index, green, until_s=60.0)
    run(world, [0.0, -1.0], 3.0)  # stands at A's line: A is being watched
    index_b, lane_b = lane_of(town, b)
    world.ego.position = lane_b.position(lane_b.length - 12.0, 0.0)
    world.ego.heading = lane_b.heading_at(lane_b.length - 12.0)
    world.ego.speed = 8.0
    return b, run(world, [0.0, 0.3], 3.0)


def test_a_parallel_junction_crossed_on_green_is_no_run_of_the_old_junctions_red(town):
    _, events = stop_at_red_then_carry_to(town, red=LightState.RED, green=LightState.GREEN)
    assert [e for e in events if e["kind"] == "red_light"] == []


def test_the_approach_the_car_is_on_is_the_one_watched(town):
    b, events = stop_at_red_then_carry_to(town, red=LightState.GREEN, green=LightState.RED)
    runs = [e for e in events if e["kind"] == "red_light"]
    assert len(runs) == 1 and runs[0]["approach"] == b.index and runs[0]["other_kind"] == "traffic_light"


def test_a_red_driven_through_deliberately_is_one_run_with_where_and_which_light(town):
    ap = town.approaches[2]
    index, lane = lane_of(town, ap)
    world = quiet_world(town, index, lane.length - 15.0)
    world.lights.force(ap.index, LightState.RED, until_s=30.0)
    world.ego.speed = 8.0
    events = run(world, [0.0, 0.2], 4.0)
    runs = [e for e in events if e["kind"] == "red_light"]
    assert len(runs) == 1
    assert runs[0]["approach"] == ap.index and runs[0]["speed_mps"] > 5.0
    assert np.hypot(runs[0]["x"] - ap.stop_line_center[0], runs[0]["y"] - ap.stop_line_center[1]) < 8.0


def test_a_car_that_stops_on_the_bar_waits_and_goes_on_green_is_not_charged(town):
    ap = town.approaches[2]
    index, lane = lane_of(town, ap)
    world = quiet_world(town, index, 8.0)
    place(world, index, lane.length - world.ego.LENGTH / 2 - 0.2, 0.0)  # the bumper on the painted bar
    world.lights.force(ap.index, LightState.RED, until_s=world.time_s + 10.0)
    waiting = run(world, [0.0, -1.0], 5.0)
    world.lights.force(ap.index, LightState.GREEN, until_s=world.time_s + 10.0)
    going = run(world, [0.0, 0.5], 4.0)
    assert world.ego.speed > 2.0
    assert not [e for e in waiting + going if e["kind"] == "red_light"]


def test_creeping_over_the_bar_on_red_is_a_run(town):
    ap = town.approaches[2]
    index, lane = lane_of(town, ap)
    world = quiet_world(town, index, 8.0)
    place(world, index, lane.length - world.ego.LENGTH / 2 - 0.2, 0.0)
    world.lights.force(ap.index, LightState.RED, until_s=world.time_s + 30.0)
    events = run(world, [0.0, 0.15], 3.0)
    assert [e["kind"] for e in events].count("red_light") == 1


@pytest.mark.parametrize("steer", [0.0, 0.6])
def test_no_turn_on_red_from_the_right_lane(town, steer):
    """towndrive's towns have no right turn on red (as in most of Europe): crossing the bar from the
    right-hand lane on red is a run, whether the car then goes straight or turns right."""
    ap = town.approaches[2]
    index, lane = lane_of(town, ap, k=1)
    world = quiet_world(town, index, lane.length - 10.0)
    world.lights.force(ap.index, LightState.RED, until_s=30.0)
    world.ego.speed = 5.0
    events = run(world, [0.0, 0.0], 1.2) + run(world, [steer, 0.0], 2.0)
    runs = [e for e in events if e["kind"] == "red_light"]
    assert len(runs) == 1 and runs[0]["approach"] == ap.index


def test_a_deviation_after_coming_back_to_the_route_counts_again(town):
    world = World(town, CFG, 0, spawn_traffic=False)
    on_route = set(world.route)
    other = next(k for k in town.road_lanes() if k[:2] not in on_route)
    back = (*world.route[world.route_index], 0)
    kinds = []
    for _ in range(2):
        place(world, other, 10.0, 0.0)
        kinds += [e["kind"] for e in run(world, [0.0, -1.0], CFG.route_deviation_s + 0.5)]
        place(world, back, 10.0, 0.0)
        kinds += [e["kind"] for e in run(world, [0.0, -1.0], 0.5)]
    assert kinds.count("route_deviation") == 2


def test_the_audit_confirms_a_red_run_and_a_collision_and_misses_nothing(town):
    from towndrive.sim.objects import SemanticClass

    ap = town.approaches[2]
    index, lane = lane_of(town, ap)
    world = quiet_world(town, index, lane.length - 15.0)
    world.lights.force(ap.index, LightState.RED, until_s=30.0)
    out_edge = next(iter(town.network.graph[ap.edge[1]]))
    truth = AuditTrace()
    world.ego.speed = 8.0
    reported = run(world, [0.0, 0.2], 3.0, truth)
    parked = world.spawn_npc((ap.edge[1], out_edge, 0), 14.0, SemanticClass.CAR, target_speed=0.0)
    assert parked is not None
    parked.speed = 0.0
    reported += run(world, [0.0, 0.5], 4.0, truth)
    kinds = [e["kind"] for e in reported]
    assert "red_light" in kinds
    result = audit_episode(town, truth, reported)
    assert result["red_light"]["confirmed"] == 1
    for kind, outcome in result.items():
        assert outcome["unconfirmed"] == [] and outcome["missed"] == [], kind


def test_the_audit_catches_a_run_the_world_did_not_report(town):
    ap = town.approaches[2]
    index, lane = lane_of(town, ap)
    world = quiet_world(town, index, lane.length - 15.0)
    world.lights.force(ap.index, LightState.RED, until_s=30.0)
    truth = AuditTrace()
    world.ego.speed = 8.0
    reported = [e for e in run(world, [0.0, 0.2], 3.0, truth) if e["kind"] != "red_light"]
    result = audit_episode(town, truth, reported)
    assert len(result["red_light"]["missed"]) == 1 and result["red_light"]["confirmed"] == 0
