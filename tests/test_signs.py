"""Road signs on synthetic perception: a stop sign's full stop and go, a yield line, speed limits and the
street's default, the bend ahead, and the detector's classes with and without the sign channels."""

from __future__ import annotations

import math

import numpy as np
import pytest

from towndrive.agent.decision.controller import Controller, ControllerConfig, PerceivedObject, Scene
from towndrive.agent.decision.signs import lanes_each_way
from towndrive.agent.perception.box_geometry import BoxGeometry
from towndrive.agent.perception.classes import CLASSES, LIGHT_CLASSES, SIGN_CLASSES, classes_of_model
from towndrive.agent.perception.detections import Detection
from towndrive.agent.perception.detector import postprocess
from towndrive.agent.perception.lanes import LaneLine, LaneResult
from towndrive.agent.perception.signs import SignLocator, SignSeen
from towndrive.sim.spec import CAMERA, CURVE_LATERAL_ACCEL_MPS2, KMH, ROAD, STOP_SPEED_MPS

DT = 0.05
CFG = ControllerConfig()
CAM = CFG.camera_to_front_m


def sign_at(kind: str, camera_to_sign: float, limit: int = 0) -> list[SignSeen]:
    """A sign as the reader reports it, seen only between 5 and 35 m (the camera loses it beside the car)."""
    return [SignSeen(kind, camera_to_sign, 4.0, limit)] if 5.0 <= camera_to_sign <= 35.0 else []


def bar(camera_to_bar: float) -> float | None:
    return camera_to_bar if 3.0 <= camera_to_bar <= 20.0 else None


def crossing_car(t: float, at: float, until: float) -> list[PerceivedObject]:
    """A car crossing from left to right 6 m beyond the line between ``at`` and ``until`` s."""
    if not at <= t <= until:
        return []
    x = -15.0 + 6.0 * (t - at)
    return [PerceivedObject(9, "car", 12.0, x - 2.3, x + 2.3, closing_speed_mps=0.0, lateral_speed_mps=6.0)]


def drive_sign(kind: str, line_m: float, seconds: float, objects=lambda t, s: [], v0: float = 8.0,
               ctrl: Controller | None = None):
    """The car drives towards a ``kind`` sign standing 2.5 m before a stop line ``line_m`` ahead of its bumper."""
    ctrl = ctrl or Controller(CFG)
    v, s, out = v0, 0.0, []
    for k in range(int(seconds / DT)):
        t = k * DT
        to_line = line_m - s
        scene = Scene(v, objects=objects(t, s), stop_line_m=bar(to_line + CAM),
                      signs=sign_at(kind, to_line + CAM - ROAD.sign_before_stop_line_m))
        d = ctrl.step(scene, 0.0, DT)
        v = max(0.0, v + d.accel_mps2 * DT)
        s += v * DT
        out.append((t, line_m - s, v, d))
    return out


def test_stop_sign_full_stop_within_2_m_then_goes_when_clear() -> None:
    run = drive_sign("stop", 45.0, 30.0)
    stands = [(t, gap) for t, gap, v, _ in run if v < STOP_SPEED_MPS and gap > -1.0]
    assert stands, "the car never made a full stop"
    t_stop, gap = stands[0]
    assert 0.0 <= gap <= 2.0, gap
    reasons = {d.reason for t, _, _, d in run if t < t_stop}
    assert any(r.startswith("stop sign: full stop") for r in reasons)
    # Then it drives on through the line, and the sign no longer holds it.
    assert run[-1][1] < -10.0 and run[-1][2] > 3.0
    assert run[-1][3].reason == "cruise"


def test_stop_sign_waits_for_a_vehicle_with_priority() -> None:
    # The car reaches the line after about 8 s; a car crosses 6 m beyond it from 7 s to 12 s.
    run = drive_sign("stop", 45.0, 30.0, objects=lambda t, s: crossing_car(t, 7.0, 12.0))
    crossed = next(t for t, gap, _, _ in run if gap < -1.0)
    assert crossed > 12.0
    assert any("waiting" in d.reason and "priority" in d.reason for _, _, _, d in run)


