"""The state observation of the RL baseline: what the autopilot plans with, as one small vector.

``StateObservation`` wraps ``Drive-v0`` (camera off) and replaces the observation with 24 numbers read
from the world's ground truth, so a policy trained on it is *privileged*, like the autopilot:

  0      lateral offset from the planned lane's centre line / 2 m (positive: right of it)
  1      heading error against the lane, rad
  2-4    heading of the lane 5, 10, 20 m ahead relative to the car, rad (curves and turns)
  5-7    lateral position of the lane centre 5, 10, 20 m ahead in the car's frame / 5 m
  8      speed / 10 m/s
  9-12   route command one-hot: follow, left, right, straight
  13-16  next light one-hot: green, yellow, red, none
  17     distance to the next stop line / 50 m (1 if none or farther)
  18     distance to where the car must stop (red, yellow it can stop for, waiting to turn left) / 50 m, 1 if none
  19     gap to the nearest vehicle or pedestrian on the car's path / 50 m (1 if none)
  20     closing speed on it / 10 m/s
  21-22  the previous action (steer, throttle_brake)
  23     route completion (0..1)

The lane plan (which lane, lane changes before turns) is the autopilot's, so the policy learns control,
not route planning.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np

from towndrive.agent.autopilot import Autopilot
from towndrive.envs.driver_context import DriverContext
from towndrive.sim.objects import LightState
from towndrive.sim.traffic import crosswalk_gap, path_gap
from towndrive.sim.world import EGO_ID

N_FEATURES = 24
PREVIEW_M = (5.0, 10.0, 20.0)


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


class StateFeatures:
    """Computes the state vector for a ``DriveEnv`` (used by the wrapper for training and by the ``rl`` driver)."""

    def __init__(self) -> None:
        self.planner = Autopilot()
        self.env: Any = None

    def reset(self, env: Any) -> None:
        self.env = DriverContext.of(env, privileged=True).env
        self.planner.reset(env)

    def __call__(self, last_action: np.ndarray) -> np.ndarray:
        world = self.env.world
        ego = world.ego
        path, s0 = self.planner.route_path(world)
        lane0 = path[0][0]
        _, lateral = lane0.local_coordinates(ego.position)
        f = np.zeros(N_FEATURES, np.float32)
        f[0] = lateral / 2.0
        f[1] = _wrap(lane0.heading_at(max(s0, 0.0)) - ego.heading)
        c, s = math.cos(ego.heading), math.sin(ego.heading)
        for k, ahead in enumerate(PREVIEW_M):
            lane, local = _lane_at(path, s0 + ahead)
            f[2 + k] = _wrap(lane.heading_at(local) - ego.heading)
            dx, dy = lane.position(local, 0.0) - ego.position
            f[5 + k] = (-s * dx + c * dy) / 5.0  # y is to the right in the map frame
        f[8] = ego.speed / 10.0
        f[9 + int(world.command())] = 1.0
        light = world.next_light()
        if light is None:
            f[16], f[17] = 1.0, 1.0
        else:
            f[13 + {LightState.GREEN: 0, LightState.YELLOW: 1, LightState.RED: 2}[LightState(light.state)]] = 1.0
            f[17] = min(max(light.distance_m, 0.0) / 50.0, 1.0)
        agents = world.agents()
        stop = self.planner.stop_gap(world, world.next_control(), agents)
        f[18] = 1.0 if stop is None else min(stop / 50.0, 1.0)
        lookahead = 50.0
        gap, lead_speed = path_gap(path, s0, ego.LENGTH / 2, agents, EGO_ID, ego.position, lookahead)
        zebra = crosswalk_gap(world.town, path, self.planner._path_lanes, s0, ego.LENGTH / 2, agents, lookahead)
        if zebra is not None and (gap is None or zebra < gap):
            gap, lead_speed = zebra, 0.0
        f[19] = 1.0 if gap is None else min(gap / 50.0, 1.0)
        f[20] = 0.0 if gap is None else (ego.speed - lead_speed) / 10.0
        f[21:23] = last_action
        f[23] = world.route_completion
        return np.clip(f, -5.0, 5.0)


def _lane_at(path: list, s: float) -> tuple[Any, float]:
    """The lane of the path at path coordinate ``s`` and the coordinate on it."""
    for lane, offset in path:
        if s <= offset + lane.length:
            return lane, max(s - offset, 0.0)
    lane, offset = path[-1]
    return lane, lane.length


class StateObservation(gym.Wrapper):
    """Drive-v0 with the state vector above as its observation (see the module docstring)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.observation_space = gym.spaces.Box(-5.0, 5.0, (N_FEATURES,), np.float32)
        self.state = StateFeatures()
        self._last_action = np.zeros(2, np.float32)

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict]:
        _, info = self.env.reset(**kwargs)
        self.state.reset(self.env.unwrapped)
        self._last_action = np.zeros(2, np.float32)
        return self.state(self._last_action), info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        self._last_action = np.clip(np.asarray(action, np.float32).reshape(2), -1.0, 1.0)
        _, reward, terminated, truncated, info = self.env.step(self._last_action)
        return self.state(self._last_action), reward, terminated, truncated, info
