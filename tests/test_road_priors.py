"""Road-design priors: a town style's, the agent's turn arc from them, and their correction by measurement."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from towndrive.agent.decision.junction import ZEBRA_SD_M, JunctionRules, turn_path
from towndrive.agent.decision.odometry import Odometry
from towndrive.agent.decision.priors import fused
from towndrive.sim.road_priors import road_priors
from towndrive.sim.spec import COUNT_DOUBT, ROAD
from towndrive.sim.town import Command, TownConfig
from towndrive.sim.world import cached_town


def tracked_bar() -> Any:
    """The controller's stop-line track as the junction guidance reads it: a bar measured 8 m ahead of a camera
    2 m behind the front bumper, no light to ignore."""
    from types import SimpleNamespace

    return SimpleNamespace(ignore_light_m=0.0, stop_line_measured=True, stop_line=8.0,
                           config=SimpleNamespace(camera_to_front_m=2.0))


def approach_odometry(yaw_rad: float = 0.0, pos: tuple[float, float] = (0.0, 0.0)) -> Odometry:
    """Dead reckoning on an approach lane measured to run along x (the car centred on it)."""
    odo = Odometry()
    odo.road_yaw, odo.yaw, odo.pos = 0.0, yaw_rad, np.array(pos, float)
    return odo


def test_a_prior_with_no_spread_is_the_design_and_one_with_a_spread_moves_towards_the_measurement() -> None:
    assert fused(12.0, 0.0, 19.0, 0.5) == 12.0
    assert fused(12.0, 1.0, None, 0.5) == 12.0
    assert fused(12.0, 1.0, 14.0, 1.0) == pytest.approx(13.0)
    assert fused(12.0, 2.0, 14.0, 1.0) == pytest.approx(12.0 + 2.0 * 4.0 / 5.0)


def test_the_classic_style_s_priors_are_the_classic_design_and_a_styled_one_s_are_measured_on_its_towns() -> None:
    assert road_priors("classic") is ROAD
    downtown = road_priors("downtown")
    assert downtown == road_priors("downtown")  # the same towns, the same numbers
    assert downtown.stop_line_setback_m > ROAD.stop_line_setback_m + 4.0 and downtown.stop_line_setback_sd_m > 0.5
    assert downtown.left_turn_radius_m is not None and downtown.right_turn_radius_m is not None
    assert 0.0 < downtown.zebra_to_centre_sd_m < downtown.stop_line_setback_sd_m  # the zebra is the better anchor
    heights = sorted(m.height_m for m in downtown.signal_mounts)  # mast arms and posts: one mode each
    assert len(heights) == 3 and heights[0] < heights[-1] - 1.0


def test_a_turn_with_a_radius_runs_straight_past_the_bar_then_bends_into_the_lane_turned_into() -> None:
    for command, side in ((2, 1.0), (1, -1.0)):
        reach = 18.0 - 1.75 if command == 2 else 18.0 + 1.75
        path, arc_end = turn_path(command, reach, 0.5, 9.0)
        steps = np.hypot(*np.diff(path, axis=0).T)
        assert steps.max() < 0.25  # one continuous polyline
        k = int(round(arc_end / 0.2))
        assert path[k - 1] == pytest.approx([0.5 + reach, side * 9.0], abs=0.2)  # the arc ends in the lane...
        assert path[-1][0] == pytest.approx(0.5 + reach)  # ... and follows it
        lead = path[(path[:, 0] > 0.5) & (path[:, 0] < 0.5 + reach - 9.0 - 0.2)]
        assert len(lead) > 10 and np.abs(lead[:, 1]).max() < 1e-9  # straight on before the arc
        # a radius wider than the lane turned into allows is the quarter circle from the bar
        assert np.array_equal(turn_path(command, reach, 0.5, 40.0)[0], turn_path(command, reach, 0.5)[0])


def _connector_deviation(style: str, town_seed: int, road) -> list[float]:
    """For each arm of two lanes in a town, how far (m) the agent's turn from ``road``'s priors (placed at the arm's
    stop bar) strays from the town's own connector, left and right."""
    town = cached_town(TownConfig.of_style(style), town_seed)
    out = []
    for entry in town.entries:
        if entry.lane_count != 2:
            continue
        t = np.array([math.cos(entry.travel_heading), math.sin(entry.travel_heading)])
        right = np.array([-t[1], t[0]])
        setback = road.stop_line_setback_m
        for command, k in ((Command.LEFT, 0), (Command.RIGHT, 1)):
            conn = next((i for i, info in town.lane_info.items() if i[0] == entry.edge[1] and i[2] == k
                         and info.kind == "connector" and info.command == command), None)
            if conn is None:
                continue
            approach = town.lane((entry.edge[0], entry.edge[1], k))
            origin = approach.position(approach.length, 0.0)
            lane = town.lane(conn)
            pts = np.array([lane.position(s, 0.0) for s in np.linspace(0.0, lane.length, 40)])
            rel = np.stack([(pts - origin) @ t, (pts - origin) @ right], axis=1)
            radius = road.left_turn_radius_m if command == Command.LEFT else road.right_turn_radius_m
            reach = road.kerb_lane_reach if command == Command.RIGHT else setback + 0.5 * road.lane_width_m
            path, _ = turn_path(int(command), reach, road.stop_bar_depth_m, radius)
            gap = np.sqrt(((rel[:, None, :] - path[None, :, :]) ** 2).sum(-1)).min(axis=1)
            out.append(float(gap.max()))
    return out


def test_in_a_styled_town_the_style_s_priors_place_the_turns_where_the_classic_design_cannot() -> None:
    """Downtown's stop bars stand 16-21 m from the junction's centre, and its turns run straight on past the bar
    before they bend: the classic design's quarter circle from the bar strays 7-9 m from the town's turns (median
    over a town's turns), the style's priors (before any measurement) 2-3 m."""
    style = _connector_deviation("downtown", 7, road_priors("downtown"))
    classic = _connector_deviation("downtown", 7, ROAD)
    assert len(style) > 20
    assert float(np.median(classic)) > 6.0
    assert float(np.median(style)) < 3.0


def test_the_zebra_beyond_the_bar_halves_the_setback_s_error() -> None:
    """The zebra's far edge lies a cross street's half width and a kerb gap before the junction's centre, which
    spreads less than the setback: corrected by it (read exactly here; the detector's error, 0.3 m median, is
    bench/eval_zebra.py's), the setback's error over two towns' arms falls from about 0.8-1.1 m to 0.4-0.5 m."""
    for style in ("downtown", "suburb"):
        road = road_priors(style)
        prior, corrected = [], []
        for seed in (7, 8):
            town = cached_town(TownConfig.of_style(style), seed)
            for entry in town.entries:
                t = np.array([math.cos(entry.travel_heading), math.sin(entry.travel_heading)])
                setback = float((town.node_position(entry.node) - entry.line_center) @ t) - road.stop_bar_depth_m
                cw = next(c for c in town.crosswalks if (c.node, c.arm) == (entry.node, entry.arm))
                beyond_bar = float(np.max((cw.polygon - entry.line_center) @ t)) - road.stop_bar_depth_m
                estimate = fused(road.stop_line_setback_m, road.stop_line_setback_sd_m,
                                 beyond_bar + road.zebra_to_centre_m, math.hypot(road.zebra_to_centre_sd_m, ZEBRA_SD_M))
                prior.append(abs(road.stop_line_setback_m - setback))
                corrected.append(abs(estimate - setback))
        assert float(np.median(corrected)) < 0.65 * float(np.median(prior)), style


def test_the_junction_guidance_corrects_its_setback_and_lane_width_by_what_is_measured() -> None:
    """``JunctionGuidance.note``: the zebra's far edge and the lane finder's width move a prior with a spread (the
    median of a junction's zebra readings), and leave the classic design's exact numbers alone."""

    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules
    from towndrive.agent.perception.stop_line import StopLine

    def guidance(road) -> JunctionGuidance:
        line = tracked_bar()
        odo = approach_odometry()
        return JunctionGuidance(JunctionRules(), line, odo, 1.0, road)

    road = road_priors("downtown")
    g = guidance(road)
    for far in (10.0 + 0.5 + 6.0, 10.0 + 0.5 + 9.0, 10.0 + 0.5 + 6.2):  # one odd reading among three
        g.note(StopLine(10.0, 0.5, 0.9, 0), far, 3.2)
    measured = 6.2 + road.zebra_to_centre_m
    assert g.setback_m == pytest.approx(fused(road.stop_line_setback_m, road.stop_line_setback_sd_m, measured,
                                              math.hypot(road.zebra_to_centre_sd_m, ZEBRA_SD_M)))
    assert min(road.stop_line_setback_m, measured) < g.setback_m < max(road.stop_line_setback_m, measured)
    assert min(3.2, road.lane_width_m) < g.lane_width_m < max(3.2, road.lane_width_m)
    g.forget()
    assert g.junction is None
    classic = guidance(ROAD)
    classic.note(StopLine(10.0, 0.5, 0.9, 0), 10.0 + 0.5 + 9.0, 3.2)
    assert classic.setback_m == ROAD.stop_line_setback_m and classic.lane_width_m == ROAD.lane_width_m