def test_a_standing_car_whose_readings_scatter_has_no_priority() -> None:
    # A car standing on the street we turn into, 20 m beyond the line and 6.5 m right: its box jitters a pixel, so
    # its fitted speed reads 1.2 m/s with a standard error of 0.7. That is no traffic to wait for; the same speed
    # read cleanly is.
    def standing(sd: float):
        def objects(t: float, s: float) -> list[PerceivedObject]:
            z = 45.0 - s + CAM + 20.0
            return [PerceivedObject(3, "car", z, 5.5, 7.5, closing_speed_mps=-1.2, lateral_speed_mps=0.2,
                                    closing_speed_sd_mps=sd, lateral_speed_sd_mps=0.1)]
        return objects

    scattered = drive_sign("stop", 45.0, 20.0, objects=standing(0.7))
    assert next(t for t, gap, _, _ in scattered if gap < -1.0) < 15.0
    clean = drive_sign("stop", 45.0, 20.0, objects=standing(0.05))
    assert all(gap > -1.0 for _, gap, _, _ in clean)
    assert any("with priority" in d.reason for _, _, _, d in clean)


def test_stop_sign_waits_for_a_person_on_the_crossing() -> None:
    def person(t: float, s: float) -> list[PerceivedObject]:
        if t > 14.0:
            return []
        to_line = 45.0 - s
        z = to_line + CAM + 3.0  # on the zebra beyond the line, in the oncoming lanes
        return [PerceivedObject(4, "pedestrian", z, -4.0, -3.5, closing_speed_mps=0.0, lateral_speed_mps=0.0)]

    run = drive_sign("stop", 45.0, 30.0, objects=person)
    crossed = next(t for t, gap, _, _ in run if gap < -1.0)
    assert crossed > 14.0
    assert any("on the crossing" in d.reason for _, _, _, d in run)


def test_yield_slows_and_goes_without_stopping_when_clear() -> None:
    run = drive_sign("yield", 45.0, 20.0)
    at_line = [v for _, gap, v, _ in run if 0.0 <= gap <= 1.5]
    assert at_line and max(at_line) <= 4.5 and min(at_line) > 2.0  # slowed to look, did not stop
    assert any(d.reason.startswith("yield") for _, _, _, d in run)
    assert run[-1][1] < -10.0


def test_yield_stops_for_crossing_traffic() -> None:
    run = drive_sign("yield", 45.0, 30.0, objects=lambda t, s: crossing_car(t, 5.0, 14.0))
    crossed = next(t for t, gap, _, _ in run if gap < -1.0)
    assert crossed > 12.0  # the crossing car is farther than priority_near_m from then on
    assert min(v for t, gap, v, _ in run if gap > 0) < 0.5


def test_limit_30_holds_until_another_limit_is_seen() -> None:
    ctrl = Controller(ControllerConfig(speed_limit_mps=15.0))  # cruise above both limits, so they govern
    for _ in range(3):
        d = ctrl.step(Scene(10.0, signs=[SignSeen("limit", 20.0, 4.0, 30)]), 0.0, DT)
    for _ in range(40):  # the sign is long gone
        d = ctrl.step(Scene(10.0), 0.0, DT)
        assert d.target_speed_mps <= 30 * KMH + 1e-9
    assert "limit 30" in d.reason
    for _ in range(3):
        d = ctrl.step(Scene(8.0, signs=[SignSeen("limit", 20.0, 4.0, 50)]), 0.0, DT)
    assert d.target_speed_mps == pytest.approx(min(15.0, 50 * KMH))


