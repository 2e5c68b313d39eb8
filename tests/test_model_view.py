"""A camera unlike the trained rig is warped into its view (agent.perception.model_view)."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np

from towndrive.agent.perception.model_view import ModelView, model_camera
from towndrive.envs.drive_env import DriveConfig, DriveEnv
from towndrive.sim.spec import CAMERA


def picture(camera) -> np.ndarray:
    env = DriveEnv(DriveConfig(camera=camera))
    try:
        obs, _ = env.reset(seed=3)
        return obs["image"].astype(int)
    finally:
        env.close()


def test_a_wider_lens_pitched_lower_is_warped_into_the_trained_picture() -> None:
    wide = replace(CAMERA, hfov_deg=100.0, pitch_deg=-7.0)
    view = ModelView(wide)
    assert view.camera == CAMERA and view.homography is not None
    trained, seen = picture(CAMERA), picture(wide)
    warped = view(seen.astype(np.uint8)).astype(int)
    assert warped.shape == trained.shape
    assert np.abs(seen - trained).mean() > 15.0  # the road and kerbs fall elsewhere in the picture
    assert np.abs(warped - trained).mean() < 4.0  # the same picture, but for resampling
    assert ModelView(CAMERA).homography is None  # the trained rig itself is not touched
    # a different mounting height stays: the agent's geometry uses the car's own
    assert model_camera(replace(wide, mount_height_m=1.5)).mount_height_m == 1.5


def test_pilotnet_sees_the_road_of_a_higher_camera_as_from_the_trained_height() -> None:
    higher = replace(CAMERA, hfov_deg=100.0, mount_height_m=1.5)
    view = ModelView(higher)
    assert view.needed and view.road_homography is not None
    trained = picture(CAMERA)
    rotated = view(picture(higher).astype(np.uint8))
    road = view.for_pilotnet(rotated)
    row = view.below_horizon_row
    assert np.array_equal(road[:row], rotated[:row])  # above the horizon: unchanged
    before = np.abs(rotated[row:].astype(int) - trained[row:]).mean()
    after = np.abs(road[row:].astype(int) - trained[row:]).mean()
    assert after < 0.5 * before, (before, after)  # the lines on the road fall where the trained rig sees them


def test_the_agent_works_in_the_trained_view_of_a_different_camera() -> None:
    from towndrive.agent.drivers import make_driver

    driver = make_driver("agent")
    driver.reset(SimpleNamespace(config=DriveConfig(camera=replace(CAMERA, hfov_deg=100.0, mount_height_m=1.5))))
    assert driver.camera.hfov_deg == CAMERA.hfov_deg and driver.camera.mount_height_m == 1.5
    assert driver.geometry.camera == driver.camera