def test_a_bar_lost_short_of_the_placing_range_is_placed_where_odometry_tracks_it() -> None:
    """``JunctionGuidance.note``: a bar last read 12.6 m ahead, then lost to the camera (low sun), places the turn
    once the tracked bar is within ``turn_bar_seen_m``; one tracked farther does not yet, nor a glimpse (a bar read
    once, nothing hiding it since: ``StopLineTrack.bar_confirmed``). (Unplaced, PilotNet alone turned late and the
    mirror's look, taking the turn for a pending lane change, held it mid-turn.)"""
    from types import SimpleNamespace

    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules
    from towndrive.agent.perception.stop_line import StopLine

    ctf = 1.3  # camera to the front bumper
    for confirmed in (True, False):
        line = SimpleNamespace(ignore_light_m=0.0, stop_line_measured=True, stop_line=12.6 - ctf,
                               bar_confirmed=confirmed, config=SimpleNamespace(camera_to_front_m=ctf))
        odo = approach_odometry()
        g = JunctionGuidance(JunctionRules(), line, odo, 1.0, ROAD)
        g.note(None)
        assert not g.placed  # tracked 12.6 m ahead: beyond the placing range
        line.stop_line, odo.pos = 11.3 - ctf, np.array([1.3, 0.0])  # 1.3 m driven, the bar not seen again
        g.note(None)
        assert g.placed is confirmed
    assert g.junction is None
    line.bar_confirmed = True
    g.note(None)
    assert g.junction is not None and g.junction[0] == pytest.approx(1.3 + 11.3 - ctf + ctf + 1.0)
    # The bar, never read near, then forgotten as a glimpse (unseen a second while still 6 m off): the turn it
    # placed goes with it. One read within the placing range stays when the bar is forgotten.
    line.stop_line_measured, line.stop_line = False, None
    g.note(None)
    assert g.junction is None
    line.stop_line_measured, line.stop_line = True, 10.0 - ctf
    g.note(StopLine(10.0, 0.5, 0.9, 0))
    line.stop_line_measured, line.stop_line = False, None
    g.note(None)
    assert g.placed


def test_with_a_design_that_spreads_the_camera_finishes_the_turn_and_with_an_exact_one_the_arc_does() -> None:
    """Past ``turn_handover_deg`` of heading change the turn arc lets go (PilotNet steers) where the design's numbers
    are priors with a spread; the classic design's exact arc leads on."""

    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules
    from towndrive.agent.perception.stop_line import StopLine

    def steer_at(road, yaw_deg: float) -> tuple[float | None, float | None]:
        line = tracked_bar()
        odo = approach_odometry()
        g = JunctionGuidance(JunctionRules(), line, odo, 1.0, road)
        g.note(StopLine(8.0, 0.5, 0.9, 0))
        odo.pos = np.array([11.0, 0.0])  # at the bar: the right turn begins
        assert g.turn_steer(2, 3.0) is not None
        along = g.setback_m - 0.3 * g.lane_width_m  # inside the arc, turned by yaw_deg
        odo.pos, odo.yaw = np.array([11.0 + 0.6 * along, 0.4 * along]), math.radians(yaw_deg)
        return g.turn_steer(2, 3.0), odo.road_yaw

    steer, road_yaw = steer_at(road_priors("downtown"), 45.0)
    assert steer is not None and road_yaw == 0.0  # still turning: the approach road is the arc's frame
    # facing the road turned into: the camera steers, and the approach road, behind the car, is no longer its road
    assert steer_at(road_priors("downtown"), 65.0) == (None, None)
    assert steer_at(ROAD, 65.0)[0] is not None


def _head_box(camera, x_m: float, z_m: float, height_m: float) -> tuple[float, float, float, float]:
    """The box a three-lamp head (0.84 m wide, 2.1 m tall) at (x right, z ahead of the camera, centre height) draws."""
    theta = math.radians(-camera.pitch_deg)
    s, c = math.sin(theta), math.cos(theta)
    k = camera.intrinsics()

    def pixel(x: float, up: float, z: float) -> tuple[float, float]:
        y = camera.mount_height_m - up  # the level frame's y points down from the camera
        cam = np.array([x, y * c - z * s, y * s + z * c])
        uvw = k @ cam
        return float(uvw[0] / uvw[2]), float(uvw[1] / uvw[2])

    u0, v0 = pixel(x_m - 0.42, height_m + 1.05, z_m)
    u1, v1 = pixel(x_m + 0.42, height_m - 1.05, z_m)
    return (u0, v0 - 0.5, u1, v1 + 0.5)


def test_a_design_with_heads_on_posts_finds_its_light_on_a_post_and_the_classic_design_does_not() -> None:
    """Where heads hang is a kind (``RoadDesign.signal_mounts``): with the stop line measured 10 m ahead, a head on
    the far corner's post (3.6 m up, 7.5 m right, 29.5 m beyond the line) is ours for a design that uses such posts,
    at the distance the post's height gives; the classic design (mast arms only) takes no such head."""
    from types import SimpleNamespace

    from towndrive.agent.decision.our_light import LightRules, OurLight
    from towndrive.agent.perception.box_geometry import BoxGeometry
    from towndrive.agent.perception.classes import CLASSES
    from towndrive.agent.perception.detections import Detection
    from towndrive.sim.spec import CameraConfig

    camera = CameraConfig()
    geometry = BoxGeometry(camera)
    line = SimpleNamespace(stop_line_measured=True, stop_line=10.0, config=SimpleNamespace(camera_to_front_m=1.3))
    downtown = road_priors("downtown")
    post = next(m for m in downtown.other_signal_mounts if m.lateral_m > 6.0 and m.beyond_stop_line_m > 20.0)
    z = 10.0 + 1.3 + post.beyond_stop_line_m
    box = _head_box(camera, post.lateral_m - 0.0, z, post.height_m)
    red = Detection(box, CLASSES.index("light_red"), 0.9)
    seen = OurLight(geometry, LightRules(), downtown).choose([red], line, 0.0)
    assert seen is not None and seen.state == "red" and seen.distance_m == pytest.approx(z, rel=0.1)
    assert OurLight(geometry, LightRules(), ROAD).choose([red], line, 0.0) is None
    # without the stop line measured, a post's head is not taken for ours (it may be the cross street's)
    unmeasured = SimpleNamespace(stop_line_measured=False, stop_line=None, config=line.config)
    assert OurLight(geometry, LightRules(), downtown).choose([red], unmeasured, 0.0) is None


def test_a_far_corner_head_read_a_row_low_is_still_ours_and_the_near_corner_s_head_is_not() -> None:
    """A suburb junction whose far corner lies 3 m beyond the design's mean (within the towns' spread), its post's
    red head read a row low: 3-4 degrees above the camera a row is metres, and a fixed 5 m tolerance turned the head
    away while the car waited at the line (it then drove on into the junction). Ours with the reading's spread
    counted; a green head on the same kind of post 12 m nearer (the cross street's near corner) is still not."""
    from types import SimpleNamespace

    from towndrive.agent.decision.our_light import LightRules, OurLight
    from towndrive.agent.perception.box_geometry import BoxGeometry
    from towndrive.agent.perception.classes import CLASSES
    from towndrive.agent.perception.detections import Detection
    from towndrive.sim.spec import CameraConfig

    camera = CameraConfig()
    geometry = BoxGeometry(camera)
    line = SimpleNamespace(stop_line_measured=True, stop_line=1.5, config=SimpleNamespace(camera_to_front_m=1.3))
    suburb = road_priors("suburb")
    post = next(m for m in suburb.other_signal_mounts if m.lateral_m > 6.0 and m.beyond_stop_line_m > 20.0)
    z = 1.5 + 1.3 + post.beyond_stop_line_m + 3.0
    u0, v0, u1, v1 = _head_box(camera, post.lateral_m, z, post.height_m)
    red = Detection((u0, v0 + 1.0, u1, v1 + 1.0), CLASSES.index("light_red"), 0.9)
    seen = OurLight(geometry, LightRules(), suburb).choose([red], line, 0.0)
    assert seen is not None and seen.state == "red"
    assert OurLight(geometry, LightRules(light_reading_sigmas=0.0), suburb).choose([red], line, 0.0) is None
    near = Detection(_head_box(camera, post.lateral_m, z - 12.0, post.height_m), CLASSES.index("light_green"), 0.9)
    assert OurLight(geometry, LightRules(), suburb).choose([near], line, 0.0) is None


def test_a_profile_sets_the_priors_their_spreads_and_the_signal_mounts_and_bad_ones_get_one_sentence() -> None:
    from towndrive.agent.deploy.profiles import ProfileError, profile_from_dict

    road = profile_from_dict({"road": {"left_turn_radius_m": 11.0, "stop_line_setback_sd_m": 1.5,
                                       "other_signal_mounts": [{"beyond_stop_line_m": 28.0, "lateral_m": 7.0,
                                                                "height_m": 3.6}]}}).road
    assert road.left_turn_radius_m == 11.0 and road.stop_line_setback_sd_m == 1.5
    assert [m.height_m for m in road.signal_mounts] == [ROAD.signal_head_height_m, 3.6]
    for bad, words in (({"other_signal_mounts": 3}, "must be a list"),
                       ({"other_signal_mounts": [{"height_m": "high"}]}, "height_m must be a number"),
                       ({"other_signal_mounts": [{"height_m": 50}]}, "height_m"),
                       ({"left_turn_radius_m": -2}, "left_turn_radius_m"),
                       ({"single_lane_limit_kmh": 0}, "single_lane_limit_kmh")):
        with pytest.raises(ProfileError, match=words):
            profile_from_dict({"road": bad})


def test_the_cli_gives_the_agent_a_style_s_priors_and_the_sign_detector_and_refuses_them_for_other_drivers() -> None:
    from towndrive.agent.shipped import DETECTOR_SIGNS_ONNX
    from towndrive.drive_cli import driver_spec, parse_args

    args = parse_args(["--driver", "agent", "--road-priors", "style", "--town-style", "suburb", "--signs"])
    args.workers = 1
    kwargs = dict(driver_spec(args).kwargs)
    assert kwargs["road"] == road_priors("suburb") and kwargs["detector"] == DETECTOR_SIGNS_ONNX
    other = parse_args(["--driver", "autopilot", "--road-priors", "style"])
    other.workers = 1
    with pytest.raises(ValueError, match="for the agent driver"):
        driver_spec(other)
    other = parse_args(["--driver", "autopilot", "--no-signs"])
    other.workers = 1
    with pytest.raises(ValueError, match="for the agent driver"):
        driver_spec(other)


