"""The full agent: box geometry, that it drives from observations alone, and one closed-loop scenario."""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from towndrive.agent.agent_driver import DEFAULT_DETECTOR, STAGES
from towndrive.agent.perception.box_geometry import BoxGeometry
from towndrive.agent.perception.pilotnet import DEFAULT_MODEL
from towndrive.sim.render import CameraConfig

needs_models = pytest.mark.skipif(not (DEFAULT_MODEL.is_file() and DEFAULT_DETECTOR.is_file()),
                                  reason="the shipped PilotNet and detector models are not in data/models")


def test_box_geometry_recovers_distance_and_lateral_position() -> None:
    cam = CameraConfig()
    geo = BoxGeometry(cam)
    for z, x in ((8.0, 0.0), (15.0, 3.5), (25.0, -3.5)):
        (u, v), = geo.birdseye.image_of_ground(np.array([x]), np.array([z]))
        h_px = geo.f * 1.5 / z  # a 1.5 m tall car
        box = (u - 10.0, v - h_px, u + 10.0, v)
        d = geo.distance(box, "car")
        assert d == pytest.approx(z, rel=0.04)
        assert geo.lateral(u, d) == pytest.approx(x, abs=0.15 + 0.02 * z)
    # cut off at the bottom of the picture: never farther than the last image row's road
    assert geo.distance((100.0, 60.0, 200.0, cam.height), "car") <= float(geo.birdseye.ground_z_of_row(np.array([cam.height]))[0])


def our_light(driver):
    """The agent's choice of our light among ``driver._lights`` (the latest light detections)."""
    return driver.stages.light.choose(driver._lights, driver.controller.line, driver.stages.odometry.turned)


def light_box(driver, lateral_m: float, z_m: float) -> tuple[float, float, float, float]:
    """The box a signal head (5.2 m high, 2.1 m tall) at camera-frame ``lateral_m``, ``z_m`` would get."""
    import math

    from towndrive.sim.spec import ROAD

    LIGHT_HEAD_HEIGHT_M, LIGHT_HOUSING_M = ROAD.signal_head_height_m, ROAD.signal_housing_height_m

    cam, k, f = driver.camera, driver.geometry.k, driver.geometry.f
    above_axis = math.atan((LIGHT_HEAD_HEIGHT_M - cam.mount_height_m) / z_m) - math.radians(cam.pitch_deg)
    v, u = float(k[1, 2]) - f * math.tan(above_axis), float(k[0, 2]) + f * lateral_m / z_m
    half_h, half_w = f * LIGHT_HOUSING_M / z_m / 2, f * 0.5 / z_m
    return (u - half_w, v - half_h, u + half_w, v + half_h)


def rotated(lateral_m: float, z_m: float, turned_rad: float) -> tuple[float, float]:
    """Where a point of the approach lane's frame appears after the car turned right by ``turned_rad``."""
    import math

    c, s = math.cos(turned_rad), math.sin(turned_rad)
    return lateral_m * c - z_m * s, lateral_m * s + z_m * c


@needs_models
def test_our_light_is_the_one_across_the_junction_not_the_cross_streets() -> None:
    from towndrive.agent.drivers import make_driver
    from towndrive.agent.perception.classes import CLASSES
    from towndrive.agent.perception.detector import Detection
    from towndrive.envs.drive_env import DriveConfig

    driver = make_driver("agent")
    driver.reset(SimpleNamespace(config=DriveConfig()))
    red, green = CLASSES.index("light_red"), CLASSES.index("light_green")
    # Ours hangs 21 m beyond the line over our lane's divider; the cross street's (green while ours is red)
    # hangs on the near right corner, over our lane's edge, 12 m nearer (as measured in the town).
    line_m = 2.0
    ours = Detection(light_box(driver, -1.75, line_m + 1.3 + 21.4), red, 0.9)
    theirs = Detection(light_box(driver, 3.4, line_m + 1.3 + 9.5), green, 0.9)
    driver._lights = [ours, theirs]
    assert our_light(driver).state == "green"  # stop line not yet seen: the nearest light near the axis wins
    driver.controller.stop_line, driver.controller.stop_line_measured = line_m, True
    seen = our_light(driver)
    assert seen.state == "red" and seen.distance_m == pytest.approx(line_m + 1.3 + 21.4, rel=0.05)

    # Turning right before the line: the camera swings, the cross street's head comes over the axis.
    driver.controller.stop_line, driver.controller.stop_line_measured = None, False
    driver.stages.odometry.yaw, driver.stages.odometry.approach_yaw = 0.5, 0.0
    driver._lights = [Detection(light_box(driver, *rotated(-1.75, 24.0, 0.5)), red, 0.9),
                      Detection(light_box(driver, *rotated(9.0, 14.0, 0.5)), green, 0.9)]
    assert abs(rotated(9.0, 14.0, 0.5)[0]) < 2.0  # the distractor is near the camera axis
    assert our_light(driver).state == "red"
    driver.stages.odometry.yaw = 0.0  # without the heading change the distractor would be taken
    assert our_light(driver).state == "green"


def blind_world_and_agent():
    """A camera-less env (its world moves the car by the same bicycle model) and an agent set up for it."""
    from towndrive.agent.drivers import make_driver
    from towndrive.envs.drive_env import DriveConfig, DriveEnv

    env = DriveEnv(DriveConfig(render_camera=False))
    env.reset(seed=1)
    driver = make_driver("agent")
    driver.reset(SimpleNamespace(config=env.config))
    return env, env.world, driver


@needs_models
def test_agent_dead_reckons_its_heading_from_speed_and_steering() -> None:
    env, world, driver = blind_world_and_agent()
    world.ego.speed = 5.0
    h0 = world.ego.heading
    for k in range(40):
        steer = 0.4 if k < 20 else -0.2
        env.step(np.array([steer, 0.0], np.float32))
        driver.stages.odometry.advance(float(world.ego.speed), steer, 2, driver.dt)
    assert driver.stages.odometry.yaw == pytest.approx(world.ego.heading - h0, abs=0.02)
    assert driver.stages.odometry.approach_yaw == 0.0  # a commanded turn under way: the approach heading stays
    env.close()


