"""Reward shaping for the RL baseline: the town's rules that Drive-v0's plain reward leaves cheap.

Why: Drive-v0 pays route progress (metres / 10) and charges -5 once for a red light and nothing for
speed. Within a fixed episode time, waiting 20 s at a red light costs more progress than the -5 it
saves, and driving twice the town's speed earns twice the reward, so a first PPO run on the plain
reward learned to drive at 19 m/s through red lights (route completion 99%, 13 red lights in 10
held-out routes). This wrapper, used only for training, makes those choices lose:

- speeding: ``overspeed_penalty`` per step and per m/s above ``speed_limit_mps`` (progress pays
  0.005 per step and per m/s at 20 Hz, so any penalty above that makes speeding a net loss);
- a red light run ends the episode with ``red_light_penalty``, as collisions do.

Evaluation always uses the environment's own reward and metrics; the wrapper never changes what the
policy observes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np


@dataclass(frozen=True)
class ShapingConfig:
    speed_limit_mps: float = 11.0  # the fastest NPCs drive 11 m/s (about 40 km/h)
    overspeed_penalty: float = 0.02  # per step and per m/s over the limit
    red_light_penalty: float = -10.0  # and the episode ends


class TrafficRulesShaping(gym.Wrapper):
    """Adds the speed-limit and red-light terms to Drive-v0's reward (see the module docstring)."""

    def __init__(self, env: gym.Env, config: ShapingConfig | None = None) -> None:
        super().__init__(env)
        self.config = config or ShapingConfig()

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        speed = float(np.asarray(obs["speed"]).reshape(-1)[0])
        reward = float(reward) - self.config.overspeed_penalty * max(0.0, speed - self.config.speed_limit_mps)
        if any(inf["kind"] == "red_light" for inf in info.get("infractions", [])):
            reward += self.config.red_light_penalty
            terminated = True
        return obs, reward, terminated, truncated, info