def test_the_agent_s_default_detector_reads_signs_and_no_signs_gives_the_six_classes() -> None:
    """The sign detector and its reader are the agent's default; ``--no-signs`` asks for the six-class detector
    alone. A reader given with a six-class model reads nothing, and the detections are those without it."""
    from towndrive.agent.agent_driver import DEFAULT_DETECTOR, DEFAULT_SIGN_READER
    from towndrive.agent.perception.classes import CLASSES
    from towndrive.agent.perception.detector import OnnxDetector, detect_and_refine
    from towndrive.agent.shipped import DETECTOR_ONNX, DETECTOR_SIGNS_ONNX, REFINER_ONNX, SIGN_READER_ONNX
    from towndrive.drive_cli import driver_spec, parse_args

    assert (DEFAULT_DETECTOR, DEFAULT_SIGN_READER) == (DETECTOR_SIGNS_ONNX, SIGN_READER_ONNX)
    args = parse_args(["--driver", "agent"])
    args.workers = 1
    assert "detector" not in dict(driver_spec(args).kwargs)  # the default
    args = parse_args(["--driver", "agent", "--no-signs"])
    args.workers = 1
    kwargs = dict(driver_spec(args).kwargs)
    assert kwargs["detector"] == DETECTOR_ONNX and kwargs["sign_reader"] is None
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 255, (160, 320, 3), dtype=np.uint8)
    frame[60:120, 140:170] = (200, 30, 30)
    plain = OnnxDetector(DETECTOR_ONNX, refiner=REFINER_ONNX)
    with_reader = OnnxDetector(DETECTOR_ONNX, refiner=REFINER_ONNX, signs=SIGN_READER_ONNX)
    raw = plain.raw(frame)
    assert raw.shape[1] - 5 == CLASSES.index("stop_sign")  # six class channels
    assert with_reader(frame) == plain(frame)

    from types import SimpleNamespace

    class NoSignsToRead:
        config = SimpleNamespace(lowest_candidate=lambda threshold: 0.01)

        def __call__(self, *args: object) -> list:
            raise AssertionError("the sign reader ran on a six-class model's boxes")

    assert detect_and_refine(raw, frame, 0.3, None, NoSignsToRead()) == detect_and_refine(raw, frame, 0.3, None)


def test_the_scenario_suite_gives_each_scenario_s_agent_the_priors_of_the_town_it_happens_in() -> None:
    """``towndrive scenario all --road-priors style``: scenarios placed in a styled town run with that style's priors,
    the others with the command line's style."""
    from towndrive.drive_cli import scenario_styles
    from towndrive.envs.scenarios import SCENARIOS

    groups = scenario_styles(list(SCENARIOS), "classic")
    assert sorted(n for g in groups.values() for n in g) == sorted(SCENARIOS)
    assert "t_junction_priority_turn" in groups["suburb"] and "red_light" in groups["classic"]
    assert all(SCENARIOS[n].place is not None and SCENARIOS[n].place.style == style
               for style, g in groups.items() if style != "classic" for n in g)


def test_a_right_turn_aims_at_the_kerb_lane_whatever_the_cross_street_s_lane_count() -> None:
    """A right turn goes into the cross street's kerb lane. Aimed at the second lane beyond the centre line (the
    classic design's two lanes each way), it fell 2.3 m short on average in suburb towns, whose cross streets often
    have one lane; the kerb lane's own prior (``RoadDesign.kerb_lane_reach_m``) is unbiased on towns it was not
    measured on, and in the classic design it is the same lane as before."""
    road = road_priors("suburb")
    old, new = [], []
    for seed in (7, 8):
        town = cached_town(TownConfig.of_style("suburb"), seed)
        for entry in town.entries:
            t = np.array([math.cos(entry.travel_heading), math.sin(entry.travel_heading)])
            for idx, info in town.lane_info.items():
                if (idx[0] != entry.edge[1] or info.kind != "connector" or info.command != Command.RIGHT
                        or idx[2] != entry.lane_count - 1):
                    continue
                lane = town.lane(idx)
                true = float((lane.position(lane.length, 0.0) - entry.line_center) @ t) - road.stop_bar_depth_m
                old.append(road.stop_line_setback_m - 1.5 * road.lane_width_m - true)
                new.append(road.kerb_lane_reach - true)
    assert len(new) > 30
    assert float(np.mean(old)) < -1.5 and abs(float(np.mean(new))) < 0.7
    assert ROAD.kerb_lane_reach == ROAD.stop_line_setback_m - 1.5 * ROAD.lane_width_m


def test_a_turn_into_a_cross_street_that_leans_ends_on_its_lane_at_its_angle() -> None:
    """``turn_path`` with the cross street's angle: the arc is tangent to the approach and ends heading along the
    lane turned into, whose centre line crosses the approach lane's ``reach`` beyond the bar's far edge."""
    for command, side in ((2, 1.0), (1, -1.0)):
        for angle in (80.0, 90.0, 100.0):
            path, arc_end = turn_path(command, 15.0, 0.5, 8.0, angle_deg=angle)
            k = int(round(arc_end / 0.2))
            d = path[-1] - path[k]  # along the exit
            heading = math.degrees(math.atan2(side * d[1], d[0]))
            assert heading == pytest.approx(angle, abs=0.5)
            # the exit line, continued back, crosses y = 0 at the bar's far edge + reach
            crossing = path[k][0] - path[k][1] * d[0] / d[1]
            assert crossing == pytest.approx(0.5 + 15.0, abs=0.05)
            first = np.argmax(np.abs(path[:, 1]) > 1e-9)
            assert abs(path[first - 1][1]) < 1e-9 and path[first - 1][0] < 0.5 + 15.0  # straight on, then the arc


def test_the_junction_guidance_reads_the_cross_street_s_angle_from_near_zebra_readings_only() -> None:
    """``JunctionGuidance.note`` with the zebra's edge slope: near readings (bar within ``skew_bar_max_m``), in the
    approach lane's frame (the camera turned 2 degrees right of it here), their median once there are enough; far
    ones and the classic design's exact square junctions are left alone."""
    from types import SimpleNamespace

    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules
    from towndrive.agent.perception.stop_line import StopLine

    def guidance(road) -> JunctionGuidance:
        line = SimpleNamespace(ignore_light_m=0.0, stop_line_measured=True, stop_line=5.0,
                               config=SimpleNamespace(camera_to_front_m=2.0))
        odo = approach_odometry(yaw_rad=math.radians(2.0))
        return JunctionGuidance(JunctionRules(), line, odo, 1.0, road)

    road = road_priors("downtown")
    g = guidance(road)
    lean = math.radians(7.4)
    g.note(StopLine(10.0, 0.5, 0.9, 0), None, None, math.tan(0.5))  # far: not taken
    for tilt in (lean + 0.03, lean - 0.01, lean + 0.5):  # one odd reading among three
        assert g.skew_rad == 0.0  # not enough readings yet
        g.note(StopLine(6.0, 0.5, 0.9, 0), None, None, math.tan(tilt + math.radians(2.0)))
    assert g.skew_rad == pytest.approx(lean + 0.03, abs=1e-6)
    classic = guidance(ROAD)
    for _ in range(3):
        classic.note(StopLine(6.0, 0.5, 0.9, 0), None, None, math.tan(lean))
    assert classic.skew_rad == 0.0


def test_the_zebra_is_read_from_the_tracked_bar_when_this_frame_misses_the_bar() -> None:
    """``JunctionGuidance.note`` with no bar read this frame (at night the bar is often lost near, the zebra
    beyond it is not): the zebra's far edge and slope are taken from the tracked bar once it is confirmed, and
    not from a bar seen once (a glimpse)."""
    from types import SimpleNamespace

    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules

    def guidance(confirmed: bool) -> JunctionGuidance:
        line = SimpleNamespace(ignore_light_m=0.0, stop_line_measured=True, stop_line=4.0, bar_confirmed=confirmed,
                               config=SimpleNamespace(camera_to_front_m=2.0))  # the camera 6 m from the bar
        return JunctionGuidance(JunctionRules(), line, approach_odometry(), 1.0, road_priors("suburb"))

    lean = math.radians(-14.0)  # the cross street 14 degrees off square
    g = guidance(True)
    for _ in range(3):
        g.note(None, 6.0 + 0.5 + 2.1, None, math.tan(lean))
    assert g.skew_rad == pytest.approx(lean)
    assert g.planned_angle_deg(2) == pytest.approx(90.0 - math.degrees(lean))  # the turn planned by that angle
    road = g.road
    assert g.setback_m == pytest.approx(fused(road.stop_line_setback_m, road.stop_line_setback_sd_m,
                                              2.1 + road.zebra_to_centre_m,
                                              math.hypot(road.zebra_to_centre_sd_m, ZEBRA_SD_M)))
    glimpse = guidance(False)
    for _ in range(3):
        glimpse.note(None, 6.0 + 0.5 + 2.1, None, math.tan(lean))
    assert glimpse.skew_rad == 0.0 and glimpse.setback_m == road.stop_line_setback_m


def _turns_beyond_zebra(style: str, seeds: tuple[int, ...]) -> list[tuple[str, int, int, bool, float, float]]:
    """Each turn of some towns with a zebra before it: (what governs the arm, our lanes, the cross street's,
    left?, the zebra's far edge along our lane, where the lane turned into crosses ours), from the bar's far edge."""
    from towndrive.sim.road_priors import control_kind, exit_crossing, zebra_far_along

    out = []
    for seed in seeds:
        town = cached_town(TownConfig.of_style(style), seed)
        for entry in town.entries:
            cw = next(c for c in town.crosswalks if (c.node, c.arm) == (entry.node, entry.arm))
            for idx, info in town.lane_info.items():
                left = info.command == Command.LEFT
                if (idx[0] != entry.edge[1] or info.kind != "connector" or info.command not in (Command.LEFT, Command.RIGHT)
                        or idx[2] != (0 if left else entry.lane_count - 1)):
                    continue
                lane = town.lane(idx)
                start = lane.position(0.0, 0.0)
                cross = town.lane_count((idx[1], next(iter(town.network.graph[idx[1]]))))
                out.append((control_kind(entry.control), entry.lane_count, cross, left,
                            zebra_far_along(cw, start, entry.travel_heading),
                            exit_crossing(lane, start, entry.travel_heading)))
    return out


