"""Closed-loop behaviour of the world: NPCs and lights, pedestrians, and every infraction kind."""

from __future__ import annotations

import math

import numpy as np
import pytest

from towndrive.sim.objects import LightState, SemanticClass
from towndrive.sim.pedestrians import PedestrianCrowd
from towndrive.sim.world import World, WorldConfig

CFG = WorldConfig()


def quiet_world(town, start=None, start_s=8.0, seed=0) -> World:
    """A world with no traffic: the test adds exactly what it needs."""
    return World(town, CFG, seed, start=start, start_s=start_s, spawn_traffic=False)


def far_lane(town, approach):
    """A road lane far from an approach, for parking the ego out of the way."""
    node = np.array(approach.stop_line_center)
    return max(town.road_lanes(), key=lambda k: np.linalg.norm(town.lane(k).position(5, 0) - node))


def test_npc_stops_at_red_light_and_goes_on_green(town):
    ap = town.approaches[5]
    world = quiet_world(town, start=far_lane(town, ap))
    lane_index = (ap.edge[0], ap.edge[1], 1)
    lane = town.lane(lane_index)
    npc = world.spawn_npc(lane_index, lane.length - 45.0, SemanticClass.CAR, target_speed=10.0)
    world.lights.force(ap.index, LightState.RED, until_s=20.0)
    brake = np.array([0.0, -1.0])
    for _ in range(int(18.0 / CFG.dt_s)):
        world.step(brake)
    front_s = lane.local_coordinates(npc.position)[0] + npc.LENGTH / 2
    assert npc.speed < 0.1
    assert 0.0 <= (lane.length - 0.5) - front_s <= 3.0  # stopped 0-3 m short of the bar
    world.lights.force(ap.index, LightState.GREEN, until_s=60.0)
    for _ in range(int(8.0 / CFG.dt_s)):
        world.step(brake)
    assert npc.lane_index[:2] != ap.edge  # it drove on into the junction


def test_pedestrian_waits_for_walk_signal_then_crosses(town):
    cw = town.crosswalks[3]
    world = quiet_world(town, start=far_lane(town, town.approaches[cw.approach]))
    world.crowd = PedestrianCrowd(town, 1, np.random.default_rng(0), 1000)
    ped = world.crowd.peds[0]
    ped.crosswalk, ped.at_start, ped.position, ped.state = cw.index, True, cw.start.copy(), "waiting"
    world.lights.force(cw.approach, LightState.GREEN, until_s=5.0)
    brake = np.array([0.0, -1.0])
    for _ in range(int(4.0 / CFG.dt_s)):
        world.step(brake)
    assert ped.state == "waiting"  # cars on that arm have green: no walking
    world.lights.force(cw.approach, LightState.RED, until_s=40.0)
    crossed = False
    for _ in range(int(20.0 / CFG.dt_s)):
        world.step(brake)
        if np.linalg.norm(ped.position - cw.end) < 0.5 or ped.crosswalk != cw.index:
            crossed = True
            break
    assert crossed


def drive_until(world: World, action, seconds: float) -> list[str]:
    kinds = []
    for _ in range(int(seconds / CFG.dt_s)):
        kinds += [i.kind for i in world.step(np.asarray(action))]
    return kinds


def test_npc_brakes_for_a_car_poking_its_nose_into_the_lane(town):
    """A car standing at an angle (mid-turn) with its centre a lane away but its bumper in the NPC's lane."""
    lane_index = max((k for k in town.road_lanes() if k[2] == 1), key=lambda k: town.lane(k).length)
    lane = town.lane(lane_index)
    world = quiet_world(town, start=far_lane(town, town.approaches[0]))
    npc = world.spawn_npc(lane_index, 5.0, SemanticClass.CAR, target_speed=8.0)
    side = lane.position(32.0, 2.5) - lane.position(32.0, 0.0)
    world.ego.position = lane.position(32.0, 2.5)
    world.ego.heading = math.atan2(-side[1], -side[0]) + 0.7  # pointing across, into the lane
    world.ego.speed = 0.0
    kinds = drive_until(world, [0.0, -1.0], 10.0)
    assert "collision_vehicle" not in kinds
    assert npc.speed < 0.1 and lane.local_coordinates(npc.position)[0] < 32.0  # stopped short of it