def car_beside_box(geo: BoxGeometry, inner_m: float, near_m: float, length_m: float = 4.5,
                   width_m: float = 1.9) -> np.ndarray:
    """The box of a 1.5 m tall car parked parallel to us, wholly left of the axis: near face at ``near_m``,
    inner side ``inner_m`` metres left. Its right box edge comes from its far inner corner."""
    outer = -(inner_m + width_m)
    (u_out, v_bottom), = geo.birdseye.image_of_ground(np.array([outer]), np.array([near_m]))
    (u_in, _), = geo.birdseye.image_of_ground(np.array([-inner_m]), np.array([near_m + length_m]))
    return np.array([u_out, v_bottom - geo.f * 1.5 / near_m, u_in, v_bottom])


def car_across_box(geo: BoxGeometry, inner_m: float, near_m: float, length_m: float = 4.5,
                   width_m: float = 1.9) -> np.ndarray:
    """The box of a 1.5 m tall car standing across our axis, wholly left of it, its side towards us: near side
    at ``near_m`` spanning ``inner_m`` to ``inner_m + length_m`` left; the right box edge from its far inner corner."""
    (u_out, v_bottom), = geo.birdseye.image_of_ground(np.array([-(inner_m + length_m)]), np.array([near_m]))
    (u_in, _), = geo.birdseye.image_of_ground(np.array([-inner_m]), np.array([near_m + width_m]))
    return np.array([u_out, v_bottom - geo.f * 1.5 / near_m, u_in, v_bottom])


@needs_models
def test_a_car_wholly_beside_the_axis_is_placed_by_its_far_corner_not_nearer() -> None:
    from towndrive.agent.drivers import make_driver
    from towndrive.agent.perception.classes import CLASSES
    from towndrive.agent.perception.tracking import Track
    from towndrive.envs.drive_env import DriveConfig

    driver = make_driver("agent")
    driver.reset(SimpleNamespace(config=DriveConfig()))
    box = car_beside_box(driver.geometry, inner_m=2.5, near_m=4.4)
    track = Track(7, box, hits=10, age=10, time_since_update=0, label=CLASSES.index("car"))
    naive = driver.geometry.lateral(box[2], driver.geometry.distance(box, "car"))
    half = driver.controller.config.path_half_width_m
    assert naive > -half  # read at its near face, the car 2.5 m to our left would be in our 1.3 m corridor
    first = driver.stages.objects.update([track], 0.0, None)[0]
    # no history yet: its box's shape says it stands lengthwise, and it is read by its length at once
    assert -2.5 - 0.1 <= first.lateral_right_m <= -half - 0.3
    for k in range(1, 8):  # standing still for 0.35 s
        obj = driver.stages.objects.update([track], 0.05 * k, None)[0]
    assert -2.5 - 0.1 <= obj.lateral_right_m <= -half - 0.3  # clear of the corridor, never beyond the truth
    # a car standing across, its box drifting sideways towards us, keeps the conservative near-face reading
    driver.reset(SimpleNamespace(config=DriveConfig()))
    across = car_across_box(driver.geometry, inner_m=2.5, near_m=8.0)
    for k in range(13):
        moving = Track(8, across + np.array([2.5 * k, 0, 2.5 * k, 0]), hits=10, age=10, time_since_update=0,
                       label=CLASSES.index("car"))
        obj = driver.stages.objects.update([moving], 0.05 * k, None)[0]
    assert obj.lateral_right_m == pytest.approx(driver.geometry.lateral(moving.box[2], obj.distance_m))


@needs_models
def test_a_car_parked_lengthwise_is_placed_by_its_length_and_one_across_by_its_width() -> None:
    """The box's width tells a car standing lengthwise (parked at the kerb) from one standing across: the first
    is read its length beyond its near face, so a parked car 1.2 m beside the axis is no longer put in our
    1.3 m corridor (read by its width it was 0.3 m nearer); one across is read by its width, never beyond it."""
    from towndrive.agent.drivers import make_driver
    from towndrive.agent.perception.classes import CLASSES
    from towndrive.agent.perception.tracking import Track
    from towndrive.envs.drive_env import DriveConfig

    driver = make_driver("agent")
    half = driver.controller.config.path_half_width_m
    for make, inner, near in ((car_beside_box, 1.4, 5.0), (car_beside_box, 1.4, 9.0), (car_across_box, 1.4, 9.0)):
        driver.reset(SimpleNamespace(config=DriveConfig()))
        box = make(driver.geometry, inner_m=inner, near_m=near)
        track = Track(3, box, hits=10, age=10, time_since_update=0, label=CLASSES.index("car"))
        for k in range(8):  # standing still for 0.35 s
            obj = driver.stages.objects.update([track], 0.05 * k, None)[0]
        assert obj.lateral_right_m >= -inner - 0.05  # never beyond the truth
        if make is car_beside_box:
            assert obj.lateral_right_m <= -half  # clear of the corridor
            assert obj.lateral_right_m == pytest.approx(-inner, abs=0.1)


