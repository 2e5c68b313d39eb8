"""The world step's shortcuts (prefilters, batched integration, one-pass lane lookup) give exactly
what the plain computations give: each is checked against the plain one on many random cases."""

from __future__ import annotations

import copy
import math
import struct

import numpy as np
import pytest

import towndrive.sim.traffic as traffic
from towndrive.sim.ego import EgoVehicle
from towndrive.sim.geometry import circle_polygon_intersect, polygons_intersect, rect_corners, wrap_to_pi
from towndrive.sim.objects import ObjectSnapshot, SemanticClass, snapshot_of
from towndrive.sim.path_filter import MARGIN_M, clearly_nearest_lane, path_rows, points_within, zone_holds
from towndrive.sim.pedestrians import BODY_MARGIN_M, FRONT_MARGIN_M, STEP_AHEAD_M, cars_in_the_way
from towndrive.sim.routes import command_at
from towndrive.sim.traffic import Agents, TownVehicle, crosswalk_gap, path_gap, step_vehicles
from towndrive.sim.world import StaticObstacles, World, WorldConfig


def car_in_the_way(ped, vehicles: np.ndarray, speeds: np.ndarray) -> bool:
    """The one-pedestrian-at-a-time rule for moving cars that ``cars_in_the_way`` compiles."""
    if len(vehicles) == 0:
        return False
    d = vehicles - (ped.position + 1.2 * np.array([math.cos(ped.heading), math.sin(ped.heading)]))
    return bool(np.any((d[:, 0] ** 2 + d[:, 1] ** 2 < 2.8 ** 2) & (speeds > 0.5)))


@pytest.fixture(scope="module")
def world(town) -> World:
    w = World(town, WorldConfig(npc_count=24, pedestrian_count=40), 3)
    for _ in range(200):
        w.step(np.array([0.0, 0.3]))
    return w