def test_turns_placed_from_the_zebra_by_the_cross_street_s_lane_count_land_on_the_lane_turned_into() -> None:
    """The zebra lies at the cross street's kerb, so the lane turned into lies a set distance beyond its far edge
    once the cross street's lanes each way are known (``RoadDesign.turn_reaches``, within 0.9 m on validation towns;
    the priors are measured on training towns). The count is not seen before the turn: its odds by what governs
    the arm and our road's lanes (who stops or gives way enters a larger street) make the expected reach, which
    misses right turns by less than the kerb lane's bar-relative prior does."""
    for style in ("downtown", "suburb"):
        road = road_priors(style)
        turns = _turns_beyond_zebra(style, (4000, 4001))
        assert len(turns) > 40, style
        known, expected, prior = [], [], []
        for control, ours, cross, left, zebra, crossing in turns:
            exact = road.turn_reach(left, float(cross == 2))
            guess = road.turn_reach(left, road.two_lane_share(control, ours))
            assert exact is not None and guess is not None
            known.append(abs(zebra + exact - crossing))
            if not left:
                expected.append(abs(zebra + guess - crossing))
                prior.append(abs(road.kerb_lane_reach - crossing))
        assert max(known) < 0.9 and float(np.median(known)) < 0.3, style
        assert float(np.mean(expected)) < 0.75 * float(np.mean(prior)), style
    assert ROAD.turn_reaches == () and ROAD.turn_reach(False, 1.0) is None  # the classic design places turns as before


def test_the_cross_street_s_odds_pool_the_kinds_the_car_could_not_tell_apart() -> None:
    from towndrive.sim.spec import CrossStreetOdds, RoadDesign, TurnReach

    road = RoadDesign(cross_street_odds=(CrossStreetOdds("stop", 1, 0.9, 10), CrossStreetOdds("signal", 1, 0.3, 40),
                                         CrossStreetOdds("signal", 2, 0.8, 20)),
                      turn_reaches=(TurnReach(1, 14.0, 11.0), TurnReach(2, 15.5, 8.5)))
    assert road.two_lane_share("stop", 1) == pytest.approx(0.9)
    assert road.two_lane_share("signal", None) == pytest.approx((12 + 16) / 60)
    assert road.two_lane_share("stop", 2) == pytest.approx(0.9)  # no stop on a two-lane road measured: the stops
    assert road.two_lane_share("yield", None) == pytest.approx(37 / 70)  # nothing of the kind: every junction
    assert road.turn_reach(False, 0.25) == pytest.approx(0.75 * 11.0 + 0.25 * 8.5)
    assert replace(road, turn_reaches=road.turn_reaches[:1]).turn_reach(True, 0.5) is None
    with pytest.raises(ValueError, match="control must be one of"):
        CrossStreetOdds("roundabout", 1, 0.5, 3)


def test_an_unseen_lane_count_is_hedged_to_keep_both_lanes_within_the_car_s_room() -> None:
    """The expected reach bets on the likelier count; where both may be, it is moved to within the car's room in
    its lane of each count's lanes in its direction (a threshold, not a squared error, is what a lane keeps): a left
    turn between the two counts' inner lanes, a right turn near the single lane's place, the inner lane of two
    (aiming at the two-lane kerb lane puts it off the road on one lane). Left alone where one count is certain."""

    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules
    from towndrive.agent.perception.stop_line import StopLine
    from towndrive.sim.spec import VEHICLE, CrossStreetOdds, TurnReach

    road = replace(road_priors("suburb"), turn_reaches=(TurnReach(1, 14.3, 11.1), TurnReach(2, 15.5, 9.0)),
                   cross_street_odds=(CrossStreetOdds("signal", 2, 0.8, 30), CrossStreetOdds("none", 2, 0.0, 30)),
                   lane_width_m=3.2)
    room = (3.2 - VEHICLE.width_m) / 2
    assert road.turn_reach(True, 0.8) == pytest.approx(0.2 * 14.3 + 0.8 * 15.5)  # the least squared error
    hedged = road.turn_reach(True, 0.8, within_m=room)
    assert hedged == pytest.approx(14.3 + room) and 15.5 - hedged <= room + 1e-9
    assert road.turn_reach(True, 0.0, within_m=room) == 14.3  # one count can be: no hedge
    assert road.turn_reach(False, 0.8) == pytest.approx(0.2 * 11.1 + 0.8 * 9.0)
    assert road.turn_reach(False, 0.8, within_m=room) == pytest.approx(11.1 - room)  # inside the two lanes' band
    assert road.turn_reach(False, 1.0, within_m=room) == pytest.approx(9.0)  # two lanes certain: the kerb lane
    line = tracked_bar()
    odo = approach_odometry()
    g = JunctionGuidance(JunctionRules(), line, odo, 1.0, replace(road, lane_width_sd_m=0.0))
    g.note(StopLine(9.0, 0.5, 0.9, 0), 9.0 + 0.5 + 6.0, None, None, "signal", 2)
    assert g.lane_room_m == pytest.approx(room)
    assert g.turn_reach_m(1) == pytest.approx(6.0 + 14.3 + room)


def test_the_junction_guidance_places_a_turn_from_the_zebra_by_the_kind_of_junction_seen() -> None:
    """``JunctionGuidance.turn_reach_m``: with the zebra measured, its far edge plus the reach expected for the
    kind of junction (a stop sign on a single-lane road: a two-lane street ahead; a light seen once keeps the arm a
    signal's); without a zebra, the priors as before."""

    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules
    from towndrive.agent.perception.stop_line import StopLine
    from towndrive.sim.spec import CrossStreetOdds, TurnReach

    road = replace(road_priors("downtown"), turn_reaches=(TurnReach(1, 14.0, 11.0), TurnReach(2, 15.5, 8.5)),
                   cross_street_odds=(CrossStreetOdds("stop", 1, 1.0, 8), CrossStreetOdds("none", 1, 0.0, 8),
                                      CrossStreetOdds("signal", 1, 0.2, 8)))
    line = tracked_bar()
    odo = approach_odometry()
    g = JunctionGuidance(JunctionRules(), line, odo, 1.0, road)
    g.note(StopLine(10.0, 0.5, 0.9, 0), None, 3.2, None, "stop", 1)
    assert g.turn_reach_m(2) == road.kerb_lane_reach  # no zebra yet
    g.note(StopLine(9.0, 0.5, 0.9, 0), 9.0 + 0.5 + 6.0, 3.2, None, "none", 1)
    assert g.turn_reach_m(2) == pytest.approx(6.0 + 8.5) and g.turn_reach_m(1) == pytest.approx(6.0 + 15.5)
    g.forget()
    g.note(StopLine(9.0, 0.5, 0.9, 0), 9.0 + 0.5 + 6.0, 3.2, None, "signal", 1)
    g.note(StopLine(8.0, 0.5, 0.9, 0), 8.0 + 0.5 + 6.0, 3.2, None, "none", 1)  # the light out of view: still one
    assert g.turn_reach_m(2) == pytest.approx(6.0 + 0.8 * 11.0 + 0.2 * 8.5)


def test_a_right_turn_s_radius_is_the_one_of_both_roads_lanes() -> None:
    """``RoadDesign.right_turn_radii``: a right turn goes round the corner's kerb at the nearer lane's distance from
    its kerb, and a parking strip puts a single-lane street's lane farther out, so a turn from a two-lane road is as
    tight as its kerb lane whatever it turns into. On validation towns the style's radius by both roads' lanes lies
    within 0.2 m of every right turn's, the style's mean radius 0.7 m or more off most of them. Expected over the
    cross street's odds; a pairing not listed, or our lanes not seen, takes the mean."""
    from towndrive.sim.road_priors import junction_samples
    from towndrive.sim.spec import TurnRadius
    from towndrive.sim.splits import split_towns
    from towndrive.sim.town import TownConfig, generate_town

    road = road_priors("suburb")
    by_pair = {(r.our_lanes, r.cross_lanes): r.right_m for r in road.right_turn_radii}
    assert road.right_turn_radius_m is not None and set(by_pair) == {(1, 1), (1, 2), (2, 1), (2, 2)}
    pair_off, mean_off = [], []
    for seed in split_towns("validation", 2):
        for key, radii in junction_samples(generate_town(TownConfig.of_style("suburb"), seed=seed)).items():
            if key.startswith("radius:"):
                pair = (int(key.split(":")[1]), int(key.split(":")[2]))
                pair_off += [abs(r - by_pair[pair]) for r in radii]
                mean_off += [abs(r - road.right_turn_radius_m) for r in radii]
    assert len(pair_off) > 20 and max(pair_off) < 0.2
    assert float(np.median(mean_off)) > 0.7
    assert road.right_turn_radius(2, {1: 0.3, 2: 0.7}) == pytest.approx(0.3 * by_pair[2, 1] + 0.7 * by_pair[2, 2])
    assert road.right_turn_radius(None, {1: 1.0}) == road.right_turn_radius_m
    partial = replace(road, right_turn_radii=(TurnRadius(1, 1, 11.0),))
    assert partial.right_turn_radius(1, {1: 0.5, 2: 0.5}) == pytest.approx(0.5 * 11.0 + 0.5 * road.right_turn_radius_m)
    assert ROAD.right_turn_radius(2, {1: 1.0}) is None  # the classic design's quarter circle