@needs_models
def test_a_near_parked_car_s_box_stopping_short_of_the_image_edge_keeps_it_lengthwise() -> None:
    """Near, a car parked beside our path reaches past the image's side edge whichever way it stands, but the
    detector's box may stop short of it: that edge is the box's, and judged by it the car looked too narrow to
    stand lengthwise, was read by its width, and its inner edge came 0.6 m nearer, into our side (a false hold
    behind a parked car). Such a box is not judged: the judgement made on the whole box farther off stands."""
    from towndrive.agent.drivers import make_driver
    from towndrive.agent.perception.classes import CLASSES
    from towndrive.agent.perception.tracking import Track
    from towndrive.envs.drive_env import DriveConfig

    driver = make_driver("agent")
    driver.reset(SimpleNamespace(config=DriveConfig()))
    geo = driver.geometry
    inner = 1.55
    far = car_beside_box(geo, inner_m=inner, near_m=9.0)
    near = car_beside_box(geo, inner_m=inner, near_m=2.8)
    assert near[0] < 0  # the car itself reaches past the image's left edge
    short = near.copy()
    short[0] = 16.0  # the detector's box ends 16 pixels inside it
    assert geo.shows_outer_edge(far, geo.distance(far, "car"), "car")
    assert not geo.shows_outer_edge(short, geo.distance(short, "car"), "car")
    assert not geo.lengthwise(short, geo.distance(short, "car"), "car")
    label = CLASSES.index("car")
    for k in range(8):  # seen whole farther off, then near with the short box, standing
        obj = driver.stages.objects.update([Track(5, far, hits=10, age=10, time_since_update=0, label=label)],
                                           0.05 * k, None, speed_mps=0.0)[0]
    assert obj.lateral_right_m == pytest.approx(-inner, abs=0.1)
    for k in range(8, 20):
        obj = driver.stages.objects.update([Track(5, short, hits=10, age=10, time_since_update=0, label=label)],
                                           0.05 * k, None, speed_mps=0.0)[0]
    assert obj.lateral_right_m == pytest.approx(-inner, abs=0.25)  # read by its width: a metre nearer


@needs_models
def test_a_car_standing_at_an_angle_to_our_axis_is_not_read_by_its_length() -> None:
    """A car standing 40 degrees off our axis (one waiting in a junction we turn through) draws a box narrower than
    either the lengthwise or the across hypothesis predicts; it is read the safe way, never beyond its nearest
    corner (read by its length, such a car was placed 1.5 m out of our path and hit)."""
    from towndrive.agent.drivers import make_driver
    from towndrive.agent.perception.classes import CLASSES
    from towndrive.agent.perception.tracking import Track
    from towndrive.envs.drive_env import DriveConfig

    driver = make_driver("agent")
    driver.reset(SimpleNamespace(config=DriveConfig()))
    geo = driver.geometry
    yaw = math.radians(40.0)
    along, across = np.array([math.sin(yaw), math.cos(yaw)]), np.array([math.cos(yaw), -math.sin(yaw)])
    centre = np.array([-3.2, 8.5])  # (x right, z ahead) of the camera
    corners = np.array([centre + sa * 2.25 * along + sb * 0.95 * across for sa in (-1, 1) for sb in (-1, 1)])
    uv = geo.birdseye.image_of_ground(corners[:, 0], corners[:, 1])
    z_near = float(corners[:, 1].min())
    box = np.array([uv[:, 0].min(), uv[:, 1].max() - geo.f * 1.5 / z_near, uv[:, 0].max(), uv[:, 1].max()])
    assert not geo.lengthwise(box, z_near, "car")
    # boxes the detector drew: a car standing 40 degrees off our axis in a junction we turned through (6.9 m), too
    # narrow for either hypothesis, and a car parked lengthwise at the kerb (7.6 m)
    assert not geo.lengthwise(np.array([32.0, 65.0, 90.0, 97.0]), 6.9, "car")
    assert geo.lengthwise(np.array([179.0, 64.0, 233.0, 95.0]), 7.6, "car")
    track = Track(4, box, hits=10, age=10, time_since_update=0, label=CLASSES.index("car"))
    for k in range(12):
        obj = driver.stages.objects.update([track], 0.05 * k, None, speed_mps=0.0)[0]
    assert obj.lateral_right_m >= float(corners[:, 0].max()) - 0.1  # not beyond its corner nearest our axis


@needs_models
def test_a_parked_car_passed_at_3_mps_stays_still_and_beside_the_corridor() -> None:
    """Nearing a parked car, its box grows towards the image's edge and is then cut by it; read at its near face,
    the box's centre drifted towards our axis at about half a metre a second, so the car looked as if it pulled
    out and was read at its near face (in our corridor). Followed by its far inner corner it stays put."""
    from towndrive.agent.drivers import make_driver
    from towndrive.agent.perception.classes import CLASSES
    from towndrive.agent.perception.tracking import Track
    from towndrive.envs.drive_env import DriveConfig

    driver = make_driver("agent")
    driver.reset(SimpleNamespace(config=DriveConfig()))
    geo, half = driver.geometry, driver.controller.config.path_half_width_m
    width = geo.camera.width
    cut = False
    for k in range(45):  # 2.25 s at 3 m/s: from 9 m to 2.4 m
        box = car_beside_box(geo, inner_m=1.6, near_m=9.0 - 0.15 * k)
        cut = cut or box[0] < 0
        box = np.clip(box, 0.0, [width - 1, geo.camera.height - 1, width - 1, geo.camera.height - 1])
        track = Track(5, box, hits=10, age=10, time_since_update=0, label=CLASSES.index("car"))
        obj = driver.stages.objects.update([track], 0.05 * k, None, speed_mps=3.0)[0]
        if k >= 8:
            assert abs(obj.lateral_speed_mps) < 0.3, k
            assert -1.6 - 0.1 <= obj.lateral_right_m <= -half, (k, obj.lateral_right_m)
    assert cut  # the last boxes were cut by the image's edge
    for k in range(45, 145):  # then standing beside it for 5 s, its box cut: still read by its length
        obj = driver.stages.objects.update([track], 0.05 * k, None, speed_mps=0.0)[0]
    assert -1.6 - 0.1 <= obj.lateral_right_m <= -half


