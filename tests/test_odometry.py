"""Dead reckoning (``agent.decision.odometry``): the approach heading a commanded turn is judged from."""

from __future__ import annotations

import math

import pytest

from towndrive.agent.decision.odometry import Odometry

DT = 0.05


def test_a_car_that_turned_a_little_before_the_line_keeps_its_approach_heading_while_it_waits() -> None:
    """Turning left is commanded; the car steers left for a few metres before the stop line, then stands there with
    its wheels straight: it still faces its light at that angle, so the approach heading must not jump to where the
    car now points. Driving straight on, it becomes the approach heading within metres; with no turn commanded, at
    once."""
    odo = Odometry()
    for _ in range(40):  # 2 s at 2 m/s, steering left
        odo.advance(2.0, -0.3, 1, DT)
    turned = odo.turned
    assert turned < math.radians(-5.0)
    for _ in range(100):  # 5 s standing with the wheels straight
        odo.advance(0.0, 0.0, 1, DT)
    assert odo.turned == pytest.approx(turned)
    for _ in range(100):  # 10 m straight on
        odo.advance(2.0, 0.0, 1, DT)
    assert abs(odo.turned) < 0.05 * abs(turned)
    odo.reset()
    for _ in range(40):
        odo.advance(2.0, -0.3, 0, DT)  # no turn commanded: the lane bends, the approach heading follows
    assert odo.turned == 0.0
