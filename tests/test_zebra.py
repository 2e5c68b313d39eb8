"""Zebra-crossing detection on rendered frames: the far edge against the town's crosswalks, nothing on the
open road, and one clear error for a frame of the wrong size."""

from __future__ import annotations

import math

import numpy as np
import pytest

from towndrive.agent.perception.lanes import LaneDetector
from towndrive.agent.perception.stop_line import StopLineDetector
from towndrive.agent.perception.zebra import ZebraDetector
from towndrive.envs.drive_env import DriveConfig, DriveEnv
from towndrive.envs.perception_truth import zebra_truth
from towndrive.sim.town import TownConfig
from towndrive.sim.world import World, WorldConfig, cached_town

FAR_EDGE_TOLERANCE_M = 0.8  # one image row spans 0.5 m of road at 16 m, 1 m at 20 m


def _frame(style: str, town_seed: int, entry_index: int, before_end_m: float) -> tuple[np.ndarray, DriveEnv]:
    """The camera frame of a car in lane 0 of an entry's road, ``before_end_m`` before the road's end."""
    cfg = DriveConfig(world=WorldConfig(town=TownConfig.of_style(style)))
    env = DriveEnv(cfg)
    town = cached_town(cfg.world.town, town_seed)
    entry = town.entries[entry_index]
    lane = town.lane((*entry.edge, 0))
    world = World(town, cfg.world, seed=0, start=(*entry.edge, 0), start_s=lane.length - before_end_m,
                  spawn_traffic=False)
    obs, _ = env.reset(seed=0, options={"world": world, "town_seed": town_seed})
    return obs["image"], env


def _chain(rgb: np.ndarray, env: DriveEnv):
    cam = env.config.camera
    lanes = LaneDetector(cam).detect(rgb)
    stop = StopLineDetector(cam).detect(rgb, lanes)
    return ZebraDetector(cam).detect(rgb, lanes, stop.distance_m if stop is not None else None)


@pytest.mark.parametrize("style, town_seed, before_end_m", [("classic", 4000, 8.0), ("classic", 4000, 14.0),
                                                            ("suburb", 4000, 10.0)])
def test_far_edge_matches_the_town(style: str, town_seed: int, before_end_m: float) -> None:
    rgb, env = _frame(style, town_seed, 0, before_end_m)
    assert env.world is not None
    truth = zebra_truth(env.world, env.config.camera)
    zebra = _chain(rgb, env)
    env.close()
    assert math.isfinite(truth.far_m) and truth.far_m < 25.0
    assert zebra is not None
    assert abs(zebra.far_m - truth.far_m) <= FAR_EDGE_TOLERANCE_M
    assert abs(zebra.near_m - truth.near_m) <= FAR_EDGE_TOLERANCE_M
    assert 0.3 <= zebra.fill <= 0.75  # stripes 0.5 m every 1 m


def test_nothing_on_the_open_road() -> None:
    """Far from the junction (its line beyond the 30 m view) no zebra is reported, with or without a stop line."""
    rgb, env = _frame("classic", 4000, 0, 60.0)
    assert env.world is not None
    truth = zebra_truth(env.world, env.config.camera)
    cam = env.config.camera
    lanes = LaneDetector(cam).detect(rgb)
    env.close()
    assert truth.bar_m > 40.0
    assert lanes.detected  # the corridor is the lane's, as when driving
    assert ZebraDetector(cam).detect(rgb, lanes) is None
    assert ZebraDetector(cam).detect(rgb, None) is None


def test_a_zebra_too_far_past_the_stop_line_does_not_count() -> None:
    rgb, env = _frame("classic", 4000, 0, 10.0)
    zebra = _chain(rgb, env)
    assert zebra is not None
    cam = env.config.camera
    env.close()
    lanes = LaneDetector(cam).detect(rgb)
    assert ZebraDetector(cam).detect(rgb, lanes, stop_line_m=zebra.near_m - 9.0) is None


