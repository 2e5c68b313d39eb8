"""The RL baseline: the state observation, a tiny training run through train.py, and the rl driver."""

from __future__ import annotations

import numpy as np
import pytest


def _state_env():
    from towndrive.agent.rl_features import StateObservation
    from towndrive.envs.drive_env import DriveConfig, DriveEnv

    return StateObservation(DriveEnv(DriveConfig(render_camera=False)))


def test_state_observation_passes_sb3s_env_checker():
    from stable_baselines3.common.env_checker import check_env

    env = _state_env()
    check_env(env, skip_render_check=True)
    env.close()


def test_state_features_see_the_lane_offset_and_the_command():
    env = _state_env()
    obs, _ = env.reset(seed=3)
    assert abs(obs[0]) < 0.1 and obs[9:13].sum() == 1.0 and obs[13:17].sum() == 1.0
    world = env.unwrapped.world
    ego = world.ego
    # move the car 1 m to its right: the lateral feature grows by about 0.5 (1 m / 2 m)
    right = np.array([-np.sin(ego.heading), np.cos(ego.heading)])
    ego.position = ego.position + right
    moved = env.state(np.zeros(2, np.float32))
    assert moved[0] - obs[0] == pytest.approx(0.5, abs=0.1)
    env.close()


def test_train_py_rl_trains_saves_and_the_driver_loads_it(tmp_path):
    import train
    from towndrive.agent.drivers import make_driver
    from towndrive.envs.drive_env import DriveConfig, DriveEnv

    model = tmp_path / "rl_ppo.zip"
    assert train.main(["rl", "--algo", "ppo", "--steps", "512", "--envs", "1", "--eval-every", "100000",
                       "--out", str(tmp_path / "run"), "--model", str(model), "--episode-seconds", "10"]) == 0
    assert model.exists() and model.with_suffix(".json").exists() and (tmp_path / "run" / "progress.csv").exists()
    driver = make_driver("rl", model=model)
    env = DriveEnv(DriveConfig(render_camera=False))
    obs, _ = env.reset(seed=1)
    driver.reset(env)
    action = driver.act(obs)
    assert action.shape == (2,) and np.all(np.abs(action) <= 1.0)
    env.close()


def test_train_py_rl_with_several_envs_steps_them_in_subprocesses(tmp_path, monkeypatch):
    import json

    from stable_baselines3.common import vec_env

    import train

    made = []
    original = vec_env.SubprocVecEnv.__init__

    def spy(self, env_fns, start_method=None):
        made.append((len(env_fns), start_method))
        original(self, env_fns, start_method=start_method)

    monkeypatch.setattr(vec_env.SubprocVecEnv, "__init__", spy)
    model = tmp_path / "rl_ppo.zip"
    assert train.main(["rl", "--algo", "ppo", "--steps", "256", "--envs", "2", "--eval-every", "100000",
                       "--out", str(tmp_path / "run"), "--model", str(model), "--episode-seconds", "5",
                       "--device", "cpu"]) == 0
    assert made == [(2, "forkserver")] or made == [(2, "spawn")]
    record = json.loads(model.with_suffix(".json").read_text())
    assert record["envs"] == 2 and record["device"] == "cpu"


def test_rl_driver_without_a_model_is_one_clear_error(tmp_path):
    from towndrive.agent.drivers import make_driver

    with pytest.raises(FileNotFoundError, match="train one with: python train.py rl"):
        make_driver("rl", model=tmp_path / "none.zip")


class _ScriptedEnv:
    """A stand-in for Drive-v0 that replays given speeds and infractions (the wrapper only reads those)."""

    def __new__(cls, speeds, infractions):
        import gymnasium as gym

        class Scripted(gym.Env):
            observation_space = gym.spaces.Dict({"speed": gym.spaces.Box(0.0, 50.0, (1,), np.float32)})
            action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

            def __init__(self):
                self.k = 0

            def reset(self, *, seed=None, options=None):
                self.k = 0
                return {"speed": np.zeros(1, np.float32)}, {}

            def step(self, action):
                obs = {"speed": np.array([speeds[self.k]], np.float32)}
                info = {"infractions": [{"kind": kind} for kind in infractions[self.k]]}
                self.k += 1
                return obs, 1.0, False, False, info

        return Scripted()


def test_shaping_charges_speeding_and_ends_the_episode_on_a_red_light():
    from towndrive.agent.training.rl_shaping import ShapingConfig, TrafficRulesShaping

    cfg = ShapingConfig(speed_limit_mps=10.0, overspeed_penalty=0.02, red_light_penalty=-10.0)
    env = TrafficRulesShaping(_ScriptedEnv([9.0, 15.0, 9.0], [[], ["wrong_way"], ["red_light"]]), cfg)
    env.reset()
    assert env.step(np.zeros(2))[1:3] == (1.0, False)  # under the limit: the reward is untouched
    reward, terminated = env.step(np.zeros(2))[1:3]
    assert reward == pytest.approx(1.0 - 0.02 * 5.0) and not terminated
    reward, terminated = env.step(np.zeros(2))[1:3]
    assert reward == pytest.approx(1.0 - 10.0) and terminated


def test_train_py_rl_continues_from_a_saved_policy(tmp_path):
    import json

    import train

    common = ["--algo", "ppo", "--steps", "512", "--envs", "1", "--eval-every", "100000", "--episode-seconds", "5"]
    first = tmp_path / "first.zip"
    assert train.main(["rl", *common, "--no-shaping", "--out", str(tmp_path / "a"), "--model", str(first)]) == 0
    second = tmp_path / "second.zip"
    assert train.main(["rl", *common, "--init", str(first), "--out", str(tmp_path / "b"), "--model", str(second)]) == 0
    record = json.loads(second.with_suffix(".json").read_text())
    assert record["init"] == str(first) and record["shaping"] is True
    with pytest.raises(SystemExit, match="no saved policy"):
        train.main(["rl", *common, "--init", str(tmp_path / "none.zip"), "--out", str(tmp_path / "c")])