def test_a_stop_sign_seen_while_turning_through_a_junction_is_not_ours() -> None:
    # Mid-turn the camera sweeps across the junction's other arms: a stop sign that stands where ours would, with
    # the car turned 12 degrees from its lane, is no stop for it; the same plate seen lined up is.
    plate = [SignSeen("stop", 19.0, 9.0)]
    turning = Controller(CFG)
    for _ in range(10):
        d = turning.step(Scene(3.0, signs=plate, turned_rad=math.radians(-12.0)), 0.0, DT)
    assert turning.signs.control is None and not d.reason.startswith("stop sign")
    lined_up = Controller(CFG)
    for _ in range(10):
        d = lined_up.step(Scene(3.0, signs=plate, turned_rad=math.radians(-2.0)), 0.0, DT)
    assert lined_up.signs.control == "stop" and d.reason.startswith("stop sign")


def test_one_frame_of_a_sign_is_not_believed() -> None:
    ctrl = Controller(ControllerConfig(speed_limit_mps=15.0))
    ctrl.step(Scene(10.0, signs=[SignSeen("limit", 20.0, 4.0, 30)], lanes_each_way=2), 0.0, DT)
    d = ctrl.step(Scene(10.0), 0.0, DT)
    assert d.target_speed_mps > 30 * KMH


def lane(color_left: str, style_left: str, color_right: str, style_right: str) -> LaneResult:
    left = LaneLine(np.array([0.0, 0.0, -1.75]), (3.0, 30.0), 1.0, 500, color_left, style_left)
    right = LaneLine(np.array([0.0, 0.0, 1.75]), (3.0, 30.0), 1.0, 500, color_right, style_right)
    return LaneResult(left, right, 0.0, math.inf, 0.0, 3.5, 1.0, True)


def test_default_limit_by_the_street_the_lane_lines_tell() -> None:
    assert lanes_each_way(lane("yellow", "solid", "white", "solid")) == 1
    assert lanes_each_way(lane("yellow", "solid", "white", "dashed")) == 2
    assert lanes_each_way(lane("white", "dashed", "white", "solid")) == 2
    assert lanes_each_way(lane("white", "unknown", "white", "unknown")) is None
    ctrl = Controller(ControllerConfig(speed_limit_mps=20.0))
    d = ctrl.step(Scene(10.0), 0.0, DT)
    assert d.target_speed_mps == pytest.approx(ROAD.single_lane_limit_kmh * KMH)  # nothing known: the lower
    d = ctrl.step(Scene(10.0, lanes_each_way=2), 0.0, DT)
    assert d.target_speed_mps == pytest.approx(ROAD.multi_lane_limit_kmh * KMH)
    d = ctrl.step(Scene(10.0), 0.0, DT)  # the kind measured last holds
    assert d.target_speed_mps == pytest.approx(ROAD.multi_lane_limit_kmh * KMH)
    d = ctrl.step(Scene(10.0, lanes_each_way=1), 0.0, DT)
    assert d.target_speed_mps == pytest.approx(ROAD.single_lane_limit_kmh * KMH)


def test_a_few_frames_of_a_line_ending_ahead_do_not_change_the_street() -> None:
    """Near a stop bar the solid edge line ends within the view and reads as dashed for a few frames: the street
    stays the single-lane one most readings told, until a second's worth of readings tell otherwise."""
    ctrl = Controller(ControllerConfig(speed_limit_mps=20.0))
    for _ in range(40):
        ctrl.step(Scene(10.0, lanes_each_way=1), 0.0, DT)
    for kind in (2, None, 2, None, 2):
        d = ctrl.step(Scene(10.0, lanes_each_way=kind), 0.0, DT)
    assert ctrl.signs.lanes_each_way == 1
    assert d.target_speed_mps == pytest.approx(ROAD.single_lane_limit_kmh * KMH)
    for _ in range(ctrl.signs.rules.street_readings):
        d = ctrl.step(Scene(10.0, lanes_each_way=2), 0.0, DT)
    assert ctrl.signs.lanes_each_way == 2  # a street that does have two lanes is told once it is seen a while
    assert d.target_speed_mps == pytest.approx(ROAD.multi_lane_limit_kmh * KMH)