@needs_models
def test_a_parked_car_passed_at_7_mps_does_not_seem_to_move_sideways() -> None:
    """A still car's inner edge turns faster the nearer we come; its sideways speed is fitted to the positions each
    bearing gives at the depth of its own time (the bearing's rate times today's depth lags and read a parked car
    passed at 7 m/s as moving sideways at 0.3-0.5 m/s)."""
    from towndrive.agent.drivers import make_driver
    from towndrive.agent.perception.classes import CLASSES
    from towndrive.agent.perception.tracking import Track
    from towndrive.envs.drive_env import DriveConfig

    driver = make_driver("agent")
    driver.reset(SimpleNamespace(config=DriveConfig()))
    geo = driver.geometry
    for k in range(30):  # 1.5 s at 7 m/s: from 14 m to 3.8 m
        box = car_beside_box(geo, inner_m=1.6, near_m=14.0 - 0.35 * k)
        track = Track(5, box, hits=10, age=10, time_since_update=0, label=CLASSES.index("car"))
        obj = driver.stages.objects.update([track], 0.05 * k, None, speed_mps=7.0)[0]
        if k >= 10:
            assert abs(obj.lateral_speed_mps) < 0.1, (k, obj.lateral_speed_mps)


@needs_models
def test_a_pedestrian_box_too_small_for_where_it_stands_is_no_person() -> None:
    from towndrive.agent.drivers import make_driver
    from towndrive.agent.perception.classes import CLASSES
    from towndrive.agent.perception.tracking import Track
    from towndrive.envs.drive_env import DriveConfig

    driver = make_driver("agent")
    driver.reset(SimpleNamespace(config=DriveConfig()))
    g = driver.geometry
    rows = np.arange(0.0, 160.0, 0.25)
    y1 = float(rows[np.nanargmin(np.abs(g.birdseye.ground_z_of_row(rows) - 5.0))])  # the road's row 5 m ahead
    whole = g.f * 1.75 / 5.0  # a 1.75 m person there is this many pixels tall
    assert driver.stages.objects.plausible_person(np.array([100.0, y1 - whole, 112.0, y1]))
    assert not driver.stages.objects.plausible_person(np.array([100.0, y1 - 0.6 * whole, 112.0, y1]))  # too short to stand there
    assert not driver.stages.objects.plausible_person(np.array([100.0, y1 - 1.5 * whole, 112.0, y1]))  # too tall
    assert driver.stages.objects.plausible_person(np.array([100.0, 0.0, 130.0, y1]))  # cut at the top: not judged
    # The floor rises with the box's height (its rows are read to a pixel or two): three quarters of a person is
    # within reading error 25 m away, not 2.5 m away (paint by the image's edge scored so at night)
    for z_m, person in ((25.0, True), (2.5, False)):
        bottom = float(rows[np.nanargmin(np.abs(g.birdseye.ground_z_of_row(rows) - z_m))])
        tall = g.f * 1.75 / float(g.birdseye.ground_z_of_row(np.array([bottom]))[0])
        box = np.array([100.0, bottom - 0.75 * tall, 108.0, bottom])
        assert driver.stages.objects.plausible_person(box) is person
    near = float(rows[np.nanargmin(np.abs(g.birdseye.ground_z_of_row(rows) - 2.5))])
    tall = g.f * 1.75 / float(g.birdseye.ground_z_of_row(np.array([near]))[0])
    assert driver.stages.objects.plausible_person(np.array([100.0, near - 0.93 * tall, 130.0, near]))
    # Cut at the bottom: a person 1.6 m ahead shows their head where 1.75 m is at that distance
    head = min(np.arange(-50.0, 80.0, 0.25), key=lambda v: abs(g.height_of_row(v, 1.6) - 1.75))
    assert driver.stages.objects.plausible_person(np.array([100.0, head, 190.0, 170.0]))
    # ... and route 504's box at the left edge, running off the bottom, reaches only 1.2 m there: a car stood 80 s
    assert not driver.stages.objects.plausible_person(np.array([5.0, 75.0, 25.0, 172.0]))
    # Route 517's night junction: the kerb's yellow line at the left border, scored a pedestrian 2.5 m away
    kerb = np.array([2.0, 79.0, 16.0, 149.0])
    assert not driver.stages.objects.plausible_person(kerb)
    track = Track(9, kerb, hits=10, age=10, time_since_update=0, label=CLASSES.index("pedestrian"))
    assert driver.stages.objects.update([track], 0.0, None) == []


@needs_models
def test_a_person_who_leaves_the_view_at_its_side_edge_is_remembered_and_turns_with_us() -> None:
    import math

    from towndrive.agent.decision.controller import PerceivedObject
    from towndrive.agent.drivers import make_driver
    from towndrive.envs.drive_env import DriveConfig

    driver = make_driver("agent")
    driver.reset(SimpleNamespace(config=DriveConfig()))
    w = float(driver.camera.width)
    # Last seen 3.5 m ahead, 3.0-3.6 m right, its box cut by the image's right edge; not in our path.
    side = PerceivedObject(5, "pedestrian", 3.5, 3.0, 3.6, 0.0, 0.0, (w - 20.0, 60.0, w - 1.0, 110.0))
    driver.stages.memory.at_side = {5: side}
    first = driver.stages.memory.recall([], 0.0, driver.stages.odometry.turn, driver.dt)
    assert [o.track_id for o in first] == [5] and first[0].distance_m == 3.5
    driver.stages.memory.at_side = {}
    driver.stages.odometry.turn = 0.1  # we turned 0.1 rad to the right since: it is now more to our left, and farther ahead
    ghost = driver.stages.memory.recall([], 0.0, driver.stages.odometry.turn, driver.dt)[0]
    assert ghost.distance_m == pytest.approx(3.3 * math.sin(0.1) + 3.5 * math.cos(0.1))
    assert 0.5 * (ghost.lateral_left_m + ghost.lateral_right_m) == pytest.approx(3.3 * math.cos(0.1) - 3.5 * math.sin(0.1))
    assert ghost.lateral_right_m - ghost.lateral_left_m == pytest.approx(0.6)


