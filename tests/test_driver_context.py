"""The driver contract: camera-only drivers get the sensor rig and time step only; privileged ones the world;
every built-in driver accepts an env made by ``gym.make`` (wrappers included)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import towndrive.envs  # noqa: F401  (registers Drive-v0)
from towndrive.agent.drivers import make_driver
from towndrive.envs.drive_env import DriveConfig
from towndrive.envs.driver_context import DriverContext
from towndrive.sim.spec import MIRRORS, CameraConfig


def test_a_camera_only_context_holds_the_rig_not_the_world() -> None:
    env = gym.make("Drive-v0", config=DriveConfig(camera=CameraConfig(width=160, height=80)))
    try:
        env.reset(seed=1)
        ctx = DriverContext.of(env)  # through gym's wrappers
        assert ctx.world is None and ctx.env is None
        assert ctx.camera.width == 160 and ctx.dt_s == env.unwrapped.config.world.dt_s
        assert ctx.mirror_camera == MIRRORS.camera and ctx.mirror_frame is not None
        assert ctx.mirror_frame("left").shape == (MIRRORS.camera.height, MIRRORS.camera.width, 3)
        privileged = DriverContext.of(env, privileged=True)
        assert privileged.world is env.unwrapped.world
        with pytest.raises(ValueError, match="privileged driver needs the world"):
            DriverContext.of(ctx, privileged=True)
    finally:
        env.close()


def test_built_in_drivers_accept_an_env_made_by_gym_make() -> None:
    env = gym.make("Drive-v0", config=DriveConfig(camera=CameraConfig(width=320, height=160)))
    try:
        obs, _ = env.reset(seed=3)
        for name in ("autopilot", "agent", "pilotnet"):
            driver = make_driver(name)
            driver.reset(env)
            action = driver.act(obs)
            assert action.shape == (2,) and np.all(np.abs(action) <= 1.0)
        agent = make_driver("agent")
        agent.reset(DriverContext(camera=CameraConfig(width=320, height=160), dt_s=0.05))  # a real camera's rig
        assert agent.act(obs).shape == (2,)
    finally:
        env.close()
