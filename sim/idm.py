"""The Intelligent Driver Model's acceleration law, shared by the simulator's traffic and the agent's controller.

Why a module of its own: the law is pure arithmetic, and the car's runtime code must not import the simulator's
traffic (and with it highway-env) to use it. ``sim.traffic.idm_acceleration`` gives it highway-env's constants.
"""

from __future__ import annotations

import math


def idm_acceleration(speed: float, target_speed: float, gap_m: float | None, closing_mps: float, a_max: float,
                     b: float, min_gap_m: float = 2.0, headway_s: float = 1.2, delta: float = 4.0) -> float:
    """Intelligent Driver Model with a bumper-to-bumper gap."""
    acc = a_max * (1.0 - (max(speed, 0.0) / max(target_speed, 0.1)) ** delta)
    if gap_m is not None:
        desired = min_gap_m + speed * headway_s + speed * closing_mps / (2.0 * math.sqrt(a_max * b))
        acc -= a_max * (max(desired, min_gap_m) / max(gap_m, 0.1)) ** 2
    return acc