@needs_models
def test_a_person_seen_whole_is_still_confirmed_at_the_edge_after_a_frame_sort_left_out() -> None:
    """SORT leaves a track it coasts on out of its output for a frame or two. A person who walked up to the car
    and was seen whole, then came back as the same track at the image's edge, was taken for a box seen only at the
    edge (not confirmed, not remembered) and forgotten beside the car's front corner, where the turn swept into them."""
    from towndrive.agent.drivers import make_driver
    from towndrive.agent.perception.classes import CLASSES
    from towndrive.agent.perception.tracking import Track
    from towndrive.envs.drive_env import DriveConfig

    driver = make_driver("agent")
    driver.reset(SimpleNamespace(config=DriveConfig()))
    objects = driver.stages.objects
    person = CLASSES.index("pedestrian")
    whole = Track(144, np.array([269.0, 45.0, 307.0, 147.0]), hits=30, age=30, time_since_update=0, label=person)
    at_edge = Track(144, np.array([284.0, 45.0, 319.0, 155.0]), hits=31, age=32, time_since_update=0, label=person)
    for k in range(5):
        objects.update([whole], 0.05 * k, None, speed_mps=0.0)
    assert objects.update([], 0.25, None, speed_mps=0.0) == []  # left out for a frame
    seen = objects.update([at_edge], 0.30, None, speed_mps=0.0)
    assert [o.track_id for o in seen] == [144] and seen[0].confirmed and 144 not in objects.edge_only


@needs_models
def test_a_person_lost_near_the_car_stays_where_last_seen_for_a_while() -> None:
    from towndrive.agent.decision.controller import PerceivedObject
    from towndrive.agent.drivers import make_driver
    from towndrive.envs.drive_env import DriveConfig

    driver = make_driver("agent")
    driver.reset(SimpleNamespace(config=DriveConfig()))
    cfg = driver.config
    # Last seen 4 m ahead in our path; its sideways "speed" is perspective (the box grows as it nears).
    near = PerceivedObject(3, "pedestrian", 4.0, 0.2, 0.8, 0.0, 1.5, (170.0, 50.0, 200.0, 120.0))
    far = PerceivedObject(4, "pedestrian", 12.0, 0.2, 0.6, 0.0, 1.5, (163.0, 70.0, 168.0, 90.0))
    driver.stages.memory.in_path_seen = {3: near, 4: far}
    seen_at: dict[int, list[float]] = {3: [], 4: []}
    for _ in range(int(5.0 / driver.dt)):
        for o in driver.stages.memory.recall([], 0.0, driver.stages.odometry.turn, driver.dt):
            seen_at[o.track_id].append(o.lateral_left_m)
        driver.stages.memory.in_path_seen = {}
    dt = driver.dt
    assert len(seen_at[3]) * dt == pytest.approx(cfg.near_memory_s, abs=2 * dt)
    assert set(seen_at[3]) == {0.2}  # it stays where it was
    assert len(seen_at[4]) * dt == pytest.approx(cfg.lost_memory_s, abs=2 * dt)
    assert seen_at[4][-1] > 0.2 + 1.5 * (cfg.lost_memory_s - 2 * dt)  # a farther one walks on


@needs_models
def test_straight_through_a_junction_the_agent_holds_the_approach_lane() -> None:
    env, world, driver = blind_world_and_agent()
    ctl = driver.controller
    # Before the junction the lane fit says: the lane runs 0.1 rad left of our axis, its centre 0.5 m left.
    z0 = -driver.camera.mount_forward_m
    centre = np.array([0.0, -0.1, -0.5 + 0.1 * z0])  # x = b z + c in the camera's ground frame
    odo = driver.stages.odometry
    odo.measure_road(centre, 0.9, driver.controller.line, z0)
    assert odo.road_yaw == pytest.approx(-0.1, abs=1e-3) and odo.road_offset == pytest.approx(0.5)
    assert driver.stages.junction.hold(3) is None  # not in a junction yet
    ctl.ignore_light_m = ctl.config.junction_ignore_m  # the bumper just crossed the stop line
    odo.measure_road(np.array([0.0, 0.3, 2.0]), 0.9, driver.controller.line, z0)  # crosswalk stripes: not measured
    assert driver.stages.odometry.road_yaw == pytest.approx(-0.1, abs=1e-3)
    assert driver.stages.junction.hold(1) is None  # a commanded turn is PilotNet's
    world.ego.speed = 5.0
    h0 = world.ego.heading
    for _ in range(80):  # 4 s, 20 m, on the same bicycle model the world uses
        steer = driver.stages.junction.hold(3)
        assert steer is not None
        env.step(np.array([steer, 0.0], np.float32))
        driver.stages.odometry.advance(float(world.ego.speed), steer, 3, driver.dt)
    assert world.ego.heading - h0 == pytest.approx(-0.1, abs=0.03)  # turned onto the lane's heading
    assert abs(driver.stages.odometry.road_offset) < 0.25  # and back near its centre (dead-reckoned)
    env.close()


@needs_models
def test_agent_drives_from_observations_only_and_times_every_stage() -> None:
    from towndrive.agent.drivers import make_driver
    from towndrive.envs.drive_env import DriveConfig, DriveEnv

    env = DriveEnv(DriveConfig(), render_mode="rgb_array")
    try:
        obs, _ = env.reset(seed=3)
        driver = make_driver("agent")
        assert driver.privileged is False
        # reset() gets a stand-in that has only the configuration: touching env.world would fail here
        driver.reset(SimpleNamespace(config=env.config))
        for _ in range(5):
            action = driver.act(obs)
            assert action.shape == (2,) and np.all(np.abs(action) <= 1.0)
            obs, *_ = env.step(action)
        assert len(driver.timings) == 5
        assert set(STAGES) | {"total"} <= set(driver.timings[-1])
        assert driver.view is not None and driver.view.decision.reason
        picture = driver.overlay()
        assert picture is not None and picture.shape == (320, 640, 3)
        summary = driver.adas_summary()
        assert set(summary["counts"]) == {"lane_departure", "forward_collision", "object_in_lane"}
    finally:
        env.close()


