"""Town styles: the classic town unchanged, the other styles' streets, junction controls, signs,
parked cars and turn lanes well formed, every town reproducible from its (style, seed)."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from towndrive.sim.fillet_lane import FilletLane
from towndrive.sim.polyline_lane import PolylineLane
from towndrive.sim.routes import shortest_route
from towndrive.sim.splits import TOWN_SPLITS, split_of, split_towns
from towndrive.sim.town import (
    OPPOSITE,
    PARKING_CLEAR_M,
    Arm,
    Command,
    Control,
    SignKind,
    Town,
    TownConfig,
    generate_town,
)
from towndrive.sim.town_style import STYLES, style_named

STYLED = ("downtown", "suburb")
SEEDS = (4000, 4001, 4002)  # validation towns: what these tests look at is no test split


def digest(town: Town) -> str:
    """A hash of the town's lanes, controls, signs, parked cars and scenery."""
    m = hashlib.sha256()
    for frm, tos in sorted(town.network.graph.items()):
        for to, lanes in sorted(tos.items()):
            for k, lane in enumerate(lanes):
                m.update(f"{frm}{to}{k}{type(lane).__name__}{town.lane_info[(frm, to, k)]}".encode())
                for s in np.linspace(0, lane.length, 5):
                    m.update(np.asarray(lane.position(s, 0.3), float).tobytes())
    for e in town.entries:
        m.update(repr((e.index, e.node, int(e.arm), e.edge, int(e.control), e.approach)).encode())
    for ap in town.approaches:
        m.update(np.concatenate([ap.light_pole, ap.light_head, [ap.head_height_m]]).tobytes() + ap.mount.encode())
    for sign in town.signs:
        m.update(repr((int(sign.kind), sign.edge, sign.value_kmh, sign.facing)).encode() + sign.position.tobytes())
    for car in town.parked_cars:
        m.update(car.position.tobytes() + repr((car.heading, car.length_m, car.color)).encode())
    for b in town.buildings:
        m.update(b.footprint.tobytes() + repr((b.height_m, b.color)).encode())
    for t in town.trees:
        m.update(t.position.tobytes())
    for kind, quads in sorted(town.markings.items()):
        for q in quads:
            m.update(kind.encode() + q.tobytes())
    return m.hexdigest()


@pytest.fixture(scope="module")
def towns() -> dict[tuple[str, int], Town]:
    return {(style, seed): generate_town(TownConfig.of_style(style), seed) for style in STYLED for seed in SEEDS}


def test_classic_is_the_default_and_stays_the_original_design(town):
    assert TownConfig().style == "classic" and TownConfig.of_style("classic") == TownConfig()
    assert town.lane_width == 3.5 and not town.signs and not town.parked_cars and not town.speed_limits_kmh
    assert all(town.lane_count(edge) == 2 for edge in {k[:2] for k in town.lane_info})
    assert {e.control for e in town.entries} == {Control.SIGNAL}
    assert len(town.entries) == len(town.approaches) and {ap.mount for ap in town.approaches} == {"mast_arm"}
    assert not town.exit_lanes and not town.markings["yield_line"]
    for ap in town.approaches:  # the stop bar's setback: 12 m from the junction centre, plus the bar
        assert float(np.linalg.norm(ap.stop_line_center - town.node_position(ap.node))) == pytest.approx(
            math.hypot(12.5, 3.5))


def test_the_same_style_and_seed_make_the_same_town_and_others_differ():
    a = generate_town(TownConfig.of_style("suburb"), 4001)
    b = generate_town(TownConfig.of_style("suburb"), 4001)
    assert digest(a) == digest(b)
    assert digest(a) != digest(generate_town(TownConfig.of_style("suburb"), 4002))
    assert digest(a) != digest(generate_town(TownConfig.of_style("downtown"), 4001))


