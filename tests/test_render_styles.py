"""The styled towns' look: signs are objects with their own classes and ids in the segmentation, their faces
look at the traffic that reads them, post-mounted signal heads hang at their approach's height (no mast arm),
the top-down map shows signs and parked cars, and the classic town's scene is what it always was."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from towndrive.sim.geometry import right_of
from towndrive.sim.objects import LIGHT_ID_BASE, SIGN_ID_BASE, SemanticClass
from towndrive.sim.render import CameraConfig, SceneRenderer
from towndrive.sim.scene_meshes import build_ground_map, build_static_groups, to_world
from towndrive.sim.sign_meshes import SIGN_CLASS
from towndrive.sim.spec import ROAD
from towndrive.sim.topdown import SIGN_RED, TopDownMap
from towndrive.sim.town import Sign, SignKind, Town, TownConfig, generate_town

CAMERA = CameraConfig()  # 320 x 160, what the agents see
SUBURB_SEED = 4000  # a validation town (no test split): stop, yield and limit signs, far-pole and mast-arm signals
# The classic town's scene (meshes, ground texels, light heads) as it was before styles had a look of their own.
CLASSIC_SCENE = {0: "10e2ebf3de84a01ff35a9475283253cf2793ab3d6b7dd1bc530d51c0270e4304",
                 3: "e69fbbcb8eadcc0d3335247d034e841ae83b1ba08acd0ef2b61bfdda4ab02202"}


@pytest.fixture(scope="module")
def suburb() -> tuple[Town, SceneRenderer]:
    town = generate_town(TownConfig.of_style("suburb"), SUBURB_SEED)
    renderer = SceneRenderer(town, seed=SUBURB_SEED)
    yield town, renderer
    renderer.close()


def project(renderer: SceneRenderer, pose: tuple[float, float, float], x: float, y: float, z: float) -> tuple[int, int]:
    """Pixel (column, row) of a map-frame point at height z, for the camera on a vehicle at ``pose``."""
    eye, fwd = renderer.camera_position(pose, CAMERA)
    right = np.array([fwd[1], -fwd[0], 0.0]) / math.hypot(fwd[0], fwd[1])
    down = np.cross(fwd, right)
    d = to_world(x, y, z) - eye
    k = CAMERA.intrinsics()
    zc = float(d @ fwd)
    return int(round(k[0, 2] + k[0, 0] * float(d @ right) / zc)), int(round(k[1, 2] + k[1, 1] * float(d @ down) / zc))


def view_of(sign: Sign, ahead_m: float, behind: bool = False) -> tuple[float, float, float]:
    """A vehicle pose ``ahead_m`` before a sign (or past it, looking back), 3.5 m to the road side of it."""
    fwd = np.array([math.cos(sign.facing), math.sin(sign.facing)])
    side = -right_of(fwd) * 3.5
    if behind:
        pos = sign.position + fwd * (ahead_m + CAMERA.mount_forward_m) + side
        return float(pos[0]), float(pos[1]), sign.facing + math.pi
    pos = sign.position - fwd * (ahead_m + CAMERA.mount_forward_m) + side
    return float(pos[0]), float(pos[1]), sign.facing


def red(rgb: np.ndarray) -> np.ndarray:
    r, g, b = (rgb[..., k].astype(int) for k in range(3))
    return (r > 80) & (r > 1.6 * g) & (r > 1.6 * b)


def best_view(town: Town, renderer: SceneRenderer, kind: SignKind, behind: bool = False):
    """Of a kind's first signs, the one the camera sees best 8 m away (a tree may stand in front of one)."""
    best = None
    for sign in [s for s in town.signs if s.kind == kind][:4]:
        pose = view_of(sign, 8.0, behind)
        frame = renderer.render(pose, CAMERA, "noon")
        n = int((frame.segmentation[..., 1] == SIGN_ID_BASE + sign.index).sum())
        if best is None or n > best[0]:
            best = (n, sign, pose, frame)
    assert best is not None
    return best[1:]


@pytest.mark.parametrize("kind", list(SignKind))
def test_a_signs_pixels_carry_its_class_and_id_and_its_post_is_a_pole(suburb, kind):
    town, renderer = suburb
    sign, pose, frame = best_view(town, renderer, kind)
    cls, oid = frame.segmentation[..., 0], frame.segmentation[..., 1]
    mine = oid == SIGN_ID_BASE + sign.index
    assert mine.sum() >= 60, "the plate covers a few dozen pixels at 8 m"
    assert set(np.unique(cls[mine]).tolist()) == {int(SIGN_CLASS[int(kind)])}
    u, v = project(renderer, pose, *sign.position, sign.plate_height_m)
    rows, cols = np.nonzero(mine)
    assert rows.min() - 1 <= v <= rows.max() + 1 and cols.min() - 1 <= u <= cols.max() + 1, "the plate is where the town puts it"
    u, v = project(renderer, pose, *sign.position, 1.0)
    assert (cls[v - 1:v + 2, u - 1:u + 2] == SemanticClass.POLE).any(), "a post holds the plate up"
    assert (oid[v - 1:v + 2, u - 1:u + 2] == 0).all(), "the post is scenery, not part of the sign's box"