@needs_models
def test_agent_stops_0_to_2_m_before_the_stop_line_at_a_red_light() -> None:
    from towndrive.agent.drivers import make_driver
    from towndrive.envs.drive_env import DriveConfig
    from towndrive.envs.scenarios import run_scenario

    driver = make_driver("agent")
    result = run_scenario("red_light", driver, DriveConfig())
    assert result.passed, result.detail
    reasons = {driver.view.decision.reason}
    assert any(r.startswith("red light") for r in reasons)


def test_turn_path_is_the_towns_quarter_circle_into_the_same_lane() -> None:
    from towndrive.agent.decision.junction import turn_path

    for command, side in ((2, 1.0), (1, -1.0)):
        radius = 12.0 - 5.25 if command == 2 else 12.0 + 5.25
        path, arc_end = turn_path(command, radius)
        steps = np.hypot(*np.diff(path, axis=0).T)
        assert steps.max() < 0.25  # one continuous polyline
        k = int(round(arc_end / 0.2))
        assert path[k - 1] == pytest.approx([0.5 + radius, side * radius], abs=0.2)  # the arc ends in the new road
        assert path[-1][0] == pytest.approx(0.5 + radius) and side * path[-1][1] > radius + 25.0  # ... and follows it


def test_the_turn_keeps_the_cars_centre_on_the_arc() -> None:
    """The junction guidance steers the bicycle model's centre (the point the safety driver measures) along the
    turn arc: pursuing the arc with the rear axle put the centre 0.19 m outside a 13.75 m arc."""
    from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules
    from towndrive.agent.decision.odometry import Odometry
    from towndrive.agent.perception.stop_line import StopLine
    from towndrive.sim.spec import ROAD

    line = SimpleNamespace(ignore_light_m=0.0, stop_line_measured=True, stop_line=8.0,
                           config=SimpleNamespace(camera_to_front_m=1.3))
    odo = Odometry()
    odo.road_yaw, odo.road_offset = 0.0, 0.0
    g = JunctionGuidance(JunctionRules(), line, odo, 1.0, ROAD)
    g.note(StopLine(9.3, 0.5, 0.9, 0))  # the bar's near edge 10.3 m ahead of the car's centre
    radius = g.turn_reach_m(1)  # the classic quarter circle from the bar's far edge, turning left (y < 0)
    centre = np.array([ROAD.stop_bar_depth_m, -radius])
    steer, worst = 0.0, 0.0
    for _ in range(400):
        target = g.turn_steer(1, 3.0)
        steer = float(np.clip(target if target is not None else 0.0, steer - 0.075, steer + 0.075))  # rate limit
        odo.advance(3.0, steer, 1, 0.05)  # the world's bicycle model, exactly
        if g.junction is None:  # out of the turn
            break
        d = np.array(g._in_bar_frame(odo.pos)) - centre
        if d[0] > 0.0 and d[1] > 0.0:  # beside the arc
            worst = max(worst, abs(float(np.hypot(*d)) - radius))
    assert 0.0 < worst < 0.06, worst


@needs_models
@pytest.mark.parametrize("command", [1, 2])
def test_a_commanded_turn_follows_the_junctions_arc_into_the_same_lane(command: int) -> None:
    """The agent's turn, dead-reckoned from a stop bar seen 10 m ahead of the camera, on the world's own bicycle model and
    connectors: the car stays within the band of its lanes and comes out on the road it turned into."""
    from towndrive.agent.drivers import make_driver
    from towndrive.agent.perception.stop_line import StopLine
    from towndrive.envs.drive_env import DriveConfig, DriveEnv
    from towndrive.envs.scenarios import APPROACH_ARM, APPROACH_NODE, exit_edge
    from towndrive.sim.routes import shortest_route
    from towndrive.sim.town import Arm
    from towndrive.sim.world import World, cached_town

    config = DriveConfig(render_camera=False)
    town = cached_town(config.world.town, config.town_seed)
    ap = town.approach_at(APPROACH_NODE, APPROACH_ARM)
    goal = shortest_route(town, ap.edge, exit_edge(town, APPROACH_NODE, Arm.N if command == 1 else Arm.S))[-1]
    k = 0 if command == 1 else 1  # the lane the turn is taken from
    lane = town.network.graph[ap.edge[0]][ap.edge[1]][k]
    start_s = lane.length - 0.5 - 9.0 - 2.3  # the bumper 9 m before the bar's near edge
    world = World(town, replace(config.world, npc_count=0, pedestrian_count=0), seed=0,
                  start=(ap.edge[0], ap.edge[1], k), start_s=start_s, goal=goal, spawn_traffic=False)
    env = DriveEnv(config)
    env.reset(seed=0, options={"world": world})
    driver = make_driver("agent")
    driver.reset(SimpleNamespace(config=env.config))
    ctl = driver.controller
    ctl.stop_line, ctl.stop_line_measured = 9.0, True  # as the stop-line detector reads it
    driver.stages.odometry.road_yaw, driver.stages.odometry.road_offset = 0.0, 0.0  # as the lane fit measures the lane
    driver.stages.junction.note(StopLine(9.0 + ctl.config.camera_to_front_m, 0.5, 0.9, 0))
    h0, steer, worst, guided = world.ego.heading, 0.0, 0.0, 0
    for _ in range(300):  # up to 15 s at about 3 m/s, until 8 m into the road turned into
        target = driver.stages.junction.turn_steer(int(world.command()), float(world.ego.speed))
        guided += target is not None
        rate = ctl.config.steer_rate_per_s * driver.dt  # the controller's steering-rate limit
        steer = float(np.clip(target if target is not None else 0.0, steer - rate, steer + rate))
        throttle = float(np.clip(0.5 * (3.0 - world.ego.speed), -1.0, 1.0))
        speed = float(world.ego.speed)  # the speed the step moves the car at (the agent's observation)
        _, _, terminated, _, info = env.step(np.array([steer, throttle], np.float32))
        driver.stages.odometry.advance(speed, steer, int(world.command()), driver.dt)
        worst = max(worst, info["lane_band_offset_m"])
        assert not terminated and not info["infractions"], info["infractions"]
        if world.ego_lane is not None and world.ego_lane[0][:2] == goal and world.ego_lane[1] > 8.0:
            break
    assert guided > 40
    assert worst < 0.5, worst
    assert world.ego_lane is not None and world.ego_lane[0][:2] == goal
    turned = math.remainder(world.ego.heading - h0, 2 * math.pi)
    assert turned == pytest.approx((-1 if command == 1 else 1) * math.pi / 2, abs=0.15)
    env.close()


