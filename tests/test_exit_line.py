"""The road turned into, read in a junction turn (``agent.perception.exit_line``): on rendered frames of cars part
way through right and left turns, in daylight and in the dark, the centre line found lies on the town's and runs its
way; nothing is reported where no such line is in view."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from towndrive.agent.decision.blind_spot import SideMount
from towndrive.agent.perception.exit_line import ExitLineFinder
from towndrive.agent.perception.lanes import BirdsEye
from towndrive.envs.drive_env import DriveConfig, DriveEnv
from towndrive.sim.spec import CORNERS, CameraConfig
from towndrive.sim.town import Command, TownConfig
from towndrive.sim.world import World, WorldConfig, cached_town

POSITION_TOLERANCE_M = 0.3  # across the line, from the middle of its paint
DIRECTION_TOLERANCE_DEG = 2.0


def _in_turn(style: str, town_seed: int, entry_index: int, command: Command, turned_deg: float,
             weather: str) -> tuple[np.ndarray, DriveEnv, tuple[np.ndarray, np.ndarray]]:
    """The camera frame of a car on a junction turn's connector where it has turned ``turned_deg``, and the road
    turned into's centre line (two points in the camera's ground frame: x right, z ahead)."""
    cfg = DriveConfig(world=WorldConfig(town=TownConfig.of_style(style)))
    town = cached_town(cfg.world.town, town_seed)
    entry = town.entries[entry_index]
    k = 0 if command == Command.LEFT else entry.lane_count - 1
    connector = next(idx for idx, info in town.lane_info.items()
                     if idx[0] == entry.edge[1] and idx[2] == k and info.kind == "connector" and info.command == command)
    lane = town.lane(connector)
    s = next(s for s in np.arange(0.0, lane.length, 0.1)
             if abs(math.remainder(lane.heading_at(s) - lane.heading_at(0.0), 2 * math.pi)) >= math.radians(turned_deg))
    env = DriveEnv(cfg)
    world = World(town, cfg.world, seed=0, start=connector, start_s=float(s), spawn_traffic=False)
    obs, _ = env.reset(seed=0, options={"world": world, "town_seed": town_seed, "weather": weather})
    ego, cam = world.ego, cfg.camera
    at = ego.position + cam.mount_forward_m * np.array([math.cos(ego.heading), math.sin(ego.heading)])
    exit_lane = town.lane((connector[1], next(iter(town.network.graph[connector[1]])), 0))

    def seen(s_m: float) -> np.ndarray:
        d = exit_lane.position(s_m, -exit_lane.width_at(s_m) / 2) - at  # lane 0's left edge: the centre line
        return np.array([-d[0] * math.sin(ego.heading) + d[1] * math.cos(ego.heading),
                         d[0] * math.cos(ego.heading) + d[1] * math.sin(ego.heading)])

    return obs["image"], env, (seen(0.0), seen(20.0))


def _off_line_m(point: tuple[float, float], a: np.ndarray, b: np.ndarray) -> float:
    """How far a point lies across the line through ``a`` and ``b`` (the camera's ground frame)."""
    u = (b - a) / np.linalg.norm(b - a)
    p = np.asarray(point) - a
    return abs(float(p[0] * u[1] - p[1] * u[0]))


@pytest.mark.parametrize("style, town_seed, entry_index, command, turned_deg, weather", [
    ("suburb", 4002, 0, Command.RIGHT, 40.0, "noon"),
    ("suburb", 4000, 3, Command.RIGHT, 55.0, "night"),
    ("downtown", 4001, 2, Command.LEFT, 50.0, "noon"),  # a left turn's road comes into view later
    ("downtown", 4000, 5, Command.LEFT, 60.0, "dusk"),
])
def test_the_centre_line_of_the_road_turned_into(style: str, town_seed: int, entry_index: int, command: Command,
                                                   turned_deg: float, weather: str) -> None:
    rgb, env, (a, b) = _in_turn(style, town_seed, entry_index, command, turned_deg, weather)
    finder = ExitLineFinder(env.config.camera)
    env.close()
    runs = math.atan2(b[0] - a[0], b[1] - a[1])
    line = finder.find(rgb, runs + math.radians(8.0))  # the expectation need not be exact
    assert line is not None
    assert _off_line_m(line.point, a, b) <= POSITION_TOLERANCE_M
    assert abs(math.degrees(math.remainder(line.direction_rad - runs, 2 * math.pi))) <= DIRECTION_TOLERANCE_DEG
    assert line.length_m >= finder.config.min_length_m


@pytest.mark.parametrize("turned_deg", [30.0, 40.0])
def test_at_dusk_a_zebra_lit_orange_is_not_taken_for_the_centre_line(turned_deg: float) -> None:
    """Early in a left turn at dusk the zebras across the junction, lit orange, line up into a band denser than the
    centre line, 12-20 m from it; paint as dense beside the band as on it makes it a patch: nothing, or the line."""
    rgb, env, (a, b) = _in_turn("suburb", 4000, 5, Command.LEFT, turned_deg, "dusk")
    finder = ExitLineFinder(env.config.camera)
    env.close()
    runs = math.atan2(b[0] - a[0], b[1] - a[1])
    line = finder.find(rgb, runs + math.radians(8.0))
    if line is not None:
        assert _off_line_m(line.point, a, b) <= POSITION_TOLERANCE_M


def test_nothing_where_no_cross_street_is_in_view() -> None:
    """On a straight street the only yellow line runs ahead: a cross street's is looked for across, and not found."""
    cfg = DriveConfig(world=WorldConfig(town=TownConfig.of_style("suburb")))
    town = cached_town(cfg.world.town, 4000)
    entry = town.entries[0]
    env = DriveEnv(cfg)
    world = World(town, cfg.world, seed=0, start=(*entry.edge, 0), start_s=town.lane((*entry.edge, 0)).length - 60.0,
                  spawn_traffic=False)
    obs, _ = env.reset(seed=0, options={"world": world, "town_seed": 4000})
    finder = ExitLineFinder(env.config.camera)
    env.close()
    assert finder.find(obs["image"], math.radians(90.0)) is None
    assert finder.find(obs["image"], math.radians(-90.0)) is None
    assert finder.find(np.zeros_like(obs["image"]), 0.0) is None


@pytest.mark.parametrize("entry_index, weather", [(1, "dusk"), (4, "night")])
def test_going_straight_the_far_sides_centre_line_in_its_corridor(entry_index: int, weather: str) -> None:
    """Going straight through a winding street's junction, the far side's centre line is found where the approach's,
    carried on, says within 2 m; without that corridor, at dusk a kerb lit orange 7 m aside outvotes it."""
    cfg = DriveConfig(world=WorldConfig(town=TownConfig.of_style("suburb")))
    town = cached_town(cfg.world.town, 4000)
    entry = town.entries[entry_index]
    connector = next(idx for idx, info in town.lane_info.items() if idx[0] == entry.edge[1] and idx[2] == 0
                     and info.kind == "connector" and info.command == Command.STRAIGHT)
    lane = town.lane(connector)
    env = DriveEnv(cfg)
    world = World(town, cfg.world, seed=0, start=connector, start_s=0.6 * lane.length, spawn_traffic=False)
    obs, _ = env.reset(seed=0, options={"world": world, "town_seed": 4000, "weather": weather})
    env.close()
    ego = world.ego
    at = ego.position + cfg.camera.mount_forward_m * np.array([math.cos(ego.heading), math.sin(ego.heading)])
    far = town.lane((connector[1], next(iter(town.network.graph[connector[1]])), 0))

    def seen(s_m: float) -> np.ndarray:
        d = far.position(s_m, -far.width_at(s_m) / 2) - at
        return np.array([-d[0] * math.sin(ego.heading) + d[1] * math.cos(ego.heading),
                         d[0] * math.cos(ego.heading) + d[1] * math.sin(ego.heading)])

    a, b = seen(0.0), seen(20.0)
    runs = math.atan2(b[0] - a[0], b[1] - a[1])
    finder = ExitLineFinder(cfg.camera)
    # the approach's centre line carried on lies within a metre of the far side's here (the street winds)
    line = finder.find(obs["image"], 0.0, (float(a[0]) + 0.6, float(a[1]), 2.0))
    assert line is not None
    assert _off_line_m(line.point, a, b) <= POSITION_TOLERANCE_M
    assert abs(math.degrees(math.remainder(line.direction_rad - runs, 2 * math.pi))) <= DIRECTION_TOLERANCE_DEG
    if weather == "dusk":
        kerb = finder.find(obs["image"], 0.0)
        assert kerb is not None and _off_line_m(kerb.point, a, b) > 2.0


@pytest.mark.parametrize("style, town_seed, entry_index, turned_deg, weather, lanes", [
    ("suburb", 4000, 0, 50.0, "noon", 2),
    ("suburb", 4000, 1, 50.0, "night", 1),
    ("suburb", 4000, 4, 40.0, "dusk", 1),
    ("downtown", 4000, 3, 50.0, "night", 2),
    ("downtown", 4000, 1, 65.0, "noon", 1),  # the lane turned into comes into view late in this turn
])
def test_the_line_a_lane_right_of_the_centre_line_tells_one_lane_from_two(
        style: str, town_seed: int, entry_index: int, turned_deg: float, weather: str, lanes: int) -> None:
    """Part way through a right turn, the white line a lane to the right of the road turned into's centre line is a
    single lane's solid edge line or the dashed divider of two lanes: painted over most of its length seen, or over
    half of it at most (``ExitLine.divider_fill``; the junction takes 0.7 as the boundary)."""
    from towndrive.agent.decision.junction import DIVIDER_SOLID_FILL

    rgb, env, (a, b) = _in_turn(style, town_seed, entry_index, Command.RIGHT, turned_deg, weather)
    finder = ExitLineFinder(env.config.camera)
    env.close()
    line = finder.find(rgb, math.atan2(b[0] - a[0], b[1] - a[1]), divider=True)
    assert line is not None and line.divider_fill is not None
    assert (line.divider_fill >= DIVIDER_SOLID_FILL) == (lanes == 1)


@pytest.mark.parametrize("style, town_seed, entry_index, command, turned_deg, weather", [
    ("suburb", 4000, 3, Command.RIGHT, 5.0, "night"),
    ("downtown", 4001, 2, Command.LEFT, 10.0, "dusk"),
    ("downtown", 4000, 5, Command.LEFT, 25.0, "night"),
])
def test_the_corner_camera_reads_the_road_turned_into_from_the_turns_start(
        style: str, town_seed: int, entry_index: int, command: Command, turned_deg: float, weather: str) -> None:
    """Barely into the turn, where the forward camera does not yet look down the road turned into, the corner
    camera on the turn's side does: its reading, carried into the forward camera's ground frame
    (``ExitLine.seen_from``, the corner camera's mount), lies on the town's centre line and runs its way."""
    _, env, (a, b) = _in_turn(style, town_seed, entry_index, command, turned_deg, weather)
    side = "right" if command == Command.RIGHT else "left"
    frame = env.corner_frame(side)
    env.close()
    x, z, yaw = SideMount(CORNERS.ahead_m, CORNERS.out_m, CORNERS.yaw_deg).in_ground_frame(
        side, env.config.camera.mount_forward_m)
    runs = math.atan2(b[0] - a[0], b[1] - a[1])
    line = ExitLineFinder(CORNERS.camera).find(frame, runs - yaw + math.radians(8.0))
    assert line is not None
    seen = line.seen_from(x, z, yaw)
    assert _off_line_m(seen.point, a, b) <= POSITION_TOLERANCE_M
    assert abs(math.degrees(math.remainder(seen.direction_rad - runs, 2 * math.pi))) <= DIRECTION_TOLERANCE_DEG


def _painted(camera: CameraConfig, strokes: list[tuple[tuple[float, float], tuple[float, float]]]) -> np.ndarray:
    """A camera frame of grey road with yellow paint 0.3 m wide along each stroke (two road points, the camera's
    ground frame: x right, z ahead)."""
    eye = BirdsEye(camera)
    rgb = np.full((camera.height, camera.width, 3), 60, np.uint8)
    for a, b in strokes:
        a_, b_ = np.asarray(a, float), np.asarray(b, float)
        u = (b_ - a_) / np.linalg.norm(b_ - a_)
        n = np.array([u[1], -u[0]]) * 0.15
        ring = np.array([a_ + n, b_ + n, b_ - n, a_ - n])
        px = eye.image_of_ground(ring[:, 0], ring[:, 1])
        cv2.fillPoly(rgb, [np.round(px).astype(np.int32)], (210, 170, 40))
    return rgb


def _along(start: tuple[float, float], direction_rad: float, from_m: float, to_m: float
           ) -> tuple[tuple[float, float], tuple[float, float]]:
    """The stroke from ``from_m`` to ``to_m`` along the bearing ``direction_rad`` (from the camera's axis, positive
    right) through ``start`` (the camera's ground frame)."""
    u = np.array([math.sin(direction_rad), math.cos(direction_rad)])
    p = np.asarray(start, float)
    return tuple(p + from_m * u), tuple(p + to_m * u)  # type: ignore[return-value]


def test_paint_in_pieces_far_apart_is_not_a_line() -> None:
    """A zebra stripe lit orange (3 m) and a fleck 5 m beyond it on the same bearing span nearly 9 m, but no
    line is painted there: nothing is read (read as one line, the turn's arc was put 2 m too far)."""
    camera = DriveConfig().camera
    runs = math.radians(-52.0)
    rgb = _painted(camera, [_along((-6.0, 7.5), runs, 0.0, 3.0), _along((-6.0, 7.5), runs, 8.0, 8.6)])
    assert ExitLineFinder(camera).find(rgb, runs) is None


def test_a_centre_line_cut_short_by_a_car_is_read_from_its_longest_piece() -> None:
    """A centre line with a car across it (a 4 m gap) is read from the longer piece in view, on the line."""
    camera = DriveConfig().camera
    runs, start = math.radians(-45.0), (-2.0, 6.0)
    rgb = _painted(camera, [_along(start, runs, 0.0, 3.0), _along(start, runs, 7.0, 16.0)])
    line = ExitLineFinder(camera).find(rgb, runs + math.radians(5.0))
    assert line is not None
    a, b = (np.asarray(p) for p in _along(start, runs, 0.0, 16.0))
    assert _off_line_m(line.point, a, b) <= POSITION_TOLERANCE_M
    assert abs(math.degrees(math.remainder(line.direction_rad - runs, 2 * math.pi))) <= DIRECTION_TOLERANCE_DEG
    assert 7.0 <= line.length_m <= 12.0  # the longer piece alone (read as one line, both: 16 m and more)
