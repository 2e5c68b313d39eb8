"""Cross traffic at give-way and stop lines: the corner cameras' tracks (which vehicle has priority), the edge
forward past the line to where the cross street is seen, and the cameras themselves."""

from __future__ import annotations

import math

import numpy as np
import pytest

from towndrive.agent.decision import cross_traffic as ct
from towndrive.agent.decision.blind_spot import SideMount
from towndrive.agent.decision.controller import Controller, ControllerConfig, Scene
from towndrive.agent.perception.box_geometry import BoxGeometry
from towndrive.agent.perception.detections import Detection
from towndrive.agent.perception.signs import SignSeen
from towndrive.sim.spec import CORNERS, ROAD

DT = 0.05
CFG = ControllerConfig()
CAM = CFG.camera_to_front_m
STILL = (0.0, 0.0, 0.0)  # the car's pose in the odometry's frame: standing at the origin, facing +x


def _stage(monkeypatch: pytest.MonkeyPatch) -> ct.CrossTraffic:
    """A stage whose detections carry their ground position in the box: (ahead, out, 0, 0)."""
    monkeypatch.setattr(ct, "side_camera_ground", lambda geometry, mount, det, side: (det.box[0], det.box[1]))
    geometry = BoxGeometry(CORNERS.camera)
    return ct.CrossTraffic(geometry, SideMount(CORNERS.ahead_m, CORNERS.out_m, CORNERS.yaw_deg))


def _car(ahead: float, out: float) -> Detection:
    return Detection((ahead, out, 0.0, 0.0), 0, 0.9)  # class 0: car


def _watch(stage: ct.CrossTraffic, side: str, where, seconds: float = 1.0,
           stop_made_s: float | None = None) -> list[str]:
    """Look on ``side`` every other frame at a car placed by ``where(t)``; the priority verdict each look (our full
    stop made at ``stop_made_s``, from then on)."""
    out = []
    for k in range(int(seconds / DT)):
        t = k * DT
        if k % 2 == 0:
            stage.update(t, side, [_car(*where(t))], STILL)
            made = stop_made_s if stop_made_s is not None and t >= stop_made_s else None
            out.append(stage.priority(t, STILL, made))
    return out


def test_a_car_coming_down_the_cross_street_has_priority(monkeypatch: pytest.MonkeyPatch) -> None:
    stage = _stage(monkeypatch)
    verdicts = _watch(stage, "left", lambda t: (8.0, 30.0 - 9.0 * t))  # 8 m ahead, 30 m to the left, 9 m/s at us
    assert not verdicts[0]  # one sighting tells no motion
    assert verdicts[-1].startswith("cross traffic from the left")


def test_parked_and_departing_cars_have_no_priority(monkeypatch: pytest.MonkeyPatch) -> None:
    stage = _stage(monkeypatch)
    assert not any(_watch(stage, "right", lambda t: (9.0, 20.0 + 0.3 * math.sin(7.0 * t))))  # parked, jittering
    stage = _stage(monkeypatch)
    assert not any(_watch(stage, "left", lambda t: (8.0, 6.0 + 9.0 * t)))  # driving away from our way
    stage = _stage(monkeypatch)
    assert not any(_watch(stage, "left", lambda t: (8.0, 60.0 - 9.0 * t)))  # coming, but 6 s and more away


def test_a_vehicle_whose_motion_is_not_told_yet_is_known_as_such(monkeypatch: pytest.MonkeyPatch) -> None:
    stage = _stage(monkeypatch)
    stage.update(0.0, "left", [_car(8.0, 25.0)], STILL)
    assert stage.unknown(0.0, STILL)
    stage.update(0.1, "left", [_car(8.0, 25.0)], STILL)
    stage.update(0.2, "left", [_car(8.0, 25.0)], STILL)
    stage.update(0.4, "left", [_car(8.0, 25.0)], STILL)
    assert not stage.unknown(0.4, STILL) and not stage.priority(0.4, STILL)