def test_styles_differ_in_streets_controls_and_scenery(towns):
    def share(style: str, test) -> float:
        items = [x for (s, _), t in towns.items() if s == style for x in test(t)]
        return sum(items) / len(items)

    single = {s: share(s, lambda t: [t.lane_count(k[:2]) == 1 for k, i in t.lane_info.items() if i.kind == "road"])
              for s in STYLED}
    assert single["suburb"] > single["downtown"] > 0.0  # suburbs are mostly residential streets
    signals = {s: share(s, lambda t: [e.control == Control.SIGNAL for e in t.entries]) for s in STYLED}
    assert signals["downtown"] > signals["suburb"]
    height = {s: share(s, lambda t: [b.height_m for b in t.buildings]) for s in STYLED}
    assert height["downtown"] > 2 * height["suburb"]
    assert all(t.signs for t in towns.values())
    assert all(t.parked_cars for (style, _), t in towns.items() if style == "suburb")
    widths = {t.lane_width for t in towns.values()}
    assert len(widths) > 1 and all(3.0 <= w <= 3.75 for w in widths)


def test_every_junction_has_one_coherent_control(towns):
    for town in towns.values():
        by_node: dict[tuple[int, int], list] = {}
        for e in town.entries:
            by_node.setdefault(e.node, []).append(e)
        for node, entries in by_node.items():
            kinds = {e.control for e in entries}
            if Control.SIGNAL in kinds or Control.ALL_WAY_STOP in kinds:
                assert len(kinds) == 1, (node, kinds)
                continue
            # priority junction: one street has priority (its arms face each other), the other stops or yields
            major = [e.arm for e in entries if e.control == Control.PRIORITY]
            minor = {e.control for e in entries if e.control != Control.PRIORITY}
            assert major and len(minor) == 1 and minor <= {Control.STOP, Control.YIELD}, (node, kinds)
            assert len(major) == 1 or OPPOSITE[major[0]] == major[1]
        for e in town.entries:
            assert (e.approach >= 0) == (e.control == Control.SIGNAL)
            assert town.entry_for_edge(e.edge) is e


def test_stop_and_yield_entries_have_their_sign_beside_the_road_facing_the_traffic(towns):
    want = {Control.STOP: SignKind.STOP, Control.ALL_WAY_STOP: SignKind.STOP, Control.YIELD: SignKind.YIELD}
    for town in towns.values():
        signs = {(s.edge, s.kind): s for s in town.signs}
        for e in town.entries:
            if e.control in want:
                sign = signs[(e.edge, want[e.control])]
                assert sign.facing == pytest.approx(e.travel_heading, abs=0.02)  # (a bowed street turns a little)
                # before the end of its lanes (where the junction starts), on the traffic's right, off the asphalt
                outer = town.lane((*e.edge, e.lane_count - 1))
                s, lat = outer.local_coordinates(sign.position)
                assert s < outer.length and lat > town.lane_width / 2
                assert not town.on_road(sign.position, margin_m=0.3)
        for s in town.signs:
            if s.kind == SignKind.SPEED_LIMIT:
                assert s.value_kmh in (30, 50) and town.speed_limit_kmh(s.edge) == s.value_kmh


def test_every_lane_runs_into_the_lane_its_successor_names(towns):
    for town in towns.values():
        graph = town.network.graph
        for frm, tos in graph.items():
            for to, lanes in tos.items():
                for k, lane in enumerate(lanes):
                    for nxt in graph.get(to, {}):
                        follow = town.lane(town.next_lane((frm, to, k), (to, nxt)))
                        gap = np.linalg.norm(lane.position(lane.length, 0) - follow.position(0, 0))
                        turn = math.remainder(lane.heading_at(lane.length) - follow.heading_at(0), 2 * math.pi)
                        assert gap < 1e-6 and abs(turn) < 1e-6, (frm, to, k, nxt)


def test_left_turns_keep_to_the_inner_lanes_and_right_turns_to_the_outer_ones(towns):
    assert any(town.exit_lanes for town in towns.values()), "the styled towns join one- and two-lane streets"
    for town in towns.values():
        for (frm, to, k), info in town.lane_info.items():
            if info.kind != "connector" or info.command not in (Command.LEFT, Command.RIGHT):
                continue
            n_in = town.lane_count((frm, to))
            out_edge = (to, next(iter(town.network.graph[to])))
            n_out = town.lane_count(out_edge)
            if info.command == Command.LEFT and k == 0:
                assert town.next_lane((frm, to, k), out_edge)[2] == 0
            if info.command == Command.RIGHT and k == n_in - 1:
                assert town.next_lane((frm, to, k), out_edge)[2] == n_out - 1


