"""The ``rl`` driver: a stable-baselines3 policy trained by ``train.py rl`` on the state observation.

The state vector comes from ground truth (``agent.rl_features``), so this driver is privileged, like
the autopilot; it is the RL row of the comparison table, not a camera-only driver.

The ``.zip`` is read without unpickling anything: stable-baselines3's own ``load`` deserialises the spaces,
schedules and policy class the file names with cloudpickle (code from the file). ``load_policy`` instead reads
only the tensors (``load_from_zip_file(load_data=False)``, which uses ``torch.load(weights_only=True)``) and the
plain JSON ``policy_kwargs``, and builds the policy itself for the known observation and action spaces.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from towndrive.agent.rl_features import StateFeatures
from towndrive.agent.shipped import RL_POLICY

if TYPE_CHECKING:
    from towndrive.envs.drive_env import DriveEnv

DEFAULT_MODEL = RL_POLICY


class RLDriver:
    name = "rl"
    privileged = True

    def __init__(self, model: str | Path = DEFAULT_MODEL) -> None:
        self.policy = load_policy(Path(model))
        self.state = StateFeatures()
        self.last_action = np.zeros(2, np.float32)

    def reset(self, env: DriveEnv) -> None:
        self.state.reset(env)
        self.last_action = np.zeros(2, np.float32)

    def act(self, observation: dict[str, Any]) -> np.ndarray:
        action, _ = self.policy.predict(self.state(self.last_action), deterministic=True)
        self.last_action = np.clip(np.asarray(action, np.float32).reshape(2), -1.0, 1.0)
        return self.last_action


def load_policy(path: Path) -> Any:
    """The MLP policy of a stable-baselines3 PPO or SAC ``.zip`` (SAC when "sac" is in the file name) on the
    24 state features, loaded as weights and plain data only (see the module docstring); errors name the file."""
    import json
    import zipfile

    import gymnasium as gym
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.save_util import load_from_zip_file

    from towndrive.agent.rl_features import N_FEATURES

    if not path.is_file():
        raise FileNotFoundError(f"RL model {path} not found; train one with: python train.py rl")
    algo = SAC if "sac" in path.stem else PPO
    try:
        with zipfile.ZipFile(path) as archive:
            data = json.loads(archive.read("data")) if "data" in archive.namelist() else {}
        kwargs = data.get("policy_kwargs", {})
        if not isinstance(kwargs, dict) or ":serialized:" in json.dumps(kwargs):
            raise ValueError("its policy_kwargs hold pickled objects, which are never loaded")
        _, params, _ = load_from_zip_file(path, load_data=False, device="cpu")
        policy = algo.policy_aliases["MlpPolicy"](gym.spaces.Box(-5.0, 5.0, (N_FEATURES,), np.float32),
                                                  gym.spaces.Box(-1.0, 1.0, (2,), np.float32),
                                                  lambda _: 0.0, **kwargs)
        policy.load_state_dict(params["policy"])
    except (ValueError, KeyError, TypeError, OSError, RuntimeError, zipfile.BadZipFile, UnicodeDecodeError) as exc:
        text = str(exc).strip().splitlines()
        raise ValueError(f"{path} is not a stable-baselines3 {algo.__name__} state policy this project can load "
                         f"({text[0][:160] if text else type(exc).__name__}).") from None
    return policy.eval()