def _through_the_line(kind: str, cross, seconds: float = 30.0, cross_street_m: float = 12.0):
    """The car drives at a ``kind`` line 30 m ahead; the corner cameras report ``cross(t, s)`` (reason or "");
    returns (t, bumper past the line, speed, decision) per frame."""
    ctrl = Controller(CFG)
    v, s, line_m, out = 8.0, 0.0, 30.0, []
    for k in range(int(seconds / DT)):
        t = k * DT
        to_line = line_m - s
        seen = to_line + CAM
        scene = Scene(v, stop_line_m=seen if 3.0 <= seen <= 20.0 else None,
                      signs=[SignSeen(kind, seen - ROAD.sign_before_stop_line_m, 4.0)] if seen > 8.0 else [],
                      cross_traffic=cross(t, -to_line), cross_street_m=cross_street_m)
        d = ctrl.step(scene, 0.0, DT)
        v = max(0.0, v + d.accel_mps2 * DT)
        s += v * DT
        out.append((t, -to_line, v, d))
    return out


def test_past_a_give_way_line_the_car_waits_where_the_cross_street_is_seen() -> None:
    look_from = 12.0 + ROAD.stop_bar_depth_m - CFG.signs.edge_margin_m  # from the bar's far edge, less the margin

    def cross(t: float, past: float) -> str:  # a car comes into view once the nose nears the cross street
        return "cross traffic from the left 20 m off, 2.0 s away" if past > 6.0 and t < 12.0 else ""

    run = _through_the_line("yield", cross)
    stood = [past for t, past, v, _ in run if v < 0.05 and past > 0.0]
    assert stood and max(stood) <= look_from + 0.5 and min(stood) >= look_from - 1.5  # stopped there, short of it
    assert any(d.reason.startswith("give way: cross traffic") for *_, d in run)
    assert run[-1][1] > look_from + 10.0  # and went on once the cross street was clear


def test_with_the_cross_street_clear_the_car_does_not_stop_past_the_line() -> None:
    run = _through_the_line("yield", lambda t, past: "")
    past_line = [v for _, past, v, _ in run if 0.0 < past < 15.0]
    assert past_line and min(past_line) > 1.5
    assert any(d.reason.startswith("give way:") and "looking" in d.reason for *_, d in run)


def test_the_corner_cameras_look_along_the_cross_street() -> None:
    from towndrive.envs.drive_env import DriveEnv, corner_pose
    from towndrive.envs.driver_context import DriverContext

    x, y, h = corner_pose((0.0, 0.0, 0.0), "left")
    assert x == pytest.approx(CORNERS.ahead_m) and y == pytest.approx(-CORNERS.out_m)
    assert h == pytest.approx(-math.radians(CORNERS.yaw_deg))
    env = DriveEnv()
    try:
        env.reset(seed=0)
        context = DriverContext.of(env)
        assert context.corner_frame is not None and context.corner_camera == CORNERS.camera
        frame = context.corner_frame("right")
        assert frame.shape == (CORNERS.camera.height, CORNERS.camera.width, 3) and frame.dtype == np.uint8
        assert frame.std() > 5.0  # a picture, not a blank
    finally:
        env.close()


def test_a_car_that_came_and_stopped_near_our_way_goes_first_for_a_while(monkeypatch: pytest.MonkeyPatch) -> None:
    """A priority car whose path our nose is near stops for it, and goes on once we stand: it is let go first,
    but not waited for for ever (it may be waiting for us)."""
    stage = _stage(monkeypatch)

    def where(t: float) -> tuple[float, float]:  # comes at 6 m/s and stops 8 m to the left at 1.5 s
        return 8.0, 8.0 + 6.0 * max(1.5 - t, 0.0)

    verdicts = _watch(stage, "left", where, seconds=6.0)
    times = [2 * k * DT for k in range(len(verdicts))]
    assert all(v for t, v in zip(times, verdicts, strict=True) if 0.5 <= t <= 4.0)  # waited for, coming or stopped
    assert any("letting it go first" in v for v in verdicts)
    assert verdicts[-1] == ""  # it stood on: no more waiting for it


