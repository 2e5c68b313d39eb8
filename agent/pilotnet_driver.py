"""The ``pilotnet`` driver: PilotNet steers from the camera frame; a PID holds a constant target speed.

It sees only what a real car has: the camera frame, its own speed and the route command (the
conditional model picks its branch with it). Its steering changes at most as fast as the autopilot's
(``STEER_RATE_PER_S``), the rate the labels were recorded with; 0 turns the limit off. The speed is
the seed's assumption: constant, configurable, with an optional slow-down while the network asks for a
sharp turn. Inference runs through ONNX Runtime
(``backend="onnx"``, the default) or torch; both load the same shipped model.

A model file the user names is the only file opened: an ``.onnx`` runs on ONNX Runtime and carries what the
runtime needs besides the weights itself (the ``command`` input says the model is conditional; the crop is in
its ``pilotnet_meta`` metadata, or the default crop every ``train.py`` export has used), a ``.pt`` runs on torch.
Only the shipped default (``DEFAULT_MODEL``) stands for its pair, ``pilotnet.pt`` and ``pilotnet.onnx``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from towndrive.agent.decision.pid import PID, STEER_RATE_PER_S
from towndrive.agent.perception.pilotnet import DEFAULT_MODEL, PilotNetModel
from towndrive.envs.driver_context import DriverContext
from towndrive.sim.spec import VEHICLE

if TYPE_CHECKING:
    pass



class PilotNetDriver:
    """PilotNet steering plus a PID speed loop (see module docstring)."""

    name = "pilotnet"
    privileged = False

    def __init__(self, model: str | Path = DEFAULT_MODEL, backend: str = "onnx", target_speed_mps: float = 7.0,
                 turn_slowdown: float = 0.5, steer_rate_per_s: float = STEER_RATE_PER_S, threads: int = 1) -> None:
        self.net = PilotNetModel(model, backend, threads)
        self.target_speed = target_speed_mps
        self.turn_slowdown = turn_slowdown
        self.steer_rate = steer_rate_per_s
        self.speed_pid = PID(0.6, 0.1, 0.0)
        self.dt = 0.05
        self.last_steer = 0.0

    def reset(self, context: DriverContext | Any) -> None:
        self.dt = DriverContext.of(context).dt_s
        self.speed_pid.reset()
        self.last_steer = 0.0

    def target_speed_for(self, steer: float) -> float:
        """The cruise speed, lowered while the network steers hard (``turn_slowdown`` 0: always constant)."""
        return self.target_speed / (1.0 + self.turn_slowdown * 3.0 * abs(steer))

    def act(self, observation: dict[str, Any]) -> np.ndarray:
        steer = float(np.clip(self.net.steer(observation["image"], int(observation["command"])), -1.0, 1.0))
        if self.steer_rate > 0:  # the expert's gentle hands: frame-to-frame jitter of the network is not steering
            step = self.steer_rate * self.dt
            steer = min(self.last_steer + step, max(self.last_steer - step, steer))
        self.last_steer = steer
        speed = float(observation["speed"][0])
        accel = self.speed_pid(self.target_speed_for(steer) - speed, self.dt) * VEHICLE.max_accel_mps2
        throttle = accel / VEHICLE.max_accel_mps2 if accel >= 0 else accel / VEHICLE.max_brake_mps2
        return np.array([steer, float(np.clip(throttle, -1.0, 1.0))], np.float32)