@needs_models
def test_after_an_intervention_the_agent_forgets_what_it_dead_reckoned() -> None:
    env, world, driver = blind_world_and_agent()
    ctl = driver.controller
    ctl.stop_line, ctl.stop_line_measured, ctl.light_state = 9.0, True, "red"
    driver.stages.odometry.road_yaw, driver.stages.odometry.pos = 0.1, np.array([30.0, 2.0])
    driver.stages.junction.note(SimpleNamespace(distance_m=10.0))
    assert driver.stages.junction.junction is not None
    driver.on_intervention()
    odo = driver.stages.odometry  # the stages start afresh
    assert driver.stages.junction.junction is None and odo.road_yaw is None and not odo.pos.any()
    assert ctl.stop_line is None and ctl.light_state is None
    env.close()


@needs_models
def test_engaged_again_inside_a_junction_a_turn_command_is_no_lane_change_to_look_for() -> None:
    """A take-over inside a junction leaves the car there, mid-turn, and the agent starts afresh with no junction
    placed: the right command must not read as a lane change still to come, which the mirror look would hold
    (PilotNet then told to follow a lane the car is not in). Taken over on the open road, it still does."""
    env, world, driver = blind_world_and_agent()
    right = 2
    driver.controller.line.ignore_light_m = 10.0  # the bumper crossed a stop line 20 m back: inside the junction
    driver.on_intervention()
    assert driver.stages.turn_end.engaged_mid_turn
    assert driver.stages.blind_spot.plan(0, right, driver._turn_placed, None)[0] is None
    driver.on_intervention()  # (the restart forgot the junction: this take-over is on the open road)
    assert not driver.stages.turn_end.engaged_mid_turn
    assert driver.stages.blind_spot.plan(0, right, driver._turn_placed, None)[0] == "right"
    env.close()


def _stand_in_a_left_turn(driver, detections, seconds: float) -> list[tuple[float, str]]:
    """Drive ``act()`` on a black frame, PilotNet steering hard left (a junction's left turn, no lane lines),
    the detector returning ``detections(frame)``; the car's speed follows its own acceleration. Returns the
    (speed, reason) of every frame."""
    from towndrive.envs.drive_env import DriveConfig

    cfg = DriveConfig()
    driver.reset(SimpleNamespace(config=cfg))
    driver.net = SimpleNamespace(steer=lambda image, command: -0.57)
    frame = {"n": 0}

    def detect(image):
        frame["n"] += 1
        return detections(frame["n"])

    driver.detector = detect
    image = np.zeros((cfg.camera.height, cfg.camera.width, 3), np.uint8)
    speed, out = 0.0, []
    for _ in range(int(seconds / driver.dt)):
        driver.act({"image": image, "speed": np.array([speed], np.float32), "command": 1})
        speed = max(0.0, speed + driver.view.decision.accel_mps2 * driver.dt)
        out.append((speed, driver.view.decision.reason))
    return out


@needs_models
def test_a_person_box_only_at_the_left_edge_holds_a_turning_car_for_a_bounded_time_then_it_creeps() -> None:
    """Issue 25: at night a facade or kerb at the image's left edge scores as a tall person 2 m away, in the
    sweep of a left turn; the car stood for it for good. The detector reports it every frame, or on and off
    (each time a new track, remembered when it goes), but never whole: the car stands at most the bounded
    time, then creeps on slowly, looking again every frame."""
    from towndrive.agent.drivers import make_driver
    from towndrive.agent.perception.classes import CLASSES
    from towndrive.agent.perception.detector import Detection

    driver = make_driver("agent")
    ped = CLASSES.index("pedestrian")
    edge = (0.0, 40.0, 14.0, 160.0)  # cut by the left edge and the bottom: about 2.3 m ahead, 2.2 m left
    # the last remembered box expires, and the bounded hold (summed over the boxes that hold the car) runs out:
    # well within the 20 s the issue allows
    bound = 12.0
    for name, detections in (("every frame", lambda n: [Detection(edge, ped, 0.8)]),
                             ("on and off", lambda n: [Detection(edge, ped, 0.8)] if n % 60 < 20 else [])):
        trace = _stand_in_a_left_turn(driver, detections, 30.0)
        first = next(k for k, (_, why) in enumerate(trace) if "pedestrian" in why)
        assert "turn's sweep" in trace[first][1] or "in our path" in trace[first][1], name
        assert any(v < 0.1 for v, _ in trace[first:]), name  # it stopped for it
        longest = run = 0
        for v, _ in trace[first:]:
            run = run + 1 if v < 0.1 else 0
            longest = max(longest, run)
        assert longest * driver.dt < bound, name  # but never stood for it long
        assert sum(v for v, _ in trace[-100:]) > 0.5 * 100 * driver.dt, name  # and moves on to the end
        if name == "every frame":
            trace_every, first_every = trace, first
    # reported every frame, the box is passed slowly, looking again every frame
    assert max(v for v, _ in trace_every[first_every:]) <= 1.5
    assert any("creeping" in why for _, why in trace_every)