def test_a_car_that_stopped_farther_off_is_let_go_first_and_has_priority_as_it_pulls_away(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A priority car that stops 24 m off (for a person on a crossing) and pulls away again 2 s later is there within
    the gap once it goes, though at its speed of the moment it would take ten seconds: waited for throughout."""
    stage = _stage(monkeypatch)

    def where(t: float) -> tuple[float, float]:  # comes at 6 m/s, stops 24 m off at 1 s, goes at 3 m/s^2 from 3 s
        if t < 1.0:
            return 12.0, 30.0 - 6.0 * t
        return 12.0, 24.0 - 1.5 * max(t - 3.0, 0.0) ** 2

    verdicts = _watch(stage, "left", where, seconds=4.5)
    times = [2 * k * DT for k in range(len(verdicts))]
    assert all(v for t, v in zip(times, verdicts, strict=True) if t >= 0.5)  # coming, standing, and pulling away


def test_how_soon_a_car_could_reach_our_way(monkeypatch: pytest.MonkeyPatch) -> None:
    stage = _stage(monkeypatch)
    a, top = stage.config.resume_accel_mps2, stage.street_speed_mps
    assert stage.reach_s(6.0, 0.0) == pytest.approx(math.sqrt(2.0 * 6.0 / a))  # pulling away, under the street's speed
    far = 40.0  # ... then at the street's speed
    assert stage.reach_s(far, 0.0) == pytest.approx(top / a + (far - top * top / (2.0 * a)) / top)
    assert stage.reach_s(30.0, 12.0) == pytest.approx(2.5)  # faster than the street's: its own speed
    assert stage.reach_s(30.0, 2.0) < 30.0 / 2.0  # slower: sooner than at its speed of the moment


def test_after_seeing_priority_traffic_both_sides_are_looked_at_afresh() -> None:
    """Edging at a give-way line: the looks that count before going are ``edge_looks`` in a row with the cross
    street clear; looks before a vehicle with priority was seen do not count."""
    ctrl = Controller(CFG)
    ctrl.signs.control, ctrl.signs.edging_m = "yield", 0.0  # standing where the cross street is seen
    seen = "cross traffic from the left 20 m off, 2.0 s away"
    pattern = [""] * (CFG.edge_looks - 1) + [seen] + [""] * (CFG.edge_looks + 2)
    went = None
    for k, cross in enumerate(pattern):
        ctrl.step(Scene(0.0, cross_traffic=cross), 0.0, DT)
        if went is None and ctrl.signs.edging_m is None:
            went = k
    assert went == CFG.edge_looks + CFG.edge_looks - 1  # the seen frame's index plus edge_looks clear looks


def test_a_car_that_came_to_its_line_after_our_full_stop_waits_its_turn(monkeypatch: pytest.MonkeyPatch) -> None:
    """At an all-way stop, who stopped first goes first: a car coming to a stand at its own line 18 m from our way
    after our full stop is not let go first; before our stop (or with none made) it is, as before."""
    def where(t: float) -> tuple[float, float]:  # comes at 6 m/s and stops 18 m to the left at 1.5 s
        return 20.0, 20.0 + 6.0 * max(1.5 - t, 0.0)

    after_ours = _watch(_stage(monkeypatch), "left", where, seconds=3.0, stop_made_s=0.5)
    before_ours = _watch(_stage(monkeypatch), "left", where, seconds=3.0, stop_made_s=2.5)
    assert any("s away" in v for v in after_ours)  # waited for while it came
    assert after_ours[-3:] == ["", "", ""]  # standing (its fitted speed has fallen under the threshold at 2.6 s)
    assert all("letting it go first" in v for v in before_ours[-3:])

    def near(t: float) -> tuple[float, float]:  # ... while one stopping 2 m from our way stopped for our nose
        return 20.0, 4.0 + 6.0 * max(1.5 - t, 0.0)

    for_our_nose = _watch(_stage(monkeypatch), "left", near, seconds=3.0, stop_made_s=0.5)
    assert all("letting it go first" in v for v in for_our_nose[-3:])
