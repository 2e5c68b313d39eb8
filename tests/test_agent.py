"""The full agent: box geometry, that it drives from observations alone, and one closed-loop scenario."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from agent.agent_driver import DEFAULT_DETECTOR, STAGES, BoxGeometry
from agent.pilotnet_driver import DEFAULT_MODEL
from sim.render import CameraConfig

needs_models = pytest.mark.skipif(not (DEFAULT_MODEL.is_file() and DEFAULT_DETECTOR.is_file()),
                                  reason="the shipped PilotNet and detector models are not in data/models")


def test_box_geometry_recovers_distance_and_lateral_position() -> None:
    cam = CameraConfig()
    geo = BoxGeometry(cam)
    for z, x in ((8.0, 0.0), (15.0, 3.5), (25.0, -3.5)):
        (u, v), = geo.birdseye.image_of_ground(np.array([x]), np.array([z]))
        h_px = geo.f * 1.5 / z  # a 1.5 m tall car
        box = (u - 10.0, v - h_px, u + 10.0, v)
        d = geo.distance(box, "car")
        assert d == pytest.approx(z, rel=0.04)
        assert geo.lateral(u, d) == pytest.approx(x, abs=0.15 + 0.02 * z)
    # cut off at the bottom of the picture: never farther than the last image row's road
    assert geo.distance((100.0, 60.0, 200.0, cam.height), "car") <= float(geo.birdseye.ground_z_of_row(np.array([cam.height]))[0])


@needs_models
def test_agent_drives_from_observations_only_and_times_every_stage() -> None:
    from agent.drivers import make_driver
    from envs.drive_env import DriveConfig, DriveEnv

    env = DriveEnv(DriveConfig(), render_mode="rgb_array")
    try:
        obs, _ = env.reset(seed=3)
        driver = make_driver("agent")
        assert driver.privileged is False
        # reset() gets a stand-in that has only the configuration: touching env.world would fail here
        driver.reset(SimpleNamespace(config=env.config))
        for _ in range(5):
            action = driver.act(obs)
            assert action.shape == (2,) and np.all(np.abs(action) <= 1.0)
            obs, *_ = env.step(action)
        assert len(driver.timings) == 5
        assert set(STAGES) | {"total"} <= set(driver.timings[-1])
        assert driver.view is not None and driver.view.decision.reason
        picture = driver.overlay()
        assert picture is not None and picture.shape == (320, 640, 3)
        summary = driver.adas_summary()
        assert set(summary["counts"]) == {"lane_departure", "forward_collision", "object_in_lane"}
    finally:
        env.close()


@needs_models
def test_agent_stops_0_to_2_m_before_the_stop_line_at_a_red_light() -> None:
    from agent.drivers import make_driver
    from envs.drive_env import DriveConfig
    from envs.scenarios import run_scenario

    driver = make_driver("agent")
    result = run_scenario("red_light", driver, DriveConfig())
    assert result.passed, result.detail
    reasons = {driver.view.decision.reason}
    assert any(r.startswith("red light") for r in reasons)
