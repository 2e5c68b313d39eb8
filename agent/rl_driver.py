"""The ``rl`` driver: a stable-baselines3 policy trained by ``train.py rl`` on the state observation.

The state vector comes from ground truth (``agent.rl_features``), so this driver is privileged, like
the autopilot; it is the RL row of the comparison table, not a camera-only driver.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from agent.drivers import register
from agent.rl_features import StateFeatures

if TYPE_CHECKING:
    from envs.drive_env import DriveEnv

DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "data" / "models" / "rl_ppo.zip"


@register("rl")
class RLDriver:
    name = "rl"
    privileged = True

    def __init__(self, model: str | Path = DEFAULT_MODEL) -> None:
        from stable_baselines3 import PPO, SAC

        path = Path(model)
        if not path.is_file():
            raise FileNotFoundError(f"RL model {path} not found; train one with: python train.py rl")
        algo = SAC if "sac" in path.stem else PPO
        try:
            self.policy = algo.load(path, device="cpu")
        except (ValueError, KeyError, OSError) as exc:
            raise ValueError(f"{path} is not a stable-baselines3 {algo.__name__} model ({exc}).") from exc
        self.state = StateFeatures()
        self.last_action = np.zeros(2, np.float32)

    def reset(self, env: DriveEnv) -> None:
        self.state.reset(env)
        self.last_action = np.zeros(2, np.float32)

    def act(self, observation: dict[str, Any]) -> np.ndarray:
        action, _ = self.policy.predict(self.state(self.last_action), deterministic=True)
        self.last_action = np.clip(np.asarray(action, np.float32).reshape(2), -1.0, 1.0)
        return self.last_action