def test_the_junction_guidance_begins_a_right_turn_s_arc_where_our_road_s_lanes_put_it() -> None:
    """``JunctionGuidance.turn_steer``: from a two-lane road the right turn's arc, tighter than the style's mean,
    begins later along the approach (the car's centre reaches it where the two-lane radius puts it)."""

    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules, arc_placement
    from towndrive.agent.perception.stop_line import StopLine
    from towndrive.sim.spec import CrossStreetOdds, TurnRadius, TurnReach

    road = replace(road_priors("suburb"), turn_reaches=(TurnReach(1, 14.4, 10.8), TurnReach(2, 15.7, 8.6)),
                   cross_street_odds=(CrossStreetOdds("signal", 2, 1.0, 50),), right_turn_radius_m=9.5,
                   right_turn_radii=(TurnRadius(2, 2, 8.6), TurnRadius(1, 1, 10.8)))
    line = tracked_bar()
    odo = approach_odometry()
    g = JunctionGuidance(JunctionRules(), line, odo, 1.0, road)
    g.note(StopLine(8.0, 0.5, 0.9, 0), 8.0 + 0.5 + 6.0, road.lane_width_m, None, "signal", 2)
    assert g.junction is not None
    reach, bar_x = g.turn_reach_m(2), g.junction[0]
    _, start = arc_placement(reach, road.stop_bar_depth_m, 8.6, 90.0)
    _, mean_start = arc_placement(reach, road.stop_bar_depth_m, 9.5, 90.0)
    assert start > mean_start + 0.8
    odo.pos = np.array([bar_x + start - 0.3, 0.0])
    assert g.turn_steer(2, 3.0) is not None and g._arc_start_m is None  # past the mean's start, short of its own
    odo.pos = np.array([bar_x + start + 0.05, 0.0])
    g.turn_steer(2, 3.0)
    assert g._arc_start_m == pytest.approx(start)
    # the path it steers along, in the camera's ground frame (the camera 1 m ahead of the centre): from the car's
    # centre, bending right, until it would run back towards the camera
    path = g.steered_path(30.0)
    assert path is not None and path[0, 1] == pytest.approx(-1.0, abs=0.2) and abs(path[0, 0]) < 0.2
    assert np.all(np.diff(path[:, 1]) > 0) and np.all(np.diff(path[:, 0]) >= -1e-9) and path[-1, 0] > 5.0
    odo.pos = np.array([bar_x - 20.0, 0.0])
    assert g.turn_steer(2, 3.0) is None and g.steered_path(30.0) is None


def test_a_profile_sets_the_turn_reaches_the_right_turn_radii_and_the_cross_street_odds() -> None:
    from towndrive.agent.deploy.profiles import ProfileError, profile_from_dict

    road = profile_from_dict({"road": {"turn_reaches": [{"cross_lanes": 2, "left_m": 15.0, "right_m": 9.0}],
                                       "cross_street_odds": [{"control": "stop", "our_lanes": 1,
                                                              "two_lane_share": 1.0}],
                                       "right_turn_radius_m": 9.0,
                                       "right_turn_radii": [{"our_lanes": 2, "cross_lanes": 1, "right_m": 8.0}]}}).road
    assert road.turn_reach(False, road.two_lane_share("stop", 1)) == 9.0
    assert road.right_turn_radius(2, {1: 1.0}) == 8.0 and road.right_turn_radius(2, {2: 1.0}) == 9.0
    for bad, words in (({"turn_reaches": {"left_m": 3}}, "must be a list"),
                       ({"cross_street_odds": [{"control": "lights"}]}, "control must be one of"),
                       ({"turn_reaches": [{"right_m": 90}]}, "right_m"),
                       ({"right_turn_radii": [{"right_m": 1.0}]}, "turn radius right_m")):
        with pytest.raises(ProfileError, match=words):
            profile_from_dict({"road": bad})


def likeliest(g: object) -> int:
    """The road turned into's likeliest lane count, as ``JunctionGuidance.exit_odds`` weighs it."""
    odds = g.exit_odds()  # type: ignore[attr-defined]
    return max(odds, key=lambda n: odds[n])


def cross_line_seen(odo: Odometry, centre_along_m: float, runs_deg: float, length_m: float = 10.0,
                    fill: float | None = None, misread_deg: float = 0.0) -> object:
    """The cross street's centre line as the camera (1 m ahead of the car's centre) sees it from where ``odo`` is:
    it crosses our lane's centre line ``centre_along_m`` beyond x = 11 (the bar's near edge, ``JunctionGuidance``
    placed as in these tests) and runs ``runs_deg`` right of our road (x right, z ahead); its direction is read
    ``misread_deg`` off."""
    from towndrive.agent.perception.exit_line import ExitLine

    runs = math.radians(runs_deg)
    cam = odo.pos + np.array([math.cos(odo.yaw), math.sin(odo.yaw)])
    point = np.array([11.0 + centre_along_m, 0.0]) + 8.0 * np.array([math.cos(runs), math.sin(runs)]) - cam
    seen = (float(-point[0] * math.sin(odo.yaw) + point[1] * math.cos(odo.yaw)),
            float(point[0] * math.cos(odo.yaw) + point[1] * math.sin(odo.yaw)))
    return ExitLine(seen, runs + math.radians(misread_deg) - odo.yaw, 400, length_m, fill)


def see_cross_centre_line(g: object, command: int, centre_along_m: float, yaw_deg: float) -> None:
    """Turn the car ``yaw_deg`` into a junction turn (the bar's near edge at x = 11 of the odometry frame) and give
    the guidance three readings of the cross street's centre line, which crosses our lane ``centre_along_m``
    beyond the bar's near edge, as the camera sees it (x right, z ahead)."""
    side = 1.0 if command == 2 else -1.0
    odo = g.odo  # type: ignore[attr-defined]
    odo.pos, odo.yaw = np.array([15.0, side * 2.0]), side * math.radians(yaw_deg)
    for _ in range(3):
        g.note_exit(cross_line_seen(odo, centre_along_m, side * 90.0))  # type: ignore[attr-defined]


def test_the_road_turned_into_read_in_the_turn_places_its_inner_lane_and_the_arc_then_leads_to_the_end() -> None:
    """``JunctionGuidance.note_exit``: the road turned into's centre line, seen from inside the turn, puts the lane
    turned into half a lane to its right in the direction of travel (right turns short of it, left turns beyond it),
    whatever the design planned; a reading far from the plan is something else; once read, the arc leads past the
    hand-over heading."""

    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules
    from towndrive.agent.perception.stop_line import StopLine

    road = road_priors("suburb")

    def reach_read(command: int, centre_along_m: float, yaw_deg: float) -> JunctionGuidance:
        line = tracked_bar()
        odo = approach_odometry()
        g = JunctionGuidance(JunctionRules(), line, odo, 1.0, road)
        g.note(StopLine(8.0, 0.5, 0.9, 0))  # the bar's near edge at x = 11 in the odometry frame
        odo.pos = np.array([11.0, 0.0])
        assert g.turn_steer(command, 3.0) is not None and g.exit_expected_rad() is None  # not yet turned
        see_cross_centre_line(g, command, centre_along_m, yaw_deg)
        expected = g.exit_expected_rad()
        side = 1.0 if command == 2 else -1.0
        assert expected is not None and expected == pytest.approx(side * math.pi / 2 - odo.yaw)
        return g

    depth = road.stop_bar_depth_m
    for command, planned_shift in ((2, -2.0), (1, 2.0)):
        g0 = reach_read(command, 0.0, 40.0)  # nothing added yet: find what was planned
        centre = g0.planned_reach_m(command) + depth + planned_shift
        g = reach_read(command, centre, 40.0)
        assert g.exit_measured
        inner = centre - 0.5 * g.lane_width_m if command == 2 else centre + 0.5 * g.lane_width_m
        if command == 1:
            assert g.turn_reach_m(command) == pytest.approx(inner - depth, abs=1e-6)
        else:  # toward the kerb lane where two lanes may be, within the car's room of the inner lane
            assert inner - depth - g.lane_room_m - 1e-9 <= g.turn_reach_m(command) <= inner - depth + 1e-9
        assert g.turn_angle_deg(command) == pytest.approx(90.0)
        far = reach_read(command, g0.planned_reach_m(command) + depth + 9.0, 40.0)  # a line 9 m from the plan
        assert not far.exit_measured and far.turn_reach_m(command) == far.planned_reach_m(command)
    # read, the arc leads on past the hand-over heading; unread (the line was too far off), the camera takes over
    planned = reach_read(2, 0.0, 40.0).planned_reach_m(2) + depth
    read, unread = reach_read(2, planned, 40.0), reach_read(2, planned + 9.0, 40.0)
    for g in (read, unread):
        g.odo.pos, g.odo.yaw = np.array([17.0, 4.0]), math.radians(65.0)
    assert read.turn_steer(2, 3.0) is not None and unread.turn_steer(2, 3.0) is None


def test_the_corner_camera_looks_down_the_road_turned_into_from_the_arcs_start() -> None:
    """``JunctionGuidance.exit_look``: once a turn's arc leads, the corner camera on the turn's side is asked to look
    for the road turned into, with the direction it should run from the car's axis, until the car has turned
    ``exit_corner_max_turned_deg``; the forward camera only from ``exit_min_turned_deg``. A reading taken so,
    before the forward camera can, places the lane turned into."""
    for command, side in ((2, "right"), (1, "left")):
        sign = 1.0 if command == 2 else -1.0
        g: Any = placed_turn()
        odo, rules, road = g.odo, g.rules, g.road
        assert g.exit_look() is None  # no turn under way yet
        odo.pos = np.array([11.0, 0.0])
        assert g.turn_steer(command, 3.0) is not None
        for turned_deg, looks in ((0.0, True), (10.0, True), (rules.exit_corner_max_turned_deg + 5.0, False)):
            odo.yaw = sign * math.radians(turned_deg)
            look = g.exit_look()
            assert (look is not None) == looks
            if look is not None:
                assert look[0] == side and look[1] == pytest.approx(sign * math.pi / 2 - odo.yaw)
        odo.pos, odo.yaw = np.array([14.0, sign * 0.5]), sign * math.radians(10.0)
        assert g.exit_expected_rad() is None  # the forward camera does not look yet
        centre = g.planned_reach_m(command) + road.stop_bar_depth_m + 1.0
        for _ in range(rules.exit_min_readings):
            g.note_exit(cross_line_seen(odo, centre, sign * 90.0))  # as the corner camera reads it
        assert g.exit_measured


