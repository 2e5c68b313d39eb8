"""Dead reckoning (``agent.decision.odometry``): the approach heading a commanded turn is judged from."""

from __future__ import annotations

import math

import pytest

from towndrive.agent.decision.odometry import Odometry

DT = 0.05


def test_a_car_that_turned_a_little_before_the_line_keeps_its_approach_heading_as_it_stops_and_waits() -> None:
    """Turning left is commanded; the car steers left in the last metres before the stop line and its wheels come
    straight as it stops: it still faces its light at that angle, so the approach heading must not jump to where the
    car now points. Driving on with straight wheels, it does at once (as with no turn commanded)."""
    odo = Odometry()
    for _ in range(40):  # 2 s at 2 m/s, steering left
        odo.advance(2.0, -0.3, 1, DT)
    turned = odo.turned
    assert turned < math.radians(-5.0)
    for v in (0.9, 0.6, 0.3, 0.0, 0.0):  # stopping with the wheels straight, then standing
        odo.advance(v, 0.0, 1, DT)
    assert odo.turned == pytest.approx(turned, abs=1e-9)
    odo.advance(2.0, 0.0, 1, DT)
    assert odo.turned == 0.0
