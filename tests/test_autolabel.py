"""Auto-labelling: boxes of a known object in a rendered frame, occlusion, truncation, YOLO lines."""

from __future__ import annotations

import math

import numpy as np
import pytest

from towndrive.agent.training.autolabel import (
    CLASSES,
    CameraPose,
    box_corners,
    in_view_fraction,
    projected_hull,
    render_and_label,
)
from towndrive.sim.objects import SemanticClass
from towndrive.sim.render import CameraConfig, SceneRenderer
from towndrive.sim.world import World, WorldConfig


def scene(town, ahead_m: tuple[float, ...], kinds: tuple[SemanticClass, ...]):
    """An empty world (no traffic, no people) with vehicles placed ahead of the ego in its own lane."""
    world = World(town, WorldConfig(npc_count=0, pedestrian_count=0), seed=5, spawn_traffic=False)
    lane_index, s_ego = world.ego_lane[0], world.ego_lane[1]
    for d, kind in zip(ahead_m, kinds, strict=True):
        assert world.spawn_npc(lane_index, s_ego + d, kind=kind, color=(0.8, 0.1, 0.1)) is not None
    return world


@pytest.fixture(scope="module")
def renderer(town):
    r = SceneRenderer(town, seed=town.seed)
    yield r
    r.close()


@pytest.mark.parametrize("camera", [CameraConfig(), CameraConfig(mount_height_m=1.75, hfov_deg=108.0, pitch_deg=-7.5)],
                         ids=["default rig", "another car's rig"])
def test_known_car_gets_a_tight_full_label(town, renderer, camera):
    """The label is the car's pixels and agrees with its 3D box, from the default camera and from another car's
    (the rig splits render each frame from a drawn camera)."""
    world = scene(town, (15.0,), (SemanticClass.CAR,))
    frame, labels = render_and_label(renderer, world, camera, "noon")
    cars = [lab for lab in labels if lab.name == "car"]
    assert len(cars) == 1
    car = cars[0]
    assert not car.ignore and car.visible_fraction > 0.95 and car.in_image_fraction == pytest.approx(1.0)
    # The camera is 1 m ahead of the ego's centre: the car's centre is ~14 m from it.
    assert car.distance_m == pytest.approx(14.0, abs=0.5)
    # Its box is exactly the bounding box of its segmentation pixels...
    ys, xs = np.nonzero(frame.segmentation[..., 1] == car.object_id)
    assert car.box == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)
    # ...and agrees with the projection of its 3D box (a car body fills most of its bounding box).
    snap = next(s for s in world.object_snapshots() if s.object_id == car.object_id)
    pose = CameraPose.of(renderer, (*world.ego.position, world.ego.heading), camera)
    hull, _ = projected_hull(pose, box_corners(snap.x, snap.y, snap.heading, snap.length_m, snap.width_m, 0.0,
                                               snap.height_m))
    x0, y0 = hull.min(axis=0)
    x1, y1 = hull.max(axis=0)
    assert abs(car.box[0] - x0) < 3 and abs(car.box[2] - x1) < 3 and abs(car.box[3] - y1) < 3
    assert car.box[1] >= y0 - 1  # the cabin is narrower than the box, so the top may sit lower
    line = car.yolo_line(camera.width, camera.height).split()
    assert int(line[0]) == CLASSES.index("car")
    cx, cy, w, h = map(float, line[1:])
    assert cx == pytest.approx((car.box[0] + car.box[2]) / 2 / camera.width, abs=1e-5)
    assert w == pytest.approx((car.box[2] - car.box[0]) / camera.width, abs=1e-5)
    assert 0 < cy < 1 and 0 < h < 1


def test_car_hidden_behind_a_truck_is_ignored_as_occluded(town, renderer):
    world = scene(town, (9.0, 22.0), (SemanticClass.TRUCK, SemanticClass.CAR))
    _, labels = render_and_label(renderer, world, CameraConfig(), "dusk")
    by_name = {lab.name: lab for lab in labels}
    assert not by_name["truck"].ignore
    if "car" in by_name:  # a sliver may show; then it must be an ignore region, never a training target
        assert by_name["car"].ignore and by_name["car"].reason == "occluded"
        assert by_name["car"].visible_fraction < 0.4