@pytest.mark.parametrize("kind", list(SignKind))
def test_a_plate_faces_its_traffic_and_shows_grey_from_behind(suburb, kind):
    town, renderer = suburb
    sign, _, front = best_view(town, renderer, kind)
    mine = front.segmentation[..., 1] == SIGN_ID_BASE + sign.index
    assert red(front.rgb)[mine].mean() > 0.2, "the face's red (octagon, border or ring) looks at its readers"
    if kind == SignKind.SPEED_LIMIT:
        dark = front.rgb[mine].max(axis=1) < 60
        assert dark.sum() >= 3, "the limit's digits are black"
    pose = view_of(sign, 8.0, behind=True)
    rear = renderer.render(pose, CAMERA, "noon")
    theirs = rear.segmentation[..., 1] == SIGN_ID_BASE + sign.index
    assert theirs.sum() >= 30, "from behind the plate is still there"
    assert red(rear.rgb)[theirs].mean() < 0.02, "its back is grey"


def test_signs_out_of_view_are_hidden_and_come_back(suburb):
    town, renderer = suburb
    sign = next(s for s in town.signs if s.kind == SignKind.STOP)
    pose = view_of(sign, 8.0)
    renderer.render((pose[0], pose[1], pose[2] + math.pi), CAMERA, "noon")
    assert not renderer._sign_shown[sign.index]
    frame = renderer.render(pose, CAMERA, "noon")
    assert renderer._sign_shown[sign.index] and (frame.segmentation[..., 1] == SIGN_ID_BASE + sign.index).any()


@pytest.mark.parametrize("mount", ["far_pole", "mast_arm"])
def test_signal_heads_hang_at_their_approachs_height_on_posts_or_mast_arms(suburb, mount):
    town, renderer = suburb
    ap = next(a for a in town.approaches if a.mount == mount)
    lane = town.lane((ap.edge[0], ap.edge[1], 0))
    s = lane.length - 22.0
    x, y = lane.position(s, 0.0)
    pose = (float(x), float(y), float(lane.heading_at(s)))
    frame = renderer.render(pose, CAMERA, "noon")
    cls, oid = frame.segmentation[..., 0], frame.segmentation[..., 1]

    def at(px: np.ndarray, z: float) -> tuple[np.ndarray, np.ndarray]:
        u, v = project(renderer, pose, float(px[0]), float(px[1]), z)
        return cls[v - 1:v + 2, u - 1:u + 2], oid[v - 1:v + 2, u - 1:u + 2]

    expected = 3.6 if mount != "mast_arm" else ROAD.signal_head_height_m
    assert ap.head_height_m == pytest.approx(expected)
    assert (at(ap.light_head, ap.head_height_m)[1] == LIGHT_ID_BASE + ap.index).sum() >= 5, "the head is at its height"
    other = ROAD.signal_head_height_m if mount != "mast_arm" else 3.6
    assert not (at(ap.light_head, other)[1] == LIGHT_ID_BASE + ap.index).any(), "and not at the other mount's"
    assert (at(ap.light_pole, 2.0)[0] == SemanticClass.POLE).any(), "a pole stands at the corner"
    above = (at(ap.light_pole, ROAD.signal_head_height_m + 0.3)[0] == SemanticClass.POLE).any()
    assert above == (mount == "mast_arm"), "only a mast arm's pole reaches above a post-mounted head"


def test_the_map_shows_signs_parked_cars_and_give_way_lines():
    town = generate_town(TownConfig.of_style("suburb"), SUBURB_SEED)
    top = TopDownMap(town, pixels_per_m=3.0)
    img = top.render()
    stop = next(s for s in town.signs if s.kind == SignKind.STOP)
    u, v = top.to_px(stop.position)
    assert tuple(img[v, u]) == SIGN_RED
    car = max(town.parked_cars, key=lambda c: min(float(np.linalg.norm(c.position - t.position)) - t.canopy_radius_m
                                                  for t in town.trees))  # canopies hide some cars from above
    u, v = top.to_px(car.position)
    assert np.abs(img[v, u].astype(int) - np.array([int(255 * c) for c in car.color])).max() <= 2
    tri = town.markings["yield_line"][0].mean(axis=0)
    u, v = top.to_px(tri)
    assert img[v, u].min() > 200, "a give-way triangle is white paint"


def classic_scene_digest(town_seed: int) -> str:
    town = generate_town(TownConfig(), town_seed)
    m = hashlib.sha256()
    for g in build_static_groups(town, town_seed):
        v, _, n = g.mesh.arrays()
        m.update(f"{g.name}{int(g.semantic)}{g.rgba}{g.emissive_at_night}".encode())
        m.update(np.asarray(v, np.float64).tobytes() + np.asarray(n, np.float64).tobytes())
    m.update(np.ascontiguousarray(build_ground_map(town).texels).tobytes())
    for ap in town.approaches:
        m.update(np.array([*ap.light_head, ap.head_height_m, ap.travel_heading]).tobytes())
    return m.hexdigest()


@pytest.mark.parametrize("town_seed", sorted(CLASSIC_SCENE))
def test_the_classic_scene_is_unchanged(town_seed):
    assert classic_scene_digest(town_seed) == CLASSIC_SCENE[town_seed]
    assert not generate_town(TownConfig(), town_seed).signs, "classic towns have no sign bodies to add"