def test_a_reading_before_the_car_has_turned_much_moves_the_arcs_start_on() -> None:
    """``JunctionRules.exit_restart_max_deg``: the arc's start is committed as the car's centre reaches it, often
    before the road turned into is read. A reading that puts the start farther on moves it there while the car has
    barely turned (it goes on straight to it); turned farther, the start stays and the reading moves the arc's end."""
    for turned_deg, moves in ((3.0, True), (JunctionRules().exit_restart_max_deg + 10.0, False)):
        g: Any = placed_turn()  # the bar's near edge at x = 11 in the odometry frame
        odo, rules, road = g.odo, g.rules, g.road
        odo.pos = np.array([11.0, 0.0])
        assert g.turn_steer(2, 3.0) is not None and g.arc_ahead_m is not None
        start = g.arc_ahead_m  # the car's centre is at the bar's near edge
        odo.pos = np.array([11.0 + start + 0.1, 0.0])
        g.turn_steer(2, 3.0)
        assert g._arc_start_m == pytest.approx(start)  # committed
        odo.yaw = math.radians(turned_deg)
        centre = g.planned_reach_m(2) + road.stop_bar_depth_m + 3.0  # the lane turned into lies 3 m farther on
        for _ in range(rules.exit_min_readings):
            g.note_exit(cross_line_seen(odo, centre, 90.0, fill=1.0))
        assert g.exit_measured
        g.turn_steer(2, 3.0)
        if moves:
            assert g._arc_start_m is None and g.arc_ahead_m > 0.5  # the start lies ahead now
        else:
            assert g._arc_start_m == pytest.approx(start)


def read_turn(command: int, centre_along_m: float, zebra: bool, share: float) -> Any:
    """A suburb junction guidance that has placed a turn from the bar (and the zebra 6 m beyond it, if ``zebra``)
    on a stop-sign arm where ``share`` of the cross streets have two lanes, then read the road turned into 40
    degrees into the turn, its centre line ``centre_along_m`` beyond the bar's near edge."""

    from towndrive.agent.decision.junction import JunctionGuidance
    from towndrive.agent.perception.stop_line import StopLine
    from towndrive.sim.spec import CrossStreetOdds, TurnReach

    road = replace(road_priors("suburb"), turn_reaches=(TurnReach(1, 14.0, 11.0), TurnReach(2, 15.5, 9.0)),
                   cross_street_odds=(CrossStreetOdds("stop", 1, share, 8),))
    line = tracked_bar()
    odo = approach_odometry()
    g = JunctionGuidance(JunctionRules(), line, odo, 1.0, road)
    # the bar's near edge at x = 11 in the odometry frame, the zebra's far edge 6 m beyond the bar's far edge
    g.note(StopLine(8.0, 0.5, 0.9, 0), 8.0 + 0.5 + 6.0 if zebra else None, 3.2, None, "stop", 1)
    odo.pos = np.array([11.0, 0.0])
    assert g.turn_steer(command, 3.0) is not None
    see_cross_centre_line(g, command, centre_along_m, 40.0)
    assert g.exit_measured
    return g


def test_a_right_turn_read_in_the_turn_keeps_within_reach_of_every_count_the_centre_line_leaves() -> None:
    """``JunctionGuidance.exit_odds``: the road turned into's centre line lies a lane farther beyond the zebra on
    a two-lane street than on a single-lane one (less its parking strip), so the reading tells the likelier count
    (with no zebra measured, the odds of the kind of junction seen alone). A right turn leans toward the kerb lane
    as far as two lanes are likely, but no farther than the car's room from the single lane's place (the inner lane
    of two): aimed at the kerb lane of two, it leaves the road if the street has one. A left turn goes into the
    inner lane."""

    depth = ROAD.stop_bar_depth_m
    w = read_turn(2, 20.0, True, 0.5).lane_width_m
    for lanes, kerb_reach in ((1, 11.0), (2, 9.0)):
        inner = 6.0 + kerb_reach + (lanes - 1) * w  # bar's far edge to the inner lane's crossing
        g = read_turn(2, inner + depth + 0.5 * w, True, 0.5)
        odds = g.exit_odds()
        assert likeliest(g) == lanes and odds[lanes] > 0.9 and sum(odds.values()) == pytest.approx(1.0)
        room = g.lane_room_m
        assert g.turn_reach_m(2) == pytest.approx(inner - min(room, odds[2] * w), abs=1e-6)
    assert g.turn_reach_m(2) == pytest.approx(inner - room)  # two lanes likely: as far as one lane's place lets
    # the same reading at a kind of junction where two-lane streets are rare, and where they are the rule:
    # a reading midway leans to the odds
    midway = 6.0 + 11.0 + 0.5 * (9.0 + w - 11.0)
    assert likeliest(read_turn(2, midway + depth + 0.5 * w, True, 0.05)) == 1
    assert likeliest(read_turn(2, midway + depth + 0.5 * w, True, 0.95)) == 2
    # no zebra: the odds alone
    for share, lanes in ((0.3, 1), (0.8, 2)):
        g = read_turn(2, 6.0 + 9.0 + w + depth + 0.5 * w, False, share)
        assert likeliest(g) == lanes
        assert g.turn_reach_m(2) == pytest.approx(g._exit_fix[0] - min(g.lane_room_m, share * w))
    # a left turn goes into the inner lane whatever the count
    g = read_turn(1, 6.0 + 15.5 + depth - 0.5 * w, True, 0.95)
    assert g.turn_reach_m(1) == pytest.approx(6.0 + 15.5, abs=1e-6)


def test_the_arc_is_driven_at_its_curve_speed_only_once_the_road_turned_into_leaves_no_count_in_doubt() -> None:
    """``JunctionGuidance.arc_radius_m``, which the controller drives the arc at the curve speed of: set once the
    road turned into is read and tells its lane count, not while a count in doubt keeps the turn within reach of
    both (driven fast, the car reached the hedged arc's start before the reading settled, and the settled reach bent
    the kept arc round inside the lane turned into). A left turn's inner lane does not depend on the count; an exact
    design's arc, which is not read, keeps the turn speed."""
    depth, w = ROAD.stop_bar_depth_m, 3.2
    clear = read_turn(2, 6.0 + 11.0 + depth + 0.5 * w, True, 0.2)  # where one lane puts it: one lane
    assert min(clear.exit_odds().values()) < COUNT_DOUBT
    clear.turn_steer(2, 3.0)
    assert clear.arc_radius_m is not None and clear.arc_radius_m > 5.0
    midway = read_turn(2, 6.0 + 11.0 + 0.5 * (9.0 + w - 11.0) + depth + 0.5 * w, True, 0.5)
    assert min(midway.exit_odds().values()) > COUNT_DOUBT  # either count may be
    midway.turn_steer(2, 3.0)
    assert midway.arc_radius_m is None
    left = read_turn(1, 6.0 + 15.5 + depth - 0.5 * w, True, 0.5)
    left.turn_steer(1, 3.0)
    assert left.arc_radius_m is not None
    # the classic design's exact arc is not read: the turn speed

    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules
    from towndrive.agent.perception.stop_line import StopLine

    line = tracked_bar()
    odo = approach_odometry()
    exact = JunctionGuidance(JunctionRules(), line, odo, 1.0, ROAD)
    exact.note(StopLine(8.0, 0.5, 0.9, 0))
    odo.pos = np.array([11.0, 0.0])  # at the bar
    assert exact.turn_steer(2, 3.0) is not None and exact.arc_radius_m is None


def test_the_turn_speed_on_an_arc_placed_by_the_road_turned_into_is_its_curve_speed() -> None:
    """``Controller._turn_cap``: on the arc, the turn speed (3 m/s) where its radius is not known to hold, the curve
    speed sqrt(lateral acceleration x radius) where it is; before the arc, what braking brings down to it."""
    from towndrive.agent.decision.controller import Controller, Scene

    ctrl = Controller()
    cfg = ctrl.config
    on_arc = Scene(4.0, turning=True, arc_ahead_m=-1.0)
    assert ctrl._turn_cap(on_arc, 0.5) == pytest.approx(cfg.junction_turn_speed_mps)
    assert ctrl._turn_cap(replace(on_arc, arc_radius_m=12.0), 0.5) == pytest.approx(math.sqrt(cfg.lateral_accel_mps2 * 12.0))
    before = replace(on_arc, arc_radius_m=12.0, arc_ahead_m=20.0)
    assert ctrl._turn_cap(before, 0.0) > math.sqrt(cfg.lateral_accel_mps2 * 12.0)


def test_a_right_turn_from_the_inner_lane_of_two_goes_into_the_inner_lane_whatever_the_cross_streets_count() -> None:
    """``sim.spec.right_turn_lanes_from_kerb`` in ``JunctionGuidance``: a right turn keeps its lane counted from the
    kerb (the town's connectors do), so from the inner lane of two it ends in the inner lane of the road turned
    into, one lane or two: the centre line read in the turn places it, whatever count ``exit_odds`` makes likeliest, and
    the plan before the read is kept within the car's room of both counts' inner lanes. From the kerb lane, the
    kerb lane."""

    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules
    from towndrive.agent.perception.stop_line import StopLine
    from towndrive.sim.spec import CrossStreetOdds, TurnReach

    road = replace(road_priors("downtown"), turn_reaches=(TurnReach(1, 14.4, 10.8), TurnReach(2, 15.7, 8.6)),
                   cross_street_odds=(CrossStreetOdds("stop", 2, 0.9, 8),), lane_width_m=3.5, lane_width_sd_m=0.0)

    def read(lanes_to_kerb: int, centre_along_m: float | None) -> JunctionGuidance:
        line = tracked_bar()
        odo = approach_odometry()
        g = JunctionGuidance(JunctionRules(), line, odo, 1.0, road)
        g.note(StopLine(8.0, 0.5, 0.9, 0), 8.0 + 0.5 + 6.0, 3.5, None, "stop", 2, lanes_to_kerb)
        odo.pos = np.array([11.0, 0.0])
        assert g.turn_steer(2, 3.0) is not None
        if centre_along_m is not None:
            see_cross_centre_line(g, 2, centre_along_m, 40.0)
            assert g.exit_measured
        return g

    depth, w = road.stop_bar_depth_m, 3.5
    room = read(1, None).lane_room_m
    inner = {1: 6.0 + 10.8, 2: 6.0 + 8.6 + w}  # the bar's far edge to each count's inner lane
    planned = read(1, None).planned_reach_m(2)
    assert all(abs(planned - reach) <= room + 1e-9 for reach in inner.values())
    for reach in inner.values():
        g = read(1, reach + depth + 0.5 * w)
        assert g.turn_reach_m(2) == pytest.approx(reach, abs=1e-6)  # the inner lane, whichever count
    # from the kerb lane, toward the kerb lane of as many lanes as the odds say, as far as the single lane's place
    # lets; once a reading leaves one lane unlikely (under COUNT_DOUBT), the kerb lane of two
    assert read(0, None).planned_reach_m(2) == pytest.approx(6.0 + 10.8 - room)
    g = read(0, inner[2] + depth + 0.5 * w)
    assert g.exit_odds()[1] < COUNT_DOUBT and g.turn_reach_m(2) == pytest.approx(6.0 + 8.6, abs=0.05)


