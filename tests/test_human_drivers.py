"""The keyboard and gamepad drivers, headless (SDL dummy video driver, events posted by hand)."""

from __future__ import annotations

import os

os.environ["SDL_VIDEODRIVER"] = "dummy"

import numpy as np  # noqa: E402
import pygame  # noqa: E402
import pytest  # noqa: E402

from towndrive.agent.drivers import Driver, make_driver  # noqa: E402
from towndrive.agent.human import GamepadDriver, KeyboardDriver  # noqa: E402
from towndrive.envs.drive_env import DriveConfig, DriveEnv  # noqa: E402
from towndrive.sim.render import CameraConfig  # noqa: E402


@pytest.fixture(scope="module")
def env():
    e = DriveEnv(DriveConfig(camera=CameraConfig(width=200, height=66)))
    e.reset(seed=0)
    yield e
    e.close()


@pytest.fixture
def driver(env):
    d = KeyboardDriver(realtime=False)
    obs, info = env.reset(seed=0)
    d.reset(env)
    d.obs = obs
    yield d
    d.close()


def key(kind: int, k: int) -> None:
    pygame.event.post(pygame.event.Event(kind, key=k))


def test_protocol_and_registry():
    d = make_driver("keyboard", realtime=False)
    assert isinstance(d, KeyboardDriver) and isinstance(d, Driver)
    assert d.name == "keyboard" and d.privileged is False
    g = make_driver("gamepad")
    assert isinstance(g, GamepadDriver) and g.privileged is False


def test_steer_ramps_right_and_returns(driver, env):
    assert driver.dt == env.config.world.dt_s
    key(pygame.KEYDOWN, pygame.K_RIGHT)
    steers = [float(driver.act(driver.obs)[0]) for _ in range(12)]
    assert steers[0] == pytest.approx(2.5 * 0.05)  # one step of the ramp, not a jump
    assert all(b >= a for a, b in zip(steers, steers[1:], strict=False))
    assert steers[4] < 1.0 and steers[-1] == pytest.approx(1.0)  # ramps, then capped at 1
    key(pygame.KEYUP, pygame.K_RIGHT)
    back = [float(driver.act(driver.obs)[0]) for _ in range(6)]
    assert all(b <= a for a, b in zip(back, back[1:], strict=False))
    assert back[0] > 0.0 and back[-1] == 0.0  # returns faster than it went out (5 steps vs 8)


def test_left_is_negative_wasd(driver):
    key(pygame.KEYDOWN, pygame.K_a)
    for _ in range(3):
        action = driver.act(driver.obs)
    assert action[0] < 0.0
    key(pygame.KEYUP, pygame.K_a)


def test_throttle_and_brake(driver):
    key(pygame.KEYDOWN, pygame.K_UP)
    for _ in range(5):
        action = driver.act(driver.obs)
    assert action[1] > 0.0 and action[0] == 0.0
    key(pygame.KEYUP, pygame.K_UP)
    key(pygame.KEYDOWN, pygame.K_s)
    for _ in range(10):
        action = driver.act(driver.obs)
    assert action[1] < 0.0
    assert action.dtype == np.float32 and action.shape == (2,)
    assert np.all(np.abs(action) <= 1.0)


def test_pause_toggles_zeros(driver):
    key(pygame.KEYDOWN, pygame.K_UP)
    driver.act(driver.obs)
    key(pygame.KEYDOWN, pygame.K_p)
    key(pygame.KEYUP, pygame.K_p)
    action = driver.act(driver.obs)
    assert driver.paused is True and np.all(action == 0.0)
    key(pygame.KEYDOWN, pygame.K_p)
    action = driver.act(driver.obs)
    assert driver.paused is False and action[1] > 0.0


def test_reset_and_quit_requests(driver, env):
    assert not driver.reset_requested and not driver.quit_requested
    key(pygame.KEYDOWN, pygame.K_r)
    driver.act(driver.obs)
    assert driver.reset_requested
    env.reset(seed=1)
    driver.reset(env)
    assert not driver.reset_requested
    key(pygame.KEYDOWN, pygame.K_ESCAPE)
    driver.act(driver.obs)
    assert driver.quit_requested


def test_q_and_window_close_request_quit(env):
    for event in (pygame.event.Event(pygame.KEYDOWN, key=pygame.K_q), pygame.event.Event(pygame.QUIT)):
        d = KeyboardDriver(realtime=False)
        d.reset(env)
        pygame.event.post(event)
        d.act({})
        assert d.quit_requested
        d.close()


def test_gamepad_without_joystick_is_a_clear_error(env):
    with pytest.raises(RuntimeError, match="No gamepad found; connect one or use --driver keyboard."):
        GamepadDriver(realtime=False).reset(env)


def test_closed_loop_throttle_speeds_up(env, tmp_path):
    d = KeyboardDriver(realtime=False)
    obs, info = env.reset(seed=0)
    d.reset(env)
    v0 = info["ego"]["speed_mps"]
    key(pygame.KEYDOWN, pygame.K_UP)
    speeds = []
    for _ in range(20):
        obs, _, terminated, truncated, info = env.step(d.act(obs))
        d.update_hud(info, recording=True)
        speeds.append(info["ego"]["speed_mps"])
        assert not (terminated or truncated)
    assert speeds[-1] > v0 + 1.0
    assert speeds[-1] > speeds[len(speeds) // 2]
    d.act(obs)  # draw the HUD for the last step
    assert d.window.surface.get_size() == (2 * 426, 2 * 106 + 64)  # composite x2 plus the HUD strip
    pygame.image.save(d.window.surface, str(tmp_path / "hud.png"))
    assert (tmp_path / "hud.png").stat().st_size > 1000
    d.close()
