"""A tracked object's speeds come with their standard errors: a standing car's box jitters a pixel from frame to
frame, which far off reads as a metre or more of distance and a speed that is not there; the error says so."""

from __future__ import annotations

import numpy as np

from towndrive.agent.perception.box_geometry import BoxGeometry
from towndrive.agent.perception.classes import CLASSES
from towndrive.agent.perception.objects import ObjectEstimator, ObjectRules, slope
from towndrive.agent.perception.tracking import Track
from towndrive.sim.spec import CAMERA

DT = 0.05
CAR = CLASSES.index("car")


def test_slope_error_is_zero_on_a_line_and_grows_with_scatter() -> None:
    t = [k * DT for k in range(20)]
    rate, sd = slope(t, [3.0 - 2.0 * x for x in t])
    assert abs(rate + 2.0) < 1e-9 and sd < 1e-9
    rng = np.random.default_rng(0)
    noisy = [3.0 + float(e) for e in rng.normal(0.0, 1.0, len(t))]
    rate, sd = slope(t, noisy)
    assert 0.5 < sd < 2.5  # about 1 / sqrt(sum (t - mean)^2) = 1.3 for unit scatter over a second
    assert abs(rate) < 3.0 * sd


def _bottom_row(geometry: BoxGeometry, z_m: float) -> float:
    rows = np.arange(70.0, 150.0)  # below the horizon
    return float(rows[np.argmin(np.abs(geometry.birdseye.ground_z_of_row(rows) - z_m))])


def test_a_standing_far_car_whose_box_jitters_reads_a_speed_within_its_error() -> None:
    geometry = BoxGeometry(CAMERA)
    bottom = _bottom_row(geometry, 22.0)
    for seed in range(6):
        rng = np.random.default_rng(seed)
        est = ObjectEstimator(geometry, ObjectRules())
        for k in range(21):  # the car stands still; its box's bottom row flickers between two rows
            b = bottom + float(rng.integers(0, 2))
            objs = est.update([_track(np.array([230.0, b - 12.0, 254.0, b]))], k * DT, None, 0.0)
        (car,) = objs
        assert car.closing_speed_sd_mps > 0.3
        assert abs(car.closing_speed_mps) < 2.5 * car.closing_speed_sd_mps  # the "speed" is within the scatter
    est = ObjectEstimator(geometry, ObjectRules())
    for k in range(21):  # a car closing in at 4 m/s from 22 m: the same pixels, a speed well beyond its error
        b = _bottom_row(geometry, 22.0 - 4.0 * k * DT)
        objs = est.update([_track(np.array([230.0, b - 12.0, 254.0, b]))], k * DT, None, 0.0)
    (car,) = objs
    assert car.closing_speed_mps - 2.0 * car.closing_speed_sd_mps > 1.0


def _track(box: np.ndarray) -> Track:
    return Track(1, box, 10, 10, 0, CAR)
