"""The ego car: highway-env's kinematic bicycle model driven by ``[steer, throttle_brake]``."""

from __future__ import annotations

import numpy as np
from highway_env.road.road import Road
from highway_env.vehicle.kinematics import Vehicle

from towndrive.sim.spec import VEHICLE


class EgoVehicle(Vehicle):
    """Bicycle-model car. Steer maps to the wheel-angle limit; throttle_brake > 0 accelerates up to
    ``MAX_ACCEL_MPS2``, < 0 brakes up to ``MAX_BRAKE_MPS2``. It never reverses."""

    LENGTH = VEHICLE.length_m  # the car's numbers live in sim.spec (the agent dead-reckons with them too)
    WIDTH = VEHICLE.width_m
    HEIGHT = VEHICLE.height_m
    MAX_STEER_RAD = VEHICLE.max_steer_rad
    MAX_ACCEL_MPS2 = VEHICLE.max_accel_mps2
    MAX_BRAKE_MPS2 = VEHICLE.max_brake_mps2
    DRAG_MPS2 = VEHICLE.drag_mps2
    MAX_SPEED = VEHICLE.max_speed_mps

    def __init__(self, road: Road, position: np.ndarray, heading: float, speed: float = 0.0) -> None:
        super().__init__(road, position, heading, speed)

    def on_state_update(self) -> None:
        """The world locates the ego on the town's lanes itself (spatial hash), so nothing here."""

    def apply(self, action: np.ndarray) -> None:
        a = np.asarray(action, dtype=np.float64).reshape(2)
        steer, throttle_brake = min(1.0, max(-1.0, float(a[0]))), min(1.0, max(-1.0, float(a[1])))
        accel = throttle_brake * (self.MAX_ACCEL_MPS2 if throttle_brake >= 0 else self.MAX_BRAKE_MPS2)
        if self.speed > 0:
            accel -= self.DRAG_MPS2
        self.action = {"steering": float(steer * self.MAX_STEER_RAD), "acceleration": float(accel)}

    def step(self, dt: float) -> None:
        super().step(dt)
        self.speed = min(self.MAX_SPEED, max(0.0, float(self.speed)))