def test_waiting_pedestrians_stand_on_the_pavement_away_from_the_corner(town):
    """Cars turning right cut the kerb corner: nobody is placed between the zebra and the junction."""
    crowd = PedestrianCrowd(town, 200, np.random.default_rng(3), 1000)
    for ped in crowd.peds:
        cw = town.crosswalks[ped.crosswalk]
        here, there = (cw.start, cw.end) if ped.at_start else (cw.end, cw.start)
        outward = (here - there) / np.linalg.norm(here - there)
        away = ped.position - here
        assert -1e-9 <= away @ outward <= 0.6 + 1e-9  # on the pavement, not towards the road
        along = away - (away @ outward) * outward
        junction = town.node_position(cw.node)
        assert np.linalg.norm(along) <= 0.8 + 1e-9
        assert np.linalg.norm(here + along - junction) >= np.linalg.norm(here - junction) - 1e-9  # away from it


def test_pedestrian_walks_round_a_car_standing_on_the_crossing_not_into_it(town):
    cw = town.crosswalks[3]
    world = quiet_world(town, start=far_lane(town, town.approaches[cw.approach]))
    across = (cw.end - cw.start) / np.linalg.norm(cw.end - cw.start)
    world.ego.position = cw.start + across * 0.45 * np.linalg.norm(cw.end - cw.start)  # mid-road, on the zebra
    world.ego.heading = math.atan2(across[0], -across[1])  # along the road
    world.ego.speed = 0.0
    world.crowd = PedestrianCrowd(town, 1, np.random.default_rng(0), 1000)
    ped = world.crowd.peds[0]
    ped.crosswalk, ped.at_start, ped.position = cw.index, True, cw.start.copy()
    ped.state, ped.target = "crossing", cw.end.copy()
    kinds, was_blocked = [], False
    for _ in range(int(25.0 / CFG.dt_s)):
        kinds += [i.kind for i in world.step(np.array([0.0, -1.0]))]
        was_blocked |= ped.blocked
        if ped.state != "crossing":
            break
    assert "collision_pedestrian" not in kinds
    assert was_blocked  # it stopped at the car first
    assert ped.state == "walking"  # then got across, round the car


def test_npc_jammed_inside_a_junction_is_moved_out_of_sight(town):
    """Two cars each in the other's path inside a junction wait for ever; like SUMO's time-to-teleport, the
    world moves a jammed NPC elsewhere (same car) after npc_jam_teleport_s."""
    inside = next(k for k, info in town.lane_info.items() if info.kind == "connector")
    world = quiet_world(town, start=far_lane(town, town.approaches[0]))
    npc = world.spawn_npc(inside, 0.5, SemanticClass.TRUCK, color=(0.1, 0.2, 0.3), target_speed=8.0)
    lane = town.lane(inside)
    world.ego.position, world.ego.heading = lane.position(9.0, 0.0), lane.heading_at(9.0) + 1.2  # across its way
    world.ego.speed = npc.speed = 0.0
    where = npc.position.copy()
    drive_until(world, [0.0, -1.0], 5.0)
    assert world.npcs[0] is npc and npc.speed < 0.1  # braked to wait for the ego, not yet moved
    drive_until(world, [0.0, -1.0], CFG.npc_jam_teleport_s)
    moved = world.npcs[0]
    assert moved is not npc and moved.object_id == npc.object_id and moved.kind == SemanticClass.TRUCK
    assert moved.color == (0.1, 0.2, 0.3) and np.linalg.norm(moved.position - where) > 1.0
    assert np.linalg.norm(moved.position - world.ego.position) >= CFG.npc_teleport_min_m
    assert moved in world.road.vehicles and npc not in world.road.vehicles


def test_collision_with_a_vehicle(town):
    start = town.road_lanes()[0]
    world = quiet_world(town, start=start)
    world.spawn_npc(start, 20.0, SemanticClass.CAR, target_speed=0.0)
    world.npcs[0].speed = 0.0
    assert "collision_vehicle" in drive_until(world, [0.0, 1.0], 6.0)


