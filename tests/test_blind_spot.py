"""The blind-spot check: where a mirror-camera box puts a vehicle, the zone and its memory, and that looking
through the mirror camera leaves the env's own frames unchanged."""

from __future__ import annotations

import math

import numpy as np
import pytest

from towndrive.agent.agent_driver import DEFAULT_DETECTOR, BoxGeometry
from towndrive.agent.decision.blind_spot import BlindSpot, BlindSpotConfig, SideMount
from towndrive.agent.perception.classes import CLASSES
from towndrive.agent.perception.detector import Detection
from towndrive.agent.perception.pilotnet import DEFAULT_MODEL
from towndrive.envs.drive_env import BLIND_SPOT_CAMERA, BLIND_SPOT_MOUNT_M, BLIND_SPOT_YAW_DEG, DriveConfig, DriveEnv
from towndrive.sim.render import CameraConfig

MOUNT = SideMount(*BLIND_SPOT_MOUNT_M, BLIND_SPOT_YAW_DEG)


def mirror_box(spot: BlindSpot, side: str, ahead: float, out: float) -> Detection:
    """The box a 1.5 m tall car whose near face stands at (ahead, out) of our centre gets in the mirror camera."""
    a = math.radians(MOUNT.yaw_deg)
    da, do = ahead - MOUNT.ahead_m, out - MOUNT.out_m
    z = da * math.cos(a) + do * math.sin(a)  # along the camera's axis, on the ground
    x = -da * math.sin(a) + do * math.cos(a)  # right of it (the right camera; the left one is its mirror image)
    if side == "left":
        x = -x
    geo = spot.geometry
    (u, v), = geo.birdseye.image_of_ground(np.array([x]), np.array([z]))
    h_px = geo.f * 1.5 / z
    return Detection((u - 20.0, v - h_px, u + 20.0, v), CLASSES.index("car"), 0.9)


@pytest.fixture
def spot() -> BlindSpot:
    return BlindSpot(BoxGeometry(BLIND_SPOT_CAMERA), MOUNT, BlindSpotConfig())


@pytest.mark.parametrize("side", ["left", "right"])
def test_mirror_box_puts_the_vehicle_where_it_is(spot: BlindSpot, side: str) -> None:
    for ahead, out in ((-4.0, 3.0), (-12.0, 3.5), (0.0, 2.6), (-18.0, 5.0)):
        got = spot.position(mirror_box(spot, side, ahead, out), side)
        assert got[0] == pytest.approx(ahead, abs=0.3 + 0.03 * abs(ahead))
        assert got[1] == pytest.approx(out, abs=0.3 + 0.03 * abs(ahead))


def test_a_vehicle_in_the_zone_holds_the_change_for_a_while(spot: BlindSpot) -> None:
    far_lane = mirror_box(spot, "right", -6.0, 9.5)  # two lanes out: the oncoming road or a parking lane
    assert spot.update(0.0, "right", [far_lane]) == []
    assert not spot.holding(0.0, "right")
    people = Detection(mirror_box(spot, "right", -4.0, 3.5).box, CLASSES.index("pedestrian"), 0.9)
    assert spot.update(0.1, "right", [people]) == []
    found = spot.update(0.2, "right", [mirror_box(spot, "right", -2.0, 3.5)])  # alongside: held 3 s, eased off
    assert len(found) == 1 and spot.alongside("right")
    assert spot.holding(0.3, "right") and not spot.holding(0.3, "left")
    assert spot.holding(0.2 + spot.config.memory_s - 0.05, "right")
    assert not spot.holding(0.2 + spot.config.memory_s + 0.05, "right")
    spot.update(5.0, "right", [mirror_box(spot, "right", -5.0, 3.5)])  # following 2.7 m behind our rear: held 1 s
    assert not spot.alongside("right")
    assert spot.holding(5.0 + spot.config.behind_memory_s - 0.05, "right")
    assert not spot.holding(5.0 + spot.config.behind_memory_s + 0.05, "right")
    assert spot.update(7.0, "right", [mirror_box(spot, "right", -9.0, 3.5)]) == []  # farther back: merged in front of
    assert "right blind spot" in spot.reason("right")
    spot.update(7.1, "right", [mirror_box(spot, "right", 0.0, 3.5)])
    spot.update(7.2, "left", [])  # each side has its own zone
    assert spot.holding(7.3, "right") and not spot.holding(7.3, "left")
    assert not spot.holding(7.3, None)


def test_looking_through_the_mirror_camera_leaves_the_env_frames_unchanged() -> None:
    config = DriveConfig(camera=CameraConfig(width=160, height=80), max_time_s=30.0)
    plain, looking = DriveEnv(config), DriveEnv(config)
    o1, _ = plain.reset(seed=3)
    o2, _ = looking.reset(seed=3)
    action = np.array([0.0, 0.6], np.float32)
    seen = []
    for k in range(30):
        side = ("left", "right")[k % 2]
        seen.append(looking.blind_spot_frame(side))
        o1, *_, i1 = plain.step(action)
        o2, *_, i2 = looking.step(action)
        assert np.array_equal(o1["image"], o2["image"])
        assert i1["objects"] == i2["objects"]
    assert seen[0].shape == (BLIND_SPOT_CAMERA.height, BLIND_SPOT_CAMERA.width, 3)
    assert seen[-1].std() > 10  # a picture, not a blank
    with pytest.raises(ValueError, match="side"):
        looking.blind_spot_frame("behind")
    plain.close()
    looking.close()



@pytest.mark.skipif(not (DEFAULT_MODEL.is_file() and DEFAULT_DETECTOR.is_file()), reason="shipped models missing")
def test_agent_looks_in_the_mirrors_and_the_overlay_lights_the_side() -> None:
    from dataclasses import replace

    from towndrive.agent.agent_overlay import BLIND_SPOT_RGB, draw_agent
    from towndrive.agent.drivers import make_driver

    env = DriveEnv(DriveConfig())
    try:
        obs, _ = env.reset(seed=3)
        assert make_driver("agent").config.blind_spot.enabled is True  # on by default (agent.decision.blind_spot)
        driver = make_driver("agent", blind_spot=BlindSpotConfig(enabled=True))
        driver.reset(env)
        looks = []
        driver._look = lambda side, look=env.blind_spot_frame: looks.append(side) or look(side)
        for _ in range(11):
            obs, *_ = env.step(driver.act(obs))
        assert len(looks) >= 3 and set(looks) == {"left", "right"}  # in turn every 5th frame, more when changing
        assert "blind_spot" in driver.timings[0] and driver.timings[0]["blind_spot"] > 0.0
        view = replace(driver.view, blind_spot=(False, True))
        picture = draw_agent(view, driver.lanes.birdseye)
        h, w = picture.shape[:2]
        amber = np.all(picture == np.array(BLIND_SPOT_RGB, np.uint8), axis=2)
        assert amber[:, w - 30:].sum() > 50 and amber[:, :30].sum() == 0
    finally:
        env.close()


@pytest.mark.skipif(not (DEFAULT_MODEL.is_file() and DEFAULT_DETECTOR.is_file()), reason="shipped models missing")
def test_with_the_mirror_look_the_agent_lets_the_overtaking_car_pass_before_its_turn() -> None:
    from towndrive.agent.drivers import make_driver
    from towndrive.envs.scenarios import run_scenario

    # Without the look, PilotNet moves into the car beside (measured: a collision in this scenario).
    driver = make_driver("agent", blind_spot=BlindSpotConfig(enabled=True))
    result = run_scenario("overtaken_before_turn", driver, DriveConfig())
    assert result.passed, result.detail