def test_in_view_fraction_measures_truncation_by_angle(renderer):
    camera = CameraConfig()
    pose = CameraPose.of(renderer, (0.0, 0.0, 0.0), camera)  # looking along +x of the map
    ahead = box_corners(20.0, 0.0, 0.0, 4.0, 2.0, 0.0, 1.5)
    assert in_view_fraction(pose, ahead) == pytest.approx(1.0)
    # Centred on the left edge of a 90 degree view (45 degrees to the left, map y up is negative):
    edge = box_corners(20.0 * math.cos(math.pi / 4), -20.0 * math.sin(math.pi / 4), math.pi / 4, 6.0, 2.0, 0.0, 1.5)
    assert 0.3 < in_view_fraction(pose, edge) < 0.7
    behind = box_corners(-10.0, 0.0, 0.0, 4.0, 2.0, 0.0, 1.5)
    assert in_view_fraction(pose, behind) == 0.0


# --------------------------------------------------------------------------- road signs (styled towns)
@pytest.fixture(scope="module")
def sign_town():
    from towndrive.sim.town import TownConfig
    from towndrive.sim.world import cached_town

    return cached_town(TownConfig.of_style("suburb"), 0)  # stop and yield signs and both limits


@pytest.fixture(scope="module")
def sign_renderer(sign_town):
    r = SceneRenderer(sign_town, seed=sign_town.seed)
    yield r
    r.close()


def camera_at(town, sign, distance_m: float, bearing_deg: float):
    """A stand-in for a world whose ego camera looks at ``sign`` from ``distance_m`` away: from in front of its
    face (bearing 0), from its side (90) or from behind (180). Nothing moves; lights red."""
    from types import SimpleNamespace

    from towndrive.sim.objects import LightState

    face = sign.facing + math.pi  # the way the face looks
    at = face + math.radians(bearing_deg)
    cam_xy = np.asarray(sign.position, float) + distance_m * np.array([math.cos(at), math.sin(at)])
    heading = at + math.pi  # looking at the sign
    ego_xy = cam_xy - 1.0 * np.array([math.cos(heading), math.sin(heading)])  # the camera is 1 m ahead of the centre
    return SimpleNamespace(ego=SimpleNamespace(position=ego_xy, heading=heading), object_snapshots=lambda: [],
                           town=town, lights=SimpleNamespace(states=[LightState.RED] * len(town.approaches)))


def test_signs_are_labelled_by_kind_and_value_and_not_from_behind(sign_town, sign_renderer):
    from towndrive.agent.perception.classes import sign_class
    from towndrive.sim.objects import SIGN_ID_BASE
    from towndrive.sim.sign_meshes import SIGN_CLASS

    seen: dict[str, int] = {}
    for sign in sign_town.signs:
        want = sign_class(sign.kind.name, sign.value_kmh)
        if want in seen:
            continue
        oid = SIGN_ID_BASE + sign.index
        frame, labels = render_and_label(sign_renderer, camera_at(sign_town, sign, 10.0, 0.0), CameraConfig(), "noon")
        mine = [lab for lab in labels if lab.object_id == oid]
        assert len(mine) == 1, (sign, mine)
        if mine[0].ignore:  # a tree or another post in front of this one: try the next sign of the kind
            assert mine[0].reason == "occluded"
            continue
        assert mine[0].name == want
        ys, xs = np.nonzero(frame.segmentation[..., 1] == oid)
        assert mine[0].box == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)  # the plate's pixels (the post is POLE)
        assert min(mine[0].box[2] - mine[0].box[0], mine[0].box[3] - mine[0].box[1]) >= 10
        assert frame.segmentation[ys[0], xs[0], 0] == SIGN_CLASS[int(sign.kind)]
        seen[want] = sign.index
    assert set(seen) == {"stop_sign", "yield_sign", "speed_limit_30", "speed_limit_50"}

    for name, index in seen.items():
        sign = sign_town.signs[index]
        oid = SIGN_ID_BASE + index
        # From behind the renderer still paints the plate's back with the sign's class and id...
        frame, labels = render_and_label(sign_renderer, camera_at(sign_town, sign, 10.0, 180.0), CameraConfig(),
                                         "noon")
        back = frame.segmentation[..., 1] == oid
        assert back.sum() >= 20, name
        assert set(frame.segmentation[..., 0][back].tolist()) == {SIGN_CLASS[int(sign.kind)]}
        # ...but a plate's back is no sign for the traffic that sees it: neither a label nor an ignore region.
        assert not [lab for lab in labels if lab.object_id == oid], name
        # Seen from the side (75 degrees off its face) it is a "don't care" region.
        _, labels = render_and_label(sign_renderer, camera_at(sign_town, sign, 8.0, 75.0), CameraConfig(), "noon")
        side = [lab for lab in labels if lab.object_id == oid]
        assert all(lab.ignore for lab in side), name