def test_turns_keep_clear_of_poles_sign_posts_and_waiting_pedestrians(towns):
    """A turn follows the kerb round the corner: the centre line stays a car's half width plus a margin from
    every pole and post, and half a lane from the kerbside places where pedestrians wait to cross."""
    for town in towns.values():
        posts = np.array([*town.poles, *[s.position for s in town.signs]])
        waits = np.array([p for cw in town.crosswalks for p in (cw.start, cw.end)])
        for index, info in town.lane_info.items():
            if info.kind != "connector":
                continue
            lane = town.lane(index)
            centre = np.array([lane.position(s, 0.0) for s in np.linspace(0, lane.length, 40)])
            to_posts = np.linalg.norm(centre[:, None] - posts[None], axis=2).min()
            to_waits = np.linalg.norm(centre[:, None] - waits[None], axis=2).min()
            assert to_posts > 0.95 + Town.POLE_RADIUS_M + 0.3, (town.config.style, town.seed, index, to_posts)
            assert to_waits > town.lane_width / 2 + 0.3, (town.config.style, town.seed, index, to_waits)


def test_every_road_reaches_every_other(towns):
    for town in towns.values():
        roads = sorted({k[:2] for k, i in town.lane_info.items() if i.kind == "road"})
        for goal in roads[1::7]:
            route = shortest_route(town, roads[0], goal)
            assert route[0] == roads[0] and route[-1] == goal


def test_parked_cars_stand_in_the_parking_strip_clear_of_lanes_and_junctions(towns):
    for town in towns.values():
        for car in town.parked_cars:
            loc = town.locate(car.position)
            assert loc is None, "a parked car stands off every lane"
            ahead = np.array([math.cos(car.heading), math.sin(car.heading)])
            for e in town.entries:  # clear of the junction's mouth
                assert np.linalg.norm(car.position - e.line_center) > PARKING_CLEAR_M - 1.0 or \
                    abs((car.position - e.line_center) @ ahead) > PARKING_CLEAR_M - 1.0


def test_fillet_lane_joins_its_poses_smoothly_and_maps_points_back():
    lane = FilletLane(np.array([0.0, 0.0]), 0.0, np.array([14.0, 9.0]), math.pi / 2, 3.25)
    assert np.allclose(lane.position(0, 0), [0, 0]) and np.allclose(lane.position(lane.length, 0), [14, 9])
    assert lane.heading_at(0) == pytest.approx(0) and lane.heading_at(lane.length) == pytest.approx(math.pi / 2)
    ss = np.linspace(0, lane.length, 400)
    headings = np.unwrap([lane.heading_at(s) for s in ss])
    assert np.all(np.diff(headings) >= -1e-9) and np.max(np.diff(headings)) < 0.02  # turns one way, no jumps
    for s in np.linspace(0.1, lane.length - 0.1, 37):
        for lat in (-1.2, 0.0, 1.2):
            back = lane.local_coordinates(lane.position(s, lat))
            assert back == pytest.approx((s, lat), abs=1e-6)
    with pytest.raises(ValueError, match="ahead"):
        FilletLane(np.array([0.0, 0.0]), 0.0, np.array([-5.0, 9.0]), math.pi / 2, 3.0)


def test_bent_towns_meet_at_other_angles_and_keep_their_lane_widths(towns):
    bent = [t for t in towns.values() if t.warp is not None and (abs(t.warp.skew_deg) > 3 or not t.warp.affine)]
    assert any(t.warp.affine for t in bent) and any(not t.warp.affine for t in bent)
    for town in bent:
        rows = {e.node: math.degrees(e.travel_heading) for e in town.entries if e.arm in (Arm.E, Arm.W)}
        cols = {e.node: math.degrees(e.travel_heading) for e in town.entries if e.arm in (Arm.N, Arm.S)}
        corners = [abs(abs(math.remainder(rows[n] - cols[n], 180)) - 90) for n in rows if n in cols]
        if town.warp.affine:  # every junction leans by the skew
            assert max(corners) == pytest.approx(abs(town.warp.skew_deg), abs=0.6)
        else:  # the bows turn each junction differently
            assert np.ptp([c for c in corners if c > 1.0]) > 2.0
        for (frm, to, k), info in town.lane_info.items():
            if info.kind == "road" and k == 1:  # the two lanes of an arterial lie about one lane width apart
                a, b = town.lane((frm, to, 0)), town.lane((frm, to, 1))
                s, lat = a.local_coordinates(b.position(b.length / 2, 0.0))
                assert lat == pytest.approx(town.lane_width, rel=0.03 if not town.warp.affine else 1e-6)
        for ap in town.approaches:  # the stop line still lies across its lanes
            lane = town.lane((*ap.edge, 0))
            assert abs(lane.local_coordinates(ap.stop_line_center)[0] - lane.length) < 1.0


