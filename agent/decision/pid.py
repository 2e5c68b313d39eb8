"""A PID speed loop and the steering rate the expert's labels were recorded with, shared by the autopilot and the
camera-only PilotNet driver (which must not import the privileged autopilot)."""

from __future__ import annotations

from dataclasses import dataclass

STEER_RATE_PER_S = 1.5  # largest change of the steer command per second


@dataclass
class PID:
    """A textbook PID on one error signal, with a clamped integral (anti-windup)."""

    kp: float
    ki: float
    kd: float
    integral_limit: float = 2.0
    _integral: float = 0.0
    _last: float | None = None

    def reset(self) -> None:
        self._integral, self._last = 0.0, None

    def __call__(self, error: float, dt: float) -> float:
        self._integral = max(-self.integral_limit, min(self.integral_limit, self._integral + error * dt))
        derivative = 0.0 if self._last is None else (error - self._last) / dt
        self._last = error
        return self.kp * error + self.ki * self._integral + self.kd * derivative