def random_agents(lanes: list, origin: np.ndarray, rng: np.random.Generator, n: int) -> Agents:
    """Agents in all states: half scattered on and beside the given lanes (so that paths have someone
    on them, or just off them), half anywhere within 50 m of the origin."""
    on = [lanes[i].position(rng.uniform(-3, lanes[i].length + 3), rng.normal(0, 2.5))
          for i in rng.integers(len(lanes), size=n // 2)]
    pos = np.array(on + list(origin + rng.uniform(-50, 50, (n - n // 2, 2))))
    ped = rng.random(n) < 0.5
    return Agents(pos, rng.uniform(-math.pi, math.pi, n), np.where(rng.random(n) < 0.3, 0.0, rng.uniform(0, 9, n)),
                  np.where(ped, 0.3, rng.choice([2.25, 3.4], n)), ped, np.arange(n, dtype=np.int64),
                  ped & (rng.random(n) < 0.5))


def plain_candidates(positions, ids, skip_id, ox, oy, radius2, *_args) -> np.ndarray:
    """What path_gap selected before the prefilter: every agent near the origin."""
    d2 = np.sum((positions - np.array([ox, oy])) ** 2, axis=1)
    return np.nonzero((d2 < radius2) & (ids != skip_id))[0]


def test_path_and_crosswalk_gaps_match_the_plain_search(town, world, monkeypatch):
    rng = np.random.default_rng(0)
    cases = []
    for trial in range(300):
        npc = world.npcs[trial % len(world.npcs)]
        lookahead = float(rng.uniform(12.0, 45.0))
        indexed, s0 = npc.path_with_indices(lookahead)
        path = [(lane, offset) for lane, offset, _ in indexed]
        origin = npc.position + rng.normal(0, 1.0, 2)
        agents = random_agents([lane for lane, _ in path], origin, rng, 40)
        cases.append((path, [i for *_, i in indexed], s0, agents, origin, lookahead))
    fast = [(path_gap(p, s0, 2.25, a, -1, o, la), crosswalk_gap(town, p, ix, s0, 2.25, a, la))
            for p, ix, s0, a, o, la in cases]
    monkeypatch.setattr(traffic, "path_candidates", plain_candidates)
    monkeypatch.setattr(traffic, "zone_holds", lambda *_: -1)
    monkeypatch.setattr(traffic, "lanes_may_hold", lambda px, py, rows, lat, pad: np.ones(len(rows), bool))
    plain = [(path_gap(p, s0, 2.25, a, -1, o, la), crosswalk_gap(town, p, ix, s0, 2.25, a, la))
             for p, ix, s0, a, o, la in cases]
    assert fast == plain
    assert sum(g is not None for (g, _), _ in fast) > 200  # the cases do find leaders
    assert sum(z is not None for _, z in fast) > 30


def plain_locate(town, position, heading):
    """Town.locate as it was: every lane of the hash cell through highway-env's geometry."""
    best = None
    half = town.lane_width / 2
    for index in town.lanes_near(position):
        lane = town.lane(index)
        s, lat = lane.local_coordinates(position)
        if not (-0.5 <= s <= lane.length + 0.5) or abs(lat) > half + 0.05:
            continue
        cost = abs(lat)
        if heading is not None:
            cost += 4.0 * abs(wrap_to_pi(lane.heading_at(s) - heading))
        if best is None or cost < best[0]:
            best = (cost, index, float(s), float(lat))
    return None if best is None else best[1:]


def test_locate_both_matches_two_plain_lookups(town):
    rng = np.random.default_rng(1)
    lanes = [town.lane(k) for k in town.lane_info]
    found = 0
    for i in rng.integers(len(lanes), size=2000):
        lane = lanes[i]
        p = lane.position(rng.uniform(-2, lane.length + 2), rng.normal(0, 2.0))
        h = float(rng.uniform(-math.pi, math.pi))
        with_heading, nearest = town.locate_both(p, h)
        assert with_heading == plain_locate(town, p, h)
        assert nearest == plain_locate(town, p, None) == town.locate(p)
        found += with_heading is not None
    assert found > 1000


def test_static_hits_match_a_test_against_every_shape(town):
    static = StaticObstacles(town)
    rng = np.random.default_rng(2)
    anchors = [b.footprint.mean(axis=0) for b in town.buildings] + list(town.poles) + [t.position for t in town.trees]
    hits = 0
    for k in rng.integers(len(anchors), size=1500):
        poly = rect_corners(anchors[k] + rng.normal(0, 4.0, 2), float(rng.uniform(-math.pi, math.pi)), 4.6, 1.9)
        plain = (any(polygons_intersect(poly, b.footprint) for b in town.buildings)
                 or any(circle_polygon_intersect(p, town.POLE_RADIUS_M, poly) for p in town.poles)
                 or any(circle_polygon_intersect(t.position, town.TRUNK_RADIUS_M, poly) for t in town.trees))
        assert static.hits(poly) == plain
        hits += plain
    assert 100 < hits < 1400


def test_batched_integration_matches_one_by_one(world):
    rng = np.random.default_rng(3)
    one = copy.deepcopy([world.ego] + world.npcs)
    batch = copy.deepcopy([world.ego] + world.npcs)
    assert type(one[0]) is EgoVehicle

    def bits(v) -> tuple:
        timer = getattr(v, "timer", None)
        return (v.position.tobytes(), np.float64(v.heading).tobytes(), struct.pack("d", v.speed), timer,
                type(v.heading), type(v.speed))

    for step in range(60):
        for a, b in zip(one, batch, strict=True):
            action = {"steering": float(rng.uniform(-1, 1)), "acceleration": float(rng.uniform(-6, 3))}
            if step % 7 == 0:  # now and then: brake to a standstill (the clamps), or run far too fast
                action["acceleration"] = -1e3 if step % 14 else 1e3
            a.action, b.action = dict(action), dict(action)
            a.crashed = b.crashed = bool(rng.random() < 0.05)
        for v in one:
            v.step(0.05)
        step_vehicles(batch, 0.05)
        for a, b in zip(one, batch, strict=True):
            assert bits(a) == bits(b)


def standing_car_in_the_way(ped, vehicles: np.ndarray, speeds: np.ndarray, headings: np.ndarray,
                            sizes: np.ndarray) -> int:
    """The one-pedestrian-at-a-time NumPy rule for standing cars that ``cars_in_the_way`` compiles (-1: none)."""
    if len(vehicles) == 0:
        return -1
    ahead = ped.position + STEP_AHEAD_M * np.array([math.cos(ped.heading), math.sin(ped.heading)])
    d = ahead - vehicles
    near = np.nonzero((d[:, 0] ** 2 + d[:, 1] ** 2 < 64.0) & (speeds <= 0.5))[0]
    for k in near:
        c, s = math.cos(headings[k]), math.sin(headings[k])
        along, across = d[k, 0] * c + d[k, 1] * s, -d[k, 0] * s + d[k, 1] * c
        front = FRONT_MARGIN_M if along > 0 else BODY_MARGIN_M
        if -sizes[k, 0] - BODY_MARGIN_M < along < sizes[k, 0] + front and abs(across) < sizes[k, 1] + BODY_MARGIN_M:
            return int(k)
    return -1


def test_pedestrians_look_out_for_cars_as_one_by_one(world):
    rng = np.random.default_rng(4)
    moving_hits = standing_hits = 0
    for trial in range(400):
        n = 12 if trial % 10 else 0  # now and then no vehicles at all
        vehicles = rng.uniform(-150, 150, (n, 2))
        speeds = np.where(rng.random(n) < 0.5, rng.uniform(0, 0.5, n), rng.uniform(0, 2, n))
        headings = rng.uniform(-4, 4, n)
        sizes = np.where(rng.random((n, 1)) < 0.3, [3.4, 1.15], [2.25, 0.95])
        peds = copy.deepcopy(world.crowd.peds)
        for p in peds:
            p.position = vehicles[int(rng.integers(n))] + rng.normal(0, 2.5, 2) if n else rng.normal(0, 2.5, 2)
            p.heading = float(rng.uniform(-math.pi, math.pi)) if rng.random() < 0.8 else 0.0
        where = np.array([(p.position[0], p.position[1], p.heading) for p in peds], dtype=float)
        moving, standing = cars_in_the_way(where, vehicles, speeds, headings, sizes)
        assert moving.tolist() == [car_in_the_way(p, vehicles, speeds) for p in peds]
        assert standing.tolist() == [standing_car_in_the_way(p, vehicles, speeds, headings, sizes) for p in peds]
        moving_hits += int(moving.sum())
        standing_hits += int((standing >= 0).sum())
    assert moving_hits > 500 and standing_hits > 500  # both rules do fire


def test_npc_lane_memo_is_only_used_within_a_decision(world):
    npc: TownVehicle = world.npcs[0]
    lane = world.town.lane(npc.target_lane_index)
    assert npc._coords is None
    before = npc._lane_coords(lane)
    npc.position = npc.position + np.array([1.0, 0.0])
    assert npc._lane_coords(lane) == lane.local_coordinates(npc.position) != before


def test_rect_corners_and_snapshots_are_what_the_plain_constructions_give():
    rng = np.random.default_rng(5)
    for _ in range(2000):
        centre, heading = rng.uniform(-300, 300, 2), float(rng.uniform(-7, 7))
        length, width = float(rng.uniform(0.3, 8)), float(rng.uniform(0.3, 3))
        c, s = math.cos(heading), math.sin(heading)
        fwd, side = np.array([c, s]) * (length / 2), np.array([-s, c]) * (width / 2)
        plain = np.array([centre + fwd - side, centre + fwd + side, centre - fwd + side, centre - fwd - side])
        assert rect_corners(centre, heading, length, width).tobytes() == plain.tobytes()
    args = (7, SemanticClass.TRUCK, 1.5, -2.25, 0.125, 6.8, 2.3, 2.8, (0.1, 0.2, 0.3))
    fast, plain_snap = snapshot_of(*args), ObjectSnapshot(*args)
    assert type(fast) is ObjectSnapshot and fast == plain_snap and hash(fast) == hash(plain_snap)
    assert repr(fast) == repr(plain_snap) and vars(fast) == vars(plain_snap)


def test_clearly_nearest_lane_is_the_exact_nearest(town):
    """Where the cheap bound names a lane, it is the one the exact lateral offsets pick (the first of equals)."""
    rng = np.random.default_rng(6)
    edges = [lanes for tos in town.network.graph.values() for lanes in tos.values()]
    named = 0
    for _ in range(6000):
        lanes = edges[int(rng.integers(len(edges)))]
        lane = lanes[int(rng.integers(len(lanes)))]
        point = lane.position(float(rng.uniform(-5, lane.length + 5)), float(rng.normal(0, 2.5)))
        lats = [abs(other.local_coordinates(point)[1]) for other in lanes]
        k = clearly_nearest_lane(float(point[0]), float(point[1]), path_rows(lanes))
        if k >= 0:
            assert k == lats.index(min(lats))
            named += 1
        else:
            assert abs(lats[0] - lats[1]) < 2 * MARGIN_M + 1e-6
    assert named > 4000


def test_points_within_and_zone_holds_match_numpy():
    rng = np.random.default_rng(8)
    sure = unsure = 0
    for _ in range(3000):
        n = int(rng.integers(0, 12))
        points = rng.uniform(-20, 20, (n, 2)) + rng.uniform(-500, 500, 2)
        centre = points[0] + rng.normal(0, 4, 2) if n else rng.uniform(-500, 500, 2)
        radius = float(rng.uniform(0.5, 8))
        d = points - centre
        assert points_within(points, float(centre[0]), float(centre[1]), (radius + 0.01) ** 2).tolist() == (
            d[:, 0] ** 2 + d[:, 1] ** 2 < (radius + 0.01) ** 2).tolist()
        angle = float(rng.uniform(-math.pi, math.pi))
        u, across = np.array([math.cos(angle), math.sin(angle)]), np.array([-math.sin(angle), math.cos(angle)])
        half_u, half_v = float(rng.uniform(1, 4)), float(rng.uniform(2, 8))
        exact = bool(((np.abs(d @ u) <= half_u) & (np.abs(d @ across) <= half_v)).any())
        held = zone_holds(points, float(centre[0]), float(centre[1]), float(u[0]), float(u[1]), float(across[0]),
                          float(across[1]), half_u, half_v)
        if held < 0:
            unsure += 1
        else:
            assert bool(held) == exact
            sure += 1
    assert sure > 2000 and unsure > 50


def test_kept_command_follows_the_route_position(town):
    w = World(town, WorldConfig(npc_count=4, pedestrian_count=4), 11)
    for _ in range(400):
        w.step(np.array([0.0, 0.5]))
        assert w.command() == w.command() == command_at(town, w.route, w.route_index, w.route_s)
    for index in range(len(w.route)):  # moved without a step (as the safety driver does)
        for s in (0.0, 5.0, 60.0):
            w.route_index, w.route_s = index, s
            assert w.command() == command_at(town, w.route, index, s)
