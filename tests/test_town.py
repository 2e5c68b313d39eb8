"""Lane and route geometry of the generated town."""

from __future__ import annotations

import math

import numpy as np
import pytest
from highway_env.road.lane import CircularLane

from towndrive.sim.routes import command_at, random_route, route_length, shortest_route
from towndrive.sim.town import Command, TownConfig, generate_town


def test_town_is_at_least_three_by_three_with_two_lanes_each_way(town):
    assert len(town.xs) >= 4 and len(town.ys) >= 4
    for frm, tos in town.network.graph.items():
        for to, lanes in tos.items():
            assert len(lanes) == 2, (frm, to)
            for lane in lanes:
                assert lane.width == pytest.approx(3.5)


def test_every_lane_end_meets_the_start_of_each_next_lane_with_the_same_heading(town):
    net = town.network
    for frm, tos in net.graph.items():
        for to, lanes in tos.items():
            for nxt, next_lanes in net.graph.get(to, {}).items():
                for k in range(2):
                    a, b = lanes[k], next_lanes[k]
                    assert np.linalg.norm(a.position(a.length, 0) - b.position(0, 0)) < 1e-6, (frm, to, nxt, k)
                    assert abs(math.remainder(a.heading_at(a.length) - b.heading_at(0), 2 * math.pi)) < 1e-6


def test_four_way_junction_has_left_right_and_straight_connectors(town):
    commands = {}
    for (frm, _to, _), info in town.lane_info.items():
        if info.kind == "connector" and info.node == (1, 1):
            commands.setdefault(frm, set()).add(info.command)
    assert len(commands) == 4
    for cmds in commands.values():
        assert cmds == {Command.LEFT, Command.RIGHT, Command.STRAIGHT}


def test_right_turns_are_tighter_than_left_turns_and_corners_are_curved(town):
    radii = {Command.LEFT: [], Command.RIGHT: []}
    bends = 0
    for index, info in town.lane_info.items():
        lane = town.lane(index)
        if info.kind == "connector" and info.command in radii:
            assert isinstance(lane, CircularLane)
            radii[info.command].append(lane.radius)
        bends += info.kind == "bend" and isinstance(lane, CircularLane)
    assert max(radii[Command.RIGHT]) < min(radii[Command.LEFT])
    assert bends == 4 * 2 * 2  # four corners, two directions, two lanes


def test_signalled_approaches_have_stop_lines_crosswalks_and_lights(town):
    assert len(town.approaches) == len(town.crosswalks) == len(town.markings["stop_line"])
    for ap in town.approaches:
        lane = town.network.graph[ap.edge[0]][ap.edge[1]][0]
        # the stop bar's near edge sits half a metre before the lane's end, across the lane
        s, lat = lane.local_coordinates(ap.stop_line_center)
        assert s == pytest.approx(lane.length - 0.5, abs=1e-6)
        assert not town.on_road(ap.light_pole)


def test_locate_finds_the_lane_and_rejects_points_off_the_road(town):
    index = town.road_lanes()[5]
    lane = town.lane(index)
    found = town.locate(lane.position(10.0, 0.5), lane.heading_at(10.0))
    assert found is not None and found[0] == index and found[2] == pytest.approx(0.5)
    assert town.locate(town.buildings[0].footprint.mean(axis=0)) is None


def test_shortest_route_is_connected_and_commands_announce_turns(town):
    rng = np.random.default_rng(3)
    route = random_route(town, town.road_lanes()[0][:2], rng, 300.0)
    assert route_length(town, route) >= 300.0
    for a, b in zip(route[:-1], route[1:], strict=True):
        assert a[1] == b[0]
    # Before each junction on the route, the command names that junction's turn.
    for k in range(len(route) - 1):
        nxt = town.lane_info[(route[k + 1][0], route[k + 1][1], 0)]
        if town.lane_info[(route[k][0], route[k][1], 0)].kind == "road" and nxt.kind == "connector":
            length = town.lane((route[k][0], route[k][1], 0)).length
            assert command_at(town, route, k, length - 5.0) == nxt.command
            assert command_at(town, route, k, 0.0) == Command.FOLLOW


def test_route_to_unreachable_edge_is_an_error(town):
    with pytest.raises(ValueError):
        shortest_route(town, town.road_lanes()[0][:2], ("nowhere", "else"))


def test_same_seed_same_town_and_config_validation():
    a, b = generate_town(TownConfig(blocks_x=2, blocks_y=3), 7), generate_town(TownConfig(blocks_x=2, blocks_y=3), 7)
    assert np.array_equal(a.xs, b.xs) and len(a.buildings) == len(b.buildings)
    assert all(np.array_equal(x.footprint, y.footprint) for x, y in zip(a.buildings, b.buildings, strict=True))
    with pytest.raises(ValueError, match="at least one block"):
        TownConfig(blocks_x=0)