def test_collision_with_a_pedestrian(town):
    start = town.road_lanes()[0]
    world = quiet_world(town, start=start)
    world.crowd = PedestrianCrowd(town, 1, np.random.default_rng(0), 1000)
    ped = world.crowd.peds[0]
    lane = town.lane(start)
    ped.position, ped.state = lane.position(22.0, 0.0), "walking"
    ped.target = ped.position.copy()
    assert "collision_pedestrian" in drive_until(world, [0.0, 1.0], 6.0)


def test_collision_with_a_building(town):
    world = quiet_world(town)
    b = town.buildings[0]
    lo, hi = b.footprint.min(axis=0), b.footprint.max(axis=0)
    world.ego.position = np.array([lo[0] - 4.0, (lo[1] + hi[1]) / 2])
    world.ego.heading = 0.0
    world.ego.speed = 3.0
    assert "collision_static" in drive_until(world, [0.0, 0.5], 3.0)


def test_leaving_the_road(town):
    start = town.road_lanes()[0]
    world = quiet_world(town, start=start)
    world.ego.speed = 8.0
    kinds = drive_until(world, [1.0, 0.3], 5.0)
    assert "off_road" in kinds or "collision_static" in kinds
    world = quiet_world(town, start=start)
    world.ego.position = town.slab_polygons[0].mean(axis=0)
    assert "off_road" in drive_until(world, [0.0, 0.0], 0.1)


def test_driving_against_the_traffic(town):
    start = town.road_lanes()[0]
    world = quiet_world(town, start=start)
    world.ego.heading += math.pi
    assert "wrong_way" in drive_until(world, [0.0, 0.2], 0.5)


def test_running_a_red_light_is_detected_and_a_green_one_is_not(town):
    ap = town.approaches[2]
    lane_index = (ap.edge[0], ap.edge[1], 0)
    lane = town.lane(lane_index)
    for state, expected in ((LightState.RED, True), (LightState.GREEN, False)):
        world = quiet_world(town, start=lane_index, start_s=lane.length - 15.0)
        world.lights.force(ap.index, state, until_s=30.0)
        world.ego.speed = 8.0
        kinds = drive_until(world, [0.0, 0.2], 3.0)
        assert ("red_light" in kinds) is expected


def test_deviating_from_the_route(town):
    world = quiet_world(town)
    on_route = {e for e in world.route}
    other = next(k for k in town.road_lanes() if k[:2] not in on_route)
    lane = town.lane(other)
    world.ego.position = lane.position(10.0, 0.0)
    world.ego.heading = lane.heading_at(10.0)
    assert "route_deviation" in drive_until(world, [0.0, 0.0], CFG.route_deviation_s + 0.5)


def test_same_seed_same_episode(town):
    def run(seed):
        world = World(town, CFG, seed)
        for k in range(200):
            world.step(np.array([0.1 * math.sin(k / 10), 0.4]))
        return np.concatenate([world.ego.position] + [v.position for v in world.npcs]
                              + [p.position for p in world.pedestrians])

    assert np.array_equal(run(4), run(4))
    assert not np.array_equal(run(4), run(5))


@pytest.mark.parametrize("action", [[0.0, 1.0], [0.0, -1.0], [1.0, 0.5]])
def test_action_maps_to_limits(town, action):
    world = quiet_world(town)
    world.ego.speed = 5.0
    world.step(np.array(action))
    ego = world.ego
    assert ego.action["steering"] == pytest.approx(action[0] * ego.MAX_STEER_RAD)
    expected = action[1] * (ego.MAX_ACCEL_MPS2 if action[1] >= 0 else ego.MAX_BRAKE_MPS2) - ego.DRAG_MPS2
    assert ego.action["acceleration"] == pytest.approx(expected)


def test_an_arrived_route_counts_as_complete(town):
    """The episode ends ROUTE_ARRIVAL_M short of the route's last point; that is arriving, so completion is 1,
    not the share of the length driven (a clean route scored about 99 before)."""
    from towndrive.sim.world import ROUTE_ARRIVAL_M

    world = quiet_world(town)
    world.route_index = len(world.route) - 1
    last = world._route_starts[-1] - world._route_starts[-2]
    world.route_s = last - ROUTE_ARRIVAL_M - 1.0
    assert not world.route_done and world.route_completion < 1.0
    world.route_s = last - ROUTE_ARRIVAL_M + 0.5
    assert world.route_done and world.route_completion == 1.0
