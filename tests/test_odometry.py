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


def test_the_road_turned_into_is_measured_afresh_once_the_turn_is_over() -> None:
    """After a right turn the approach road's heading is behind the car: kept, it placed the next junction's arc
    and straight hold 90 degrees off (the car drove straight across where it had to turn, and the hold steered
    hard against a heading it did not have). ``leave_road`` forgets it; the first sure lane lined up with the car
    measures the new road outright, even while the junction's lights are still ignored."""
    import numpy as np

    from towndrive.agent.decision.controller import ControllerConfig
    from towndrive.agent.decision.stop_line_track import StopLineTrack

    line = StopLineTrack(ControllerConfig())
    odo = Odometry()
    odo.measure_road(np.array([0.0, 0.0, 0.0]), 0.9, line, -1.0)  # along the approach road, centred
    assert odo.road_yaw == pytest.approx(0.0)
    odo.yaw = math.radians(90.0)  # the turn right, dead-reckoned
    line.ignore_light_m = 10.0  # still within the junction's window
    lined_up = np.array([0.0, math.tan(math.radians(2.0)), 0.3])  # 2 degrees right of the car's axis
    odo.measure_road(lined_up, 0.9, line, -1.0)
    assert odo.road_yaw == pytest.approx(0.0)  # inside a junction the approach road is kept ...
    odo.leave_road()
    assert odo.road_yaw is None
    odo.measure_road(np.array([0.0, math.tan(math.radians(20.0)), 0.3]), 0.9, line, -1.0)  # not lined up: not yet
    odo.measure_road(lined_up, 0.3, line, -1.0)  # unsure: not yet
    assert odo.road_yaw is None
    odo.measure_road(lined_up, 0.9, line, -1.0)
    assert odo.road_yaw == pytest.approx(math.radians(92.0))
    assert odo.road_offset == pytest.approx(-0.3 + math.tan(math.radians(2.0)))