def test_polyline_lane_follows_its_curve_with_exact_end_headings():
    arc = FilletLane(np.array([0.0, 0.0]), 0.0, np.array([20.0, 20.0]), math.pi / 2, 3.0)
    ss = np.linspace(0, arc.length, 34)
    lane = PolylineLane(np.array([arc.position(s, 0) for s in ss]), np.array([arc.heading_at(s) for s in ss]), 3.0)
    assert lane.heading_at(0) == pytest.approx(0) and lane.heading_at(lane.length) == pytest.approx(math.pi / 2)
    headings = [lane.heading_at(s) for s in np.linspace(0, lane.length, 500)]
    assert np.max(np.abs(np.diff(headings))) < 0.01  # no jumps between samples
    for s in np.linspace(1, arc.length - 1, 23):
        for lat in (-1.5, 0.0, 1.5):
            p = arc.position(s, lat)
            s2, lat2 = lane.local_coordinates(p)
            assert lat2 == pytest.approx(lat, abs=0.05) and s2 == pytest.approx(s, abs=0.05)
            assert np.linalg.norm(lane.position(s2, lat2) - p) < 0.05


def test_style_names_and_splits_are_checked_in_one_sentence():
    assert set(STYLES) == {"classic", "downtown", "suburb"}
    with pytest.raises(ValueError, match="the styles are classic, downtown, suburb"):
        style_named("uptown")
    with pytest.raises(ValueError, match="styles"):
        TownConfig(style="uptown")
    ranges = list(TOWN_SPLITS.values())
    assert all(a.stop <= b.start for a, b in zip(ranges, ranges[1:], strict=False))
    assert split_of(101) == "train" and split_of(4500) == "validation" and split_of(5999) == "test"
    assert list(split_towns("test", 3)) == [5000, 5001, 5002]
    assert list(split_towns("test", 2, first=5005)) == [5005, 5006]
    with pytest.raises(ValueError, match="holds towns 5000-5999; asked for 1001 from 5000"):
        split_towns("test", 1001)
    with pytest.raises(ValueError, match="asked for 2 from 4999"):
        split_towns("test", 2, first=4999)
    with pytest.raises(ValueError, match="asked for 2 from 5999"):
        split_towns("test", 2, first=5999)


def test_reset_option_town_style_builds_that_style(tmp_path):
    from towndrive.envs.drive_env import DriveConfig, DriveEnv

    env = DriveEnv(DriveConfig(render_camera=False))
    try:
        env.reset(seed=1, options={"town_seed": 4003, "town_style": "suburb"})
        assert env.world.town.config.style == "suburb" and env.world.town.seed == 4003
        with pytest.raises(ValueError, match="unknown town style"):
            env.reset(seed=1, options={"town_style": "village"})
        assert env.world.town.config.style == "suburb"  # the bad option changed nothing
    finally:
        env.close()


def _styled_rollout(style: str, seed: int, steps: int = 25) -> tuple[list[np.ndarray], list[str]]:
    from towndrive.envs.drive_env import DriveConfig, DriveEnv
    from towndrive.sim.render import CameraConfig
    from towndrive.sim.world import WorldConfig

    config = DriveConfig(camera=CameraConfig(width=200, height=66), observe_segmentation=True, town_seed=4004,
                         world=WorldConfig(town=TownConfig.of_style(style)))
    env = DriveEnv(config)
    try:
        obs, info = env.reset(seed=seed)
        rng = np.random.default_rng(7)
        frames, infos = [obs["image"].copy(), obs["segmentation"].copy()], [repr(info)]
        for _ in range(steps):
            obs, _, term, trunc, info = env.step(rng.uniform(-0.2, 1.0, 2).astype(np.float32))
            frames += [obs["image"].copy(), obs["segmentation"].copy()]
            infos.append(repr(info))
            if term or trunc:
                break
    finally:
        env.close()
    return frames, infos