def test_the_line_on_our_right_tells_how_many_lanes_lie_between_ours_and_the_kerb() -> None:
    from types import SimpleNamespace

    from towndrive.agent.decision.signs import lanes_to_kerb
    from towndrive.agent.perception.lanes import LaneLine

    def result(right: LaneLine | None) -> SimpleNamespace:
        return SimpleNamespace(detected=right is not None, left=None, right=right)

    def line(color: str, style: str) -> LaneLine:
        return LaneLine(np.zeros(3), (4.0, 20.0), 0.9, 300, color, style, 0.5)

    assert lanes_to_kerb(result(line("white", "solid"))) == 0
    assert lanes_to_kerb(result(line("white", "dashed"))) == 1
    assert lanes_to_kerb(result(line("white", "unknown"))) is None
    assert lanes_to_kerb(result(line("yellow", "solid"))) is None
    assert lanes_to_kerb(result(None)) is None and lanes_to_kerb(None) is None


def test_the_lanes_to_the_kerb_describe_the_lane_they_were_read_in() -> None:
    """``KerbLanes``: a reading of the line on our right is kept while the car drives on in its lane, and forgotten
    once it has moved half a lane sideways (its own lane change into the kerb lane, with no line read there) or
    travelled ``forget_after_m`` without a fresh reading; a fresh reading starts afresh from where it was taken."""
    import math

    from towndrive.agent.decision.signs import KerbLanes

    heading = math.radians(30.0)
    along, across = np.array([math.cos(heading), math.sin(heading)]), np.array([-math.sin(heading), math.cos(heading)])
    kerb = KerbLanes(forget_after_m=25.0, lane_width_m=3.5)
    start = np.array([10.0, -4.0])
    assert kerb.note(1, tuple(start), heading) == 1
    assert kerb.note(None, tuple(start + 20.0 * along + 1.0 * across), heading) == 1  # drifting within its lane
    assert kerb.note(None, tuple(start + 20.0 * along + 2.0 * across), heading) is None  # a lane change
    assert kerb.note(0, tuple(start + 22.0 * along + 3.5 * across), heading) == 0  # read afresh in the new lane
    assert kerb.note(None, tuple(start + 46.0 * along + 3.5 * across), heading) == 0
    assert kerb.note(None, tuple(start + 48.0 * along + 3.5 * across), heading) is None  # too far since
    kerb.note(1, (0.0, 0.0), 0.0)
    kerb.forget()
    assert kerb.count is None


def test_a_turn_under_way_is_not_held_straight_when_the_command_moves_on() -> None:
    """Leaving a junction by a turn, the route's command already announces the next junction: "straight" there
    must not hand the car, still on the turn's arc, to the straight hold, which steered it back to the approach
    lane's heading and across the oncoming lanes (a downtown vehicle collision). Going straight, it still holds."""
    from types import SimpleNamespace

    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules

    line = SimpleNamespace(ignore_light_m=20.0, junction_ignore_m=30.0, stop_line_measured=True, stop_line=None,
                           config=SimpleNamespace(camera_to_front_m=2.0))  # the bumper 10 m past the bar
    odo = approach_odometry(pos=(14.0, 3.0))
    odo.yaw = math.radians(45.0)  # half way round a right turn
    g = JunctionGuidance(JunctionRules(), line, odo, 1.0, road_priors("downtown"))  # type: ignore[arg-type]
    g.junction = (5.0, 0.0, 0.0, 2)  # its bar, and the right turn under way
    assert g.arc_leads and g.hold(3) is None
    g.junction = (5.0, 0.0, 0.0, 0)  # no turn begun here: straight on
    assert g.hold(3) == pytest.approx(-g.rules.hold_max_steer)  # back onto the approach lane's heading


def test_going_straight_the_hold_keeps_to_the_far_sides_lane_once_read() -> None:
    """``JunctionGuidance._note_far``: going straight through a junction of a winding street, the far side's centre
    line (read as the road turned into is) places the lane the hold keeps to: half a lane width to its right, at its
    heading, each weighed against how far the design lets the far side lie and turn; before it is read, or where a
    reading lies a lane or more across, the approach lane's line as before. A design whose far side lies exactly
    where the approach lane carried on would (the classic one, downtown's grid) reads nothing."""
    from types import SimpleNamespace

    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules
    from towndrive.agent.perception.exit_line import ExitLine

    def holding(road: object, line_x_m: float, line_deg: float) -> JunctionGuidance:
        rules = JunctionRules()
        line = SimpleNamespace(ignore_light_m=5.0, junction_ignore_m=5.0, stop_line_measured=True, stop_line=None,
                               config=SimpleNamespace(camera_to_front_m=2.0))  # the bumper just past the bar
        odo = approach_odometry(pos=(10.0, 0.0))
        g = JunctionGuidance(rules, line, odo, 1.0, road)  # type: ignore[arg-type]
        assert g.hold(3) == pytest.approx(0.0)  # on the approach lane's line, on its heading
        expected = g.exit_expected_rad()
        if road.far_lane_shift_sd_m == 0:
            assert expected is None and g.far_corridor() is None
            return g
        assert expected == pytest.approx(0.0)  # the far side is looked for straight ahead, along our road's centre
        assert g.far_corridor() == pytest.approx((-0.5 * g.lane_width_m, -1.0, rules.far_max_shift_m))  # line
        # the far side's centre line seen 15 m ahead of the camera, line_x_m across (x right), turned line_deg
        for _ in range(3):
            g.note_exit(ExitLine((line_x_m, 15.0), math.radians(line_deg), 300, 8.0))
        return g

    from towndrive.agent.decision.junction import FAR_ANGLE_SD_DEG, FAR_SD_M

    road = road_priors("suburb")
    w = road.lane_width_m
    shift_weight = road.far_lane_shift_sd_m ** 2 / (road.far_lane_shift_sd_m ** 2 + FAR_SD_M ** 2)
    turn_weight = road.far_lane_turn_sd_deg ** 2 / (road.far_lane_turn_sd_deg ** 2 + FAR_ANGLE_SD_DEG ** 2)
    assert 0.5 < shift_weight < 1.0 and 0.5 < turn_weight < 1.0  # the suburb's far sides shift and turn: mostly read
    g = holding(road, -0.5 * w + 0.8, 0.0)  # the far side's lane lies 0.8 m right of ours
    assert g.far_lane == pytest.approx((26.0, 0.8, 0.0))  # 15 m ahead of the camera, 1 m ahead of the car's centre
    assert g.hold(3) == pytest.approx(g.rules.hold_offset_gain * 0.8 * shift_weight)  # steers right, towards it
    g = holding(road, -0.5 * w, 3.0)  # ... running 3 degrees right of the approach
    assert math.degrees(g.far_lane[2]) == pytest.approx(3.0)
    g.odo.pos = np.array([g.far_lane[0], g.far_lane[1]])  # on that lane, on the approach's heading
    assert g.hold(3) == pytest.approx(g.rules.hold_heading_gain * math.radians(3.0) * turn_weight, rel=0.05)
    # the same readings in a design whose far side lies exactly on: nothing read, the approach lane held
    exact = holding(road_priors("downtown"), -0.5 * road_priors("downtown").lane_width_m + 0.8, 0.0)
    assert exact.far_lane is None and exact.hold(3) == pytest.approx(0.0)
    assert holding(road, -0.5 * w + 3.0, 0.0).far_lane is None  # a lane and more across: something else
    assert holding(road, -0.5 * w, 15.0).far_lane is None  # turned too far
    assert holding(ROAD, -0.5 * ROAD.lane_width_m + 0.8, 3.0).far_lane is None


def test_a_kind_of_junction_seen_only_a_few_times_leaves_the_other_lane_count_possible() -> None:
    """Eight stop-sign arms, all entering two-lane streets, do not make a single-lane street impossible: a turn
    planned on certainty leaves the road where it is one. The share is drawn towards the style's overall share as
    far as the kind was seen at few junctions; one seen at many keeps its own."""
    from towndrive.sim.road_priors import ODDS_PRIOR_JUNCTIONS, cross_street_odds
    from towndrive.sim.spec import COUNT_DOUBT

    samples = {"odds:stop:1": np.ones(8), "odds:signal:2": np.array([1.0, 0.0] * 100)}
    odds = {o.control: o for o in cross_street_odds(samples)}
    overall = 108 / 208
    assert odds["stop"].two_lane_share == pytest.approx((8 + ODDS_PRIOR_JUNCTIONS * overall)
                                                        / (8 + ODDS_PRIOR_JUNCTIONS), abs=1e-3)
    assert 1.0 - odds["stop"].two_lane_share >= COUNT_DOUBT and odds["stop"].junctions == 8
    assert odds["signal"].two_lane_share == pytest.approx(0.5, abs=0.01)
    for style in ("downtown", "suburb"):  # every kind the styles' training towns show
        for o in road_priors(style).cross_street_odds:
            assert 0.0 < o.two_lane_share < 1.0