def test_far_speed_limits_are_ignored_since_their_value_is_unreadable(sign_town, sign_renderer):
    from towndrive.sim.objects import SIGN_ID_BASE
    from towndrive.sim.town import SignKind

    reasons = set()
    for sign in [s for s in sign_town.signs if s.kind == SignKind.SPEED_LIMIT][:6]:
        _, labels = render_and_label(sign_renderer, camera_at(sign_town, sign, 20.0, 0.0), CameraConfig(), "noon")
        mine = [lab for lab in labels if lab.object_id == SIGN_ID_BASE + sign.index]
        assert all(lab.ignore for lab in mine)
        reasons |= {lab.reason for lab in mine}
    assert "value unreadable" in reasons


def test_sign_classes_are_appended_and_named_in_one_place():
    from towndrive.agent.perception.classes import LIMIT_OF_CLASS, SIGN_CLASSES, sign_class
    from towndrive.sim.town import SignKind

    assert CLASSES[:6] == ("car", "truck", "pedestrian", "light_red", "light_yellow", "light_green")
    assert SIGN_CLASSES == CLASSES[6:] == ("stop_sign", "yield_sign", "speed_limit_30", "speed_limit_50")
    assert sign_class(SignKind.STOP.name) == "stop_sign" and sign_class(SignKind.YIELD.name, 0) == "yield_sign"
    assert [sign_class(SignKind.SPEED_LIMIT.name, v) for v in (30, 50, 70)] == ["speed_limit_30", "speed_limit_50", None]
    assert LIMIT_OF_CLASS == {"speed_limit_30": 30, "speed_limit_50": 50}


def test_rig_range_draws_other_cars_cameras_around_the_default_rig():
    """Each draw is a camera within the ranges (size and stereo kept); the default rig and the other car of the
    closed-loop check (0.2 m higher, 100 degrees) lie inside them; the same seed draws the same cameras."""
    from towndrive.agent.training.autolabel import RigRange

    rigs, base = RigRange(), CameraConfig()
    for lo_hi, value in ((rigs.mount_height_m, base.mount_height_m), (rigs.hfov_deg, base.hfov_deg),
                         (rigs.pitch_deg, base.pitch_deg), (rigs.mount_height_m, base.mount_height_m + 0.2),
                         (rigs.hfov_deg, 100.0)):
        assert lo_hi[0] < value < lo_hi[1]
    draws = [rigs.draw(np.random.default_rng(3), base) for _ in range(2)]
    assert draws[0] == draws[1]
    many = [rigs.draw(rng, base) for rng in [np.random.default_rng(4)] for _ in range(200)]
    for cam in many:
        assert rigs.mount_height_m[0] <= cam.mount_height_m <= rigs.mount_height_m[1]
        assert rigs.hfov_deg[0] <= cam.hfov_deg <= rigs.hfov_deg[1]
        assert rigs.pitch_deg[0] <= cam.pitch_deg <= rigs.pitch_deg[1]
        assert (cam.width, cam.height, cam.mount_forward_m) == (base.width, base.height, base.mount_forward_m)
    assert np.ptp([c.hfov_deg for c in many]) > 30 and np.ptp([c.mount_height_m for c in many]) > 0.5


def test_on_policy_split_keeps_what_the_agents_detector_sees(tmp_path):
    """``train_agent``-style splits: the camera-only agent drives, and each frame is rendered with the trained lens
    and pitch at the drawn car's mounting height (what the agent's model view hands its detector), its camera in
    the meta file; an unknown driver is one sentence."""
    import json

    from towndrive.agent.training.autolabel import RigRange, SplitSpec, generate_split
    from towndrive.sim.spec import CAMERA

    spec = SplitSpec("train_agent", (30,), ("noon",), 3, frames_per_episode=3, rigs=RigRange(), driver="agent")
    counts = generate_split(tmp_path, spec, 0, progress=False)
    assert counts["frames"] == 3
    rows = [json.loads(line) for line in (tmp_path / "train_agent_meta.jsonl").read_text().splitlines()]
    heights = {r["camera"]["mount_height_m"] for r in rows}
    assert len(heights) == 1 and RigRange().mount_height_m[0] <= heights.pop() <= RigRange().mount_height_m[1]
    assert all((r["camera"]["hfov_deg"], r["camera"]["pitch_deg"]) == (CAMERA.hfov_deg, CAMERA.pitch_deg) for r in rows)
    assert len(list((tmp_path / "images" / "train_agent").glob("*.png"))) == 3
    with pytest.raises(ValueError, match="unknown driver"):
        generate_split(tmp_path, SplitSpec("x", (30,), ("noon",), 1, driver="human"), 0, progress=False)