@pytest.mark.parametrize("style", STYLED)
def test_every_style_passes_the_env_checker_and_repeats_frames_and_info(style):
    from gymnasium.utils.env_checker import check_env

    from towndrive.envs.drive_env import DriveConfig, DriveEnv
    from towndrive.sim.render import CameraConfig
    from towndrive.sim.world import WorldConfig

    env = DriveEnv(DriveConfig(camera=CameraConfig(width=200, height=66), town_seed=4004,
                               world=WorldConfig(town=TownConfig.of_style(style))))
    check_env(env, skip_render_check=True)
    env.close()
    a, a_info = _styled_rollout(style, 3)
    b, b_info = _styled_rollout(style, 3)
    assert len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert a_info == b_info
    c, _ = _styled_rollout(style, 4)
    assert not all(np.array_equal(x, y) for x, y in zip(a, c, strict=False))


def test_curve_speed_limit_slows_for_fillets_and_sampled_turns():
    from towndrive.sim.traffic import CURVE_LATERAL_ACCEL_MPS2, curve_speed_limit

    fillet = FilletLane(np.array([0.0, 0.0]), 0.0, np.array([20.0, 20.0]), math.pi / 2, 3.0, radius_m=6.0)
    radius, start = fillet.tightest_turn()
    assert radius == pytest.approx(6.0) and start == pytest.approx(14.0)
    at_turn = curve_speed_limit([(fillet, 0.0)], start)
    assert at_turn == pytest.approx(math.sqrt(CURVE_LATERAL_ACCEL_MPS2 * 6.0))
    assert at_turn < curve_speed_limit([(fillet, 0.0)], 0.0) < math.inf  # braking room before the arc
    ss = np.linspace(0, fillet.length, 40)
    sampled = PolylineLane(np.array([fillet.position(s, 0) for s in ss]), np.array([fillet.heading_at(s) for s in ss]),
                           3.0)
    assert sampled.tightest_turn()[0] == pytest.approx(6.0, rel=0.1)


def test_the_safety_drivers_lane_band_of_a_one_lane_street_is_its_lane():
    from towndrive.sim.world import World, WorldConfig

    town = generate_town(TownConfig.of_style("suburb"), 4001)
    edge = next(k[:2] for k, i in town.lane_info.items() if i.kind == "road" and town.lane_count(k[:2]) == 1
                and town.lane(k).length > 40)
    world = World(town, WorldConfig(town=town.config, npc_count=0, pedestrian_count=0), seed=1, start=(*edge, 0))
    lane = town.lane((*edge, 0))
    s = lane.local_coordinates(world.ego.position)[0]
    world.ego.position = lane.position(s, 1.4)
    world.step(np.zeros(2))
    assert world.lane_band_offset_m() == pytest.approx(1.4, abs=0.1)


def test_no_lane_turns_tighter_than_the_car_can(towns):
    from towndrive.sim.spec import VEHICLE
    from towndrive.sim.traffic import tightest_turn

    for town in towns.values():
        for index in town.lane_info:
            radius, _ = tightest_turn(town.lane(index))
            assert radius > VEHICLE.min_turn_radius_m, (town.config.style, town.seed, index, radius)


def test_the_map_follows_the_town_without_a_camera():
    """The map view (the clips' ground truth) is drawn from the episode's own town when towns change between
    episodes, also when no camera is rendered: it kept the first town's map, whose lights a town with fewer
    signals does not have (an IndexError that failed whole evaluations)."""
    from towndrive.envs.drive_env import DriveConfig, DriveEnv
    from towndrive.sim.world import WorldConfig

    env = DriveEnv(DriveConfig(render_camera=False, world=WorldConfig(town=TownConfig.of_style("suburb"))))
    try:
        counts = []
        for town_seed in (4000, 4001, 4002, 4003):
            env.reset(seed=1, options={"town_seed": town_seed})
            env.map_view(64)
            counts.append(len(env.world.town.approaches))
            assert env._topdown.town is env.world.town
        assert len(set(counts)) > 1  # the towns differ in their signals
    finally:
        env.close()