@needs_models
def test_a_person_seen_whole_in_the_turn_s_sweep_holds_the_car_as_long_as_they_stand_there() -> None:
    from towndrive.agent.drivers import make_driver
    from towndrive.agent.perception.classes import CLASSES
    from towndrive.agent.perception.detector import Detection

    driver = make_driver("agent")
    g = driver.geometry
    rows = np.arange(0.0, 160.0, 0.25)
    y1 = float(rows[np.nanargmin(np.abs(g.birdseye.ground_z_of_row(rows) - 4.0))])  # the road's row 4 m ahead
    h = g.f * 1.75 / 4.0
    whole = (95.0, y1 - h, 105.0, y1)  # a person 4 m ahead, 1.5 m left, standing
    ped = CLASSES.index("pedestrian")
    trace = _stand_in_a_left_turn(driver, lambda n: [Detection(whole, ped, 0.8)], 30.0)
    assert all(v < 0.1 for v, _ in trace[40:])
    assert "pedestrian" in trace[-1][1] and "creeping" not in trace[-1][1]


@needs_models
def test_the_lanes_to_the_kerb_are_read_clear_of_a_stop_bar_and_forgotten_in_a_junction() -> None:
    """The line on our right tells how many lanes lie between ours and the kerb (a right turn keeps that count);
    its style is read from its paint ``coverage_z_max_m`` ahead, so with the stop bar nearer (the bar cuts it
    short: a kerb lane's edge line read as a dashed divider) the last reading holds; it is forgotten when the car
    has moved sideways into another lane since, and inside a junction (the road left behind is not the one
    ahead)."""
    from towndrive.agent.drivers import make_driver
    from towndrive.agent.perception.lanes import LaneLine
    from towndrive.envs.drive_env import DriveConfig

    driver = make_driver("agent")
    driver.reset(SimpleNamespace(config=DriveConfig()))
    line = driver.controller.line
    reach = driver.stages.lanes.config.markings.coverage_z_max_m

    def seen(style: str) -> SimpleNamespace:
        return SimpleNamespace(detected=True, left=None,
                               right=LaneLine(np.zeros(3), (3.0, 18.0), 0.9, 300, "white", style, 0.5))

    line.stop_line = None
    driver._note_lanes_to_kerb(seen("solid"))
    assert driver._kerb_lanes.count == 0
    line.stop_line = reach - 10.0  # the bar cuts the edge line short: it reads as dashed
    driver._note_lanes_to_kerb(seen("dashed"))
    assert driver._kerb_lanes.count == 0
    line.stop_line = reach + 10.0
    driver._note_lanes_to_kerb(seen("dashed"))
    assert driver._kerb_lanes.count == 1
    odo = driver.stages.odometry
    odo.pos = odo.pos + np.array([5.0, 2.0])  # the car changed lanes, and read no line on its right since
    driver._note_lanes_to_kerb(SimpleNamespace(detected=True, left=None, right=None))
    assert driver._kerb_lanes.count is None
    driver._note_lanes_to_kerb(seen("dashed"))
    line.stop_line, line.ignore_light_m = None, 10.0  # past the bar, in the junction
    driver._note_lanes_to_kerb(seen("solid"))
    assert driver._kerb_lanes.count is None


@needs_models
def test_the_street_s_lane_count_is_not_read_from_lines_a_stop_line_cuts_short() -> None:
    """The kind of street (lanes each way: the default limit, the far kerb of a crossing) is read from the lane
    lines only where they tell about our street: with a stop line within ``coverage_z_max_m`` ahead, tracked or
    put by a stop sign, the solid edge line ends in view and reads as dashed (two lanes each way), and beyond the
    line lie the junction's lines; inside the junction alike. A single-lane street stays one."""
    from towndrive.agent.drivers import make_driver
    from towndrive.agent.perception.lanes import LaneLine, LaneResult
    from towndrive.envs.drive_env import DriveConfig

    driver = make_driver("agent")
    driver.reset(SimpleNamespace(config=DriveConfig()))
    ctrl, reach = driver.controller, driver.stages.lanes.config.markings.coverage_z_max_m

    def lines(right_style: str) -> LaneResult:
        left = LaneLine(np.array([0.0, 0.0, -1.75]), (3.0, 18.0), 0.9, 300, "yellow", "solid", 0.9)
        right = LaneLine(np.array([0.0, 0.0, 1.75]), (3.0, 18.0), 0.9, 300, "white", right_style, 0.5)
        return LaneResult(left, right, 0.0, math.inf, 0.0, 3.5, 0.9, True)

    def frames(n: int, style: str, bar_m: float | None = None) -> None:
        stop = SimpleNamespace(distance_m=bar_m) if bar_m is not None else None
        for _ in range(n):
            driver._decide(1.0, 0, 0.0, None, None, None, [], None, stop, lines(style), None)

    frames(40, "solid")
    assert ctrl.signs.lanes_each_way == 1
    ctrl.signs.control, ctrl.signs.sign_line_m = "stop", reach - 6.0  # a stop sign's line, no bar tracked yet
    frames(40, "dashed")
    assert ctrl.signs.lanes_each_way == 1
    ctrl.signs.control, ctrl.signs.sign_line_m = None, None
    frames(40, "dashed", bar_m=reach - 6.0)  # the bar tracked
    assert ctrl.signs.lanes_each_way == 1
    ctrl.line.reset()
    frames(40, "dashed")  # clear of any line: a dashed divider on our right is another lane of ours
    assert ctrl.signs.lanes_each_way == 2