def placed_turn() -> object:
    """Junction guidance on the suburb priors with the stop bar's near edge at x = 11 of the odometry frame."""

    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules
    from towndrive.agent.perception.stop_line import StopLine

    line = tracked_bar()
    g = JunctionGuidance(JunctionRules(), line, approach_odometry(), 1.0, road_priors("suburb"))
    g.note(StopLine(8.0, 0.5, 0.9, 0))
    return g


def drive_arc(g: object, command: int, until_deg: float, speed_mps: float = 3.0) -> float:
    """Drive the car's centre on the bicycle model by the arc's steer until it has turned ``until_deg``; the last
    steer."""
    from towndrive.sim.spec import VEHICLE

    odo, dt, steer = g.odo, 0.05, 0.0  # type: ignore[attr-defined]
    odo.pos = np.array([5.0, 0.0])
    for _ in range(400):
        target = g.turn_steer(command, speed_mps)  # type: ignore[attr-defined]
        steer = 0.0 if target is None else target
        if abs(odo.yaw) >= math.radians(until_deg):
            return steer
        delta = steer * VEHICLE.max_steer_rad
        beta = math.atan(math.tan(delta) / 2)
        odo.pos = odo.pos + speed_mps * dt * np.array([math.cos(odo.yaw + beta), math.sin(odo.yaw + beta)])
        odo.yaw += speed_mps * dt * math.sin(beta) / (VEHICLE.length_m / 2)
    raise AssertionError("the arc never turned the car that far")


def test_a_reading_in_the_turn_moves_the_arcs_end_not_where_it_began() -> None:
    """A right turn under way on the arc planned before it: the road turned into, read 1.5 m farther on than
    planned, re-places the arc's end; the car, turning already, keeps turning (the arc's radius grows) instead of
    steering back out to an arc begun later, which it then cannot follow round."""
    g = placed_turn()
    steer = drive_arc(g, 2, 25.0)
    assert steer > 0.3
    planned = g.planned_reach_m(2)  # type: ignore[attr-defined]
    depth = g.road.stop_bar_depth_m  # type: ignore[attr-defined]
    inner = planned + depth + 0.5 * g.lane_width_m + 1.5  # type: ignore[attr-defined]
    for _ in range(3):
        g.note_exit(cross_line_seen(g.odo, inner, 90.0))  # type: ignore[attr-defined]
    assert g.exit_measured and g.turn_reach_m(2) > planned + 0.5  # type: ignore[attr-defined]
    assert g.turn_steer(2, 3.0) > 0.2  # type: ignore[attr-defined]  (an arc begun later: 0.07)


def test_the_cross_streets_direction_read_from_a_short_line_leans_on_the_zebras() -> None:
    """``JunctionGuidance.note_exit``: a centre line seen over a few metres, far off, runs up to 10 degrees off
    (its paint smears along the line of sight); weighed against the cross street's angle read from the zebra before
    the turn, its reach is off by a fraction of what its own direction, carried 8 m across, would make it. A line
    seen long is taken as it runs."""
    from towndrive.agent.perception.stop_line import StopLine

    def reach_read(length_m: float, misread_deg: float) -> tuple[float, float]:
        g = placed_turn()
        for _ in range(3):  # the zebra's edges square to our road
            g.note(StopLine(6.0, 0.5, 0.9, 0), None, None, 0.0)  # type: ignore[attr-defined]
        drive_arc(g, 2, 30.0)
        centre = g.planned_reach_m(2) + g.road.stop_bar_depth_m  # type: ignore[attr-defined]
        for _ in range(3):
            g.note_exit(cross_line_seen(g.odo, centre, 90.0, length_m, misread_deg=misread_deg))  # type: ignore
        reach, angle = g._exit_fix  # type: ignore[attr-defined]
        return reach - (centre - 0.5 * g.lane_width_m - g.road.stop_bar_depth_m), angle  # type: ignore[attr-defined]

    # the line's point is true; only its direction is read off (a short line: 10 degrees less turned)
    true = reach_read(3.5, 0.0)
    assert true[0] == pytest.approx(0.0, abs=0.05) and true[1] == pytest.approx(90.0, abs=0.01)
    short = reach_read(3.5, -10.0)
    assert abs(short[0]) < 0.1 and abs(short[1] - 90.0) < 0.5  # its own direction: 1.4 m and 10 degrees off
    long = reach_read(20.0, -5.0)  # a long line is believed
    assert long[1] == pytest.approx(85.0, abs=0.5)


def test_the_line_beside_the_cross_streets_centre_line_tells_its_lane_count() -> None:
    """``JunctionGuidance.exit_odds``: with the centre line where either count could put it, the white line a lane
    to its right tells them apart: solid (painted over most of its length) a single lane's edge line, dashed the
    divider of two lanes; a single frame's odd reading does not overturn the rest."""
    def odds(fills: list[float | None]) -> dict[int, float]:
        g = placed_turn()
        drive_arc(g, 2, 30.0)
        centre = g.planned_reach_m(2) + g.road.stop_bar_depth_m + 0.5 * g.lane_width_m  # type: ignore[attr-defined]
        for fill in fills:
            g.note_exit(cross_line_seen(g.odo, centre, 90.0, fill=fill))  # type: ignore[attr-defined]
        return g.exit_odds()  # type: ignore[attr-defined]

    unread = odds([None, None, None])
    assert 0.05 < unread[2] < 0.95  # the centre line alone leaves it open
    assert odds([0.9, 0.95, 1.0])[1] > 0.9
    assert odds([0.4, 0.3, 0.45])[2] > 0.9
    assert odds([0.1, 0.9, 0.95, 1.0])[1] > 0.9


def test_a_bar_read_with_the_car_turned_away_from_its_lane_places_no_turn() -> None:
    """``JunctionGuidance.note``: turned more than ``place_max_turned_deg`` from the approach lane, paint read as a
    bar ahead lies across the road being turned into (its zebra, another arm's line), not on the approach; placed,
    it set a turn's arc in the approach lane's frame from the middle of the turn."""
    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules
    from towndrive.agent.perception.stop_line import StopLine

    rules = JunctionRules()
    for turned_deg, placed in ((rules.place_max_turned_deg + 20.0, False), (rules.place_max_turned_deg / 2, True)):
        odo = approach_odometry()
        odo.yaw = math.radians(turned_deg)  # turned since the car last drove along its lane (approach_yaw 0)
        g = JunctionGuidance(rules, tracked_bar(), odo, 1.0, road_priors("suburb"))
        g.note(StopLine(8.0, 0.5, 0.9, 0))
        assert g.placed is placed


def test_the_rest_of_a_turn_from_the_car_s_pose_ends_on_the_lane_turned_into() -> None:
    """``arc_from_pose``: from a car already turned part way (its centre off the approach lane's line), straight on
    along its heading, then the design's radius when there is room, else tighter, ending along the lane turned into
    (whose centre line crosses the approach lane's ``reach`` beyond the bar's far edge at the turn's angle)."""
    from towndrive.agent.decision.junction import arc_from_pose

    for command, side in ((2, 1.0), (1, -1.0)):
        for (along, across, heading_deg), radius, room in (((4.0, 0.3, 10.0), 8.0, True), ((9.4, 1.0, 15.0), 10.0, False)):
            placed = arc_from_pose(command, (along, side * across), side * math.radians(heading_deg), 16.6, 0.5,
                                   radius, 97.0)
            assert placed is not None
            path, begins, ends, r = placed
            k0, k1 = int(round(begins / 0.2)), int(round(ends / 0.2))
            # through the car's centre, along its heading
            assert np.min(np.hypot(*(path - np.array([along, side * across])).T)) < 0.15
            d0 = path[k0] - path[k0 - 5]
            assert math.degrees(math.atan2(side * d0[1], d0[0])) == pytest.approx(heading_deg, abs=0.5)
            d1 = path[-1] - path[k1]
            assert math.degrees(math.atan2(side * d1[1], d1[0])) == pytest.approx(97.0, abs=0.5)
            crossing = path[k1][0] - path[k1][1] * d1[0] / d1[1]  # the exit line, carried back to our lane's line
            assert crossing == pytest.approx(0.5 + 16.6, abs=0.1)
            assert (r == radius) is room and (r <= radius)
    assert arc_from_pose(2, (10.0, 5.0), math.radians(100.0), 16.6, 0.5, 8.0, 97.0) is None  # already along it


def test_a_turn_read_to_end_elsewhere_after_its_arc_began_is_re_placed_from_where_the_car_is() -> None:
    """``JunctionGuidance.turn_steer``: the arc's start committed for one reach, a reading well on in the turn
    that puts the lane turned into 2.2 m farther (the other lane count) would stretch the arc from that start to a
    radius far from the design's; the rest of the turn is re-placed from the car's pose on the design's radius
    instead (``replace_radius_m``), which keeps nearer the lanes (the stretched arc cuts inside the corner)."""
    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules

    rules = JunctionRules()
    odo = approach_odometry()
    g = JunctionGuidance(rules, tracked_bar(), odo, 1.0, road_priors("suburb"))
    g.junction = (11.0, 0.0, 0.0, 2)  # a right turn under way, the bar's near edge at x = 11
    g._arc_start_m = 5.0
    g._exit_fix = (14.4, 90.0)  # read: the arc from 5.0 m needs no stretching
    odo.pos, odo.yaw = np.array([11.0 + 9.4, 1.0]), math.radians(15.0)
    g.turn_steer(2, 3.0)
    assert g._replaced is None
    g._exit_fix = (14.4 + 2.2 + 4.0, 90.0)  # read on, far from where the arc from 5.0 m ends on the design's radius
    g.turn_steer(2, 3.0)
    assert g._replaced is not None
    (path, begins, ends, radius), reach, angle = g._replaced
    assert np.min(np.hypot(*(path - np.array([9.4, 1.0])).T)) < 0.15  # from where the car is
    assert g.arc_ahead_m is not None and g.arc_ahead_m >= -0.2