def test_slows_for_a_bend_seen_ahead_before_steering_into_it() -> None:
    radius = 22.0  # the town's corner bends
    ctrl = Controller(CFG)
    centre = np.array([1.0 / (2 * radius), 0.0, 0.0])
    for _ in range(40):
        d = ctrl.step(Scene(8.0, lane_centre=centre, lane_range_m=20.0), 0.0, DT)
    assert d.reason.startswith("bend ahead")
    assert d.accel_mps2 < 0.0
    v_bend = math.sqrt(CURVE_LATERAL_ACCEL_MPS2 * radius)
    assert ctrl._bend_cap(Scene(8.0, lane_centre=centre, lane_range_m=20.0), DT) == pytest.approx(v_bend, rel=0.02)
    # A straight lane, or a fit too short to tell a bend, does not slow the car.
    ctrl = Controller(CFG)
    for _ in range(40):
        d = ctrl.step(Scene(8.0, lane_centre=np.array([0.0, 0.0, 0.0])), 0.0, DT)
        e = Controller(CFG).step(Scene(8.0, lane_centre=centre, lane_range_m=8.0), 0.0, DT)
    assert d.reason == "cruise" and e.reason == "cruise"


def test_sign_reader_measures_a_stop_sign_on_our_side() -> None:
    geometry = BoxGeometry(CAMERA)
    reader = SignLocator(geometry)
    f, cx = geometry.f, float(geometry.k[0, 2])
    z, x, size_px = 15.0, 4.0, geometry.f * ROAD.sign_plate_size_m / 15.0
    u = cx + x * f / z
    box = (u - size_px / 2, 40.0, u + size_px / 2, 40.0 + size_px)
    stop = CLASSES.index("stop_sign")
    seen = reader.read([Detection(box, stop, 0.9)])
    assert len(seen) == 1 and seen[0].kind == "stop"
    assert seen[0].distance_m == pytest.approx(z, rel=0.01) and seen[0].lateral_m == pytest.approx(x, rel=0.01)
    u_left = cx - x * f / z  # by the oncoming lanes: not ours
    edge_on = (u - 1.0, 40.0, u + 1.0, 40.0 + size_px)  # facing the cross street
    assert reader.read([Detection((u_left - size_px / 2, 40.0, u_left + size_px / 2, 40.0 + size_px), stop, 0.9),
                        Detection(edge_on, stop, 0.9)]) == []
    limit = reader.read([Detection(box, CLASSES.index("speed_limit_30"), 0.9)])
    assert limit[0].kind == "limit" and limit[0].limit_kmh == 30


def test_classes_and_a_detector_with_six_or_ten_class_channels() -> None:
    assert CLASSES[:6] == ("car", "truck", "pedestrian", "light_red", "light_yellow", "light_green")
    assert SIGN_CLASSES == ("stop_sign", "yield_sign", "speed_limit_30", "speed_limit_50")
    assert LIGHT_CLASSES == ("light_red", "light_yellow", "light_green")
    assert classes_of_model(6) == CLASSES[:6] and classes_of_model(10) == CLASSES
    with pytest.raises(ValueError):
        classes_of_model(11)
    for channels, best in ((6, 2), (10, 6)):
        pred = np.zeros((3, 5 + channels), np.float32)
        pred[:, :4] = [[10, 10, 30, 50], [100, 20, 110, 30], [200, 20, 210, 30]]
        pred[:, 4] = 0.9
        pred[0, 5 + 2] = 0.9  # a pedestrian
        pred[1, 5 + best] = 0.9  # a pedestrian (6) or a stop sign (10)
        pred[2, 5 + 3] = 0.9  # a red light
        names = sorted(d.name for d in postprocess(pred, 0.3))
        assert names == sorted(["pedestrian", CLASSES[best], "light_red"])