def test_wrong_frame_is_one_value_error() -> None:
    detector = ZebraDetector()
    with pytest.raises(ValueError, match="320x160 uint8 RGB"):
        detector.detect(np.zeros((160, 320), np.uint8), None)
    with pytest.raises(ValueError, match="320x160 uint8 RGB"):
        detector.detect(np.zeros((120, 320, 3), np.uint8), None)


@pytest.mark.parametrize("style, entry_index, before_end_m", [("downtown", 0, 5.0), ("downtown", 1, 7.0),
                                                               ("suburb", 3, 5.0), ("classic", 0, 7.0)])
def test_the_zebra_s_edges_tell_the_cross_street_s_direction(style: str, entry_index: int,
                                                              before_end_m: float) -> None:
    """Where a junction is not square the zebra's edges run along the cross street: the slope of its stripes' ends
    (dz/dx, the car lined up with its lane) against the town's crosswalk, within 0.05 (3 degrees; a downtown
    junction leans 7.4 degrees, a classic one not at all)."""
    rgb, env = _frame(style, 4000, entry_index, before_end_m)
    assert env.world is not None
    town = env.world.town
    entry = town.entries[entry_index]
    cw = next(c for c in town.crosswalks if (c.node, c.arm) == (entry.node, entry.arm))
    t = np.array([math.cos(entry.travel_heading), math.sin(entry.travel_heading)])
    axis = np.asarray(cw.end, float) - np.asarray(cw.start, float)
    truth = float(axis @ t) / float(axis @ np.array([-t[1], t[0]]))
    zebra = _chain(rgb, env)
    env.close()
    assert zebra is not None and zebra.tilt is not None
    assert abs(zebra.tilt - truth) <= 0.05, (zebra.tilt, truth)
    if style != "classic":
        assert abs(truth) > 0.1  # the case is one that leans


@pytest.mark.parametrize("before_end_m", [12.0, 16.0])
def test_on_an_arm_with_no_bar_the_zebra_stands_in_for_one(before_end_m: float) -> None:
    """``bar_checked`` on a suburb arm with priority (no bar painted; a training town): far off, the zebra's stripes
    run together and the stop-line detector reads a "bar" inside the zebra's band, which is dropped; the zebra then
    stands in for the bar, placed where the style's design puts bars before a zebra's far edge, off the arm's own
    bar line by the arm's difference from that design and the far edge's reading error."""
    from towndrive.agent.perception.stop_line import StopLine
    from towndrive.agent.perception.zebra import bar_checked
    from towndrive.sim.road_priors import road_priors
    from towndrive.sim.town import Control

    road = road_priors("suburb")
    town_seed, entry_index = 1000, 1
    assert cached_town(TownConfig.of_style("suburb"), town_seed).entries[entry_index].control == Control.PRIORITY
    rgb, env = _frame("suburb", town_seed, entry_index, before_end_m)
    assert env.world is not None
    truth = zebra_truth(env.world, env.config.camera)
    cam = env.config.camera
    env.close()
    lanes = LaneDetector(cam).detect(rgb)
    read = StopLineDetector(cam).detect(rgb, lanes)
    zebra = ZebraDetector(cam).detect(rgb, lanes, None)
    assert zebra is not None and read is not None
    assert zebra.near_m < read.distance_m < zebra.far_m  # the zebra, read as a bar
    assert bar_checked(read, zebra, road) is None
    assert bar_checked(read, zebra, road, 5.0) is None  # the stand-in lies farther than that
    stand_in = bar_checked(read, zebra, road, 20.0)
    assert stand_in is not None
    arm = truth.far_m - truth.bar_m  # this arm's bar line to its zebra's far edge
    assert abs(stand_in.distance_m - truth.bar_m) <= abs(arm - road.zebra_beyond_bar_m) + FAR_EDGE_TOLERANCE_M
    bar = StopLine(zebra.near_m - 1.0, 0.5, 0.9, 0)  # a bar read before the zebra is a bar, kept as read
    assert bar_checked(bar, zebra, road, 20.0) is bar
