"""Drive-v0: API checkers, determinism, vector envs, and what the camera shows."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import towndrive.envs  # noqa: F401  (registers Drive-v0)
from towndrive.envs.drive_env import DriveConfig, DriveEnv
from towndrive.sim.objects import LIGHT_ID_BASE, LightState, SemanticClass
from towndrive.sim.render import CameraConfig

SMALL = CameraConfig(width=200, height=66)


def test_registered_and_passes_gymnasium_checker():
    from gymnasium.utils.env_checker import check_env

    env = gym.make("Drive-v0", config=DriveConfig(camera=SMALL))
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_passes_stable_baselines3_checker():
    from stable_baselines3.common.env_checker import check_env

    env = DriveEnv(DriveConfig(camera=SMALL))
    check_env(env, warn=False)
    env.close()


def _rollout(seed: int, steps: int = 40) -> tuple[list[np.ndarray], list[dict]]:
    env = DriveEnv(DriveConfig(camera=SMALL, observe_segmentation=True))
    obs, info = env.reset(seed=seed)
    rng = np.random.default_rng(99)
    frames, infos = [obs["image"].copy()], [info]
    for _ in range(steps):
        obs, _, term, trunc, info = env.step(rng.uniform(-0.3, 1.0, 2).astype(np.float32))
        frames.append(obs["image"].copy())
        frames.append(obs["segmentation"].copy())
        infos.append(info)
        if term or trunc:
            break
    env.close()
    return frames, infos


def test_same_seed_gives_bit_identical_frames_and_info():
    a_frames, a_info = _rollout(11)
    b_frames, b_info = _rollout(11)
    assert len(a_frames) == len(b_frames)
    assert all(np.array_equal(x, y) for x, y in zip(a_frames, b_frames, strict=True))
    assert repr(a_info) == repr(b_info)
    c_frames, _ = _rollout(12)
    assert not all(np.array_equal(x, y) for x, y in zip(a_frames, c_frames, strict=False))


def test_runs_in_a_vector_env():
    vec = gym.vector.SyncVectorEnv([lambda: DriveEnv(DriveConfig(camera=SMALL)) for _ in range(2)])
    obs, _ = vec.reset(seed=[1, 2])
    assert obs["image"].shape == (2, SMALL.height, SMALL.width, 3)
    for _ in range(3):
        obs, reward, term, trunc, _ = vec.step(np.array([[0.0, 0.5], [0.0, 0.5]], dtype=np.float32))
    assert reward.shape == (2,)
    vec.close()


def _env_before_red_light(weather: str = "noon", distance_m: float = 22.0):
    env = DriveEnv(DriveConfig(observe_segmentation=True, observe_depth=True, weather=weather), render_mode="rgb_array")
    town_env_world = env.reset(seed=0)  # builds the renderer
    del town_env_world
    town = env.world.town
    ap = town.approaches[1]
    lane = town.network.graph[ap.edge[0]][ap.edge[1]][0]
    obs, info = env.reset(seed=0, options={"start": (ap.edge[0], ap.edge[1], 0)})
    world = env.world
    world.ego.position = lane.position(lane.length - distance_m, 0.0)
    world.ego.heading = lane.heading_at(lane.length - distance_m)
    world.lights.force(ap.index, LightState.RED, until_s=60.0)
    obs, *_ , info = env.step(np.array([0.0, -1.0], dtype=np.float32))
    return env, ap, obs, info


def test_frame_shows_road_lane_lines_and_the_lit_red_lamp_where_segmentation_says():
    env, ap, obs, info = _env_before_red_light()
    rgb = obs["image"].astype(np.int32)
    cls = obs["segmentation"][..., 0]
    oid = obs["segmentation"][..., 1]
    assert rgb.std() > 20  # not blank
    road = cls == SemanticClass.ROAD
    lines = cls == SemanticClass.LANE_MARKING
    assert road.sum() > 0.15 * road.size and lines.sum() > 30
    assert rgb[lines].mean() > rgb[road].mean() + 60  # painted lines are bright on dark asphalt
    lamp = (cls == SemanticClass.TRAFFIC_LAMP) & (oid == LIGHT_ID_BASE + ap.index)
    assert lamp.sum() >= 3
    lit = rgb[lamp]
    reddest = lit[np.argmax(lit[:, 0] - lit[:, 1])]
    assert reddest[0] > 180 and reddest[1] < 100 and reddest[2] < 100  # the red lamp is lit
    assert not np.any((lit[:, 1] > 180) & (lit[:, 0] < 120))  # the green lamp is dark
    assert info["next_light"]["state"] == "red"
    assert any(o["class"] == "traffic_light" and o["approach"] == ap.index for o in info["objects"])
    env.close()


def test_depth_matches_the_ground_plane_within_one_percent():
    env, _, obs, _ = _env_before_red_light()
    cam = env.config.camera
    K = cam.intrinsics()
    depth = obs["depth"]
    cls = obs["segmentation"][..., 0]
    pitch = math.radians(cam.pitch_deg)
    checked = 0
    for v in range(cam.height - 1, cam.height // 2 + 8, -6):
        u = cam.width // 2
        if cls[v, u] != SemanticClass.ROAD:
            continue
        # Ray through the pixel, camera frame (x right, y down, z forward), pitched down by |pitch|.
        y_c = (v - K[1, 2]) / K[1, 1]
        down = y_c * math.cos(pitch) - math.sin(pitch)  # downward component per unit optical depth
        expected = cam.mount_height_m / down
        assert depth[v, u] == pytest.approx(expected, rel=0.01)
        checked += 1
    assert checked >= 3
    env.close()


def test_info_carries_ground_truth_and_reward_is_progress():
    env = DriveEnv(DriveConfig(camera=SMALL))
    obs, info = env.reset(seed=3)
    for key in ("ego", "lane_offset_m", "next_light", "objects", "infractions", "route", "command"):
        assert key in info
    total = 0.0
    for _ in range(60):
        obs, r, term, trunc, info = env.step(np.array([0.0, 0.6], dtype=np.float32))
        total += r
        if term or trunc:
            break
    assert info["route"]["progress_m"] > 5.0
    assert total == pytest.approx(info["route"]["progress_m"] / 10 - 0.8, abs=1.5)
    env.close()


def test_bad_options_get_one_clear_error():
    env = DriveEnv(DriveConfig(camera=SMALL))
    with pytest.raises(ValueError, match="Unknown weather"):
        env.reset(seed=0, options={"weather": "monsoon"})
    with pytest.raises(ValueError, match="Unknown reset option"):
        env.reset(seed=0, options={"scenario_typo": 1})
    with pytest.raises(RuntimeError, match="reset"):
        DriveEnv(DriveConfig(camera=SMALL)).step(np.zeros(2))
    env.close()


def test_human_render_mode_opens_a_window_headless(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    env = DriveEnv(DriveConfig(camera=SMALL), render_mode="human")
    env.reset(seed=0)
    env.step(np.array([0.0, 0.3], dtype=np.float32))
    assert env._window is not None and env._window.get_size()[0] > 0
    rgb = DriveEnv(DriveConfig(camera=SMALL), render_mode="rgb_array")
    rgb.reset(seed=0)
    frame = rgb.render()
    assert frame.ndim == 3 and frame.shape[1] > SMALL.width
    env.close()
    rgb.close()
