"""Auto-labelling: 2D detection boxes from the renderer's segmentation map, checked against 3D ground truth.

The segmentation map says which pixels belong to which object, but not how much of an object is hidden
behind another or cut off by the image border. So each object's 3D box (from its ``ObjectSnapshot``, or
the light's housing) is projected into the image as well:

* **truncation**: the share of the projected box that falls inside the image;
* **occlusion**: within the projected box, pixels that show something *nearer* than the object's nearest
  face are occluded; ``visible / (visible + occluded)`` is the visible fraction. Pixels that show
  something behind the object (the background between a pedestrian's legs) count as neither.

An object becomes a label when it is visible enough, inside the image enough and large enough; otherwise it
becomes an *ignore* region: neither a positive nor a negative for training, and detections on it are not
counted as false positives in evaluation (KITTI's "don't care"). Traffic lights are labelled with their state
(``light_red`` / ``light_yellow`` / ``light_green``) when their lamps face the camera. Lights seen from the
side are ignored; lights seen from behind show no lamps and stay background, so that the detector learns not
to report a state it cannot see.

Road signs (styled towns) are labelled the same way from their plate's pixels (segmentation classes
``STOP_SIGN`` / ``YIELD_SIGN`` / ``SPEED_LIMIT_SIGN`` with id ``SIGN_ID_BASE + k``; the post is ``POLE``); the class
comes from the town's sign ``k``, its kind and posted value (``classes.sign_class``). The renderer labels the
plate's grey back with the sign's class and id too, so facing is decided by geometry, as for lights: a face
within ``sign_facing_deg`` of the camera is a label, a face turned further is a side view (ignored), and beyond
90 degrees only the back shows: background, since a plate's back says nothing to the traffic that sees it.
Signs need ``min_sign_px`` pixels of width and height, and a limit's value needs ``min_limit_px`` (its digits
are 0.42 of the plate's height): smaller limits are ignore regions, so the detector is neither taught nor
marked on guessing a value it cannot read.

The box of a label is the bounding box of the object's *visible* pixels, clipped to the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from towndrive.agent.perception.classes import (  # noqa: F401 (re-exported)
    CLASSES,
    LIGHT_CLASSES,
    LIMIT_OF_CLASS,
    SIGN_CLASSES,
    STATE_OF_CLASS,
    sign_class,
)
from towndrive.sim.objects import LIGHT_ID_BASE, SIGN_ID_BASE, LightState, ObjectSnapshot, SemanticClass
from towndrive.sim.render import CameraConfig, SceneRenderer
from towndrive.sim.scene_meshes import HOUSING_HALF, SURFACE_RAISED, Z_SLAB, to_world
from towndrive.sim.town import Sign, Town

_KIND_CLASS = {SemanticClass.CAR: 0, SemanticClass.TRUCK: 1, SemanticClass.PEDESTRIAN: 2}
_STATE_CLASS = {LightState.RED: 3, LightState.YELLOW: 4, LightState.GREEN: 5}
LIMIT_CLASSES = frozenset(LIMIT_OF_CLASS)


@dataclass(frozen=True)
class LabelRules:
    """Thresholds that decide label, ignore or nothing. Defaults are the dataset's."""

    min_visible_fraction: float = 0.4  # of the unoccluded part inside the image
    min_in_image_fraction: float = 0.3  # of the box's horizontal and vertical view angles (truncation)
    min_height_px: int = 6  # KITTI's "moderate" 25 px at 1242 wide, scaled to 320: a car at 40 m is 6 px tall
    min_width_px: int = 2
    min_pixels: int = 10
    occluder_margin_m: float = 0.3  # something nearer than the nearest face by this much occludes
    light_facing_deg: float = 60.0  # lamps within this angle of the camera: labelled with state
    light_side_deg: float = 110.0  # between facing and this: ignored; beyond it (seen from behind): background
    sign_facing_deg: float = 60.0  # a sign's face within this angle of the camera: labelled
    sign_side_deg: float = 90.0  # between facing and this: ignored; beyond it only the plate's back shows: background
    min_sign_px: int = 5  # a plate's width and height (0.75 m: 5 px at about 24 m)
    min_limit_px: int = 10  # a speed limit's, for its value (its digits 4 px tall; about 18 m away)
    min_sign_pixels: int = 15


@dataclass(frozen=True)
class ObjectLabel:
    """One object in one frame, with everything the evaluation needs to slice results."""

    cls: int  # index into CLASSES
    box: tuple[int, int, int, int]  # x0, y0, x1, y1 in pixels, x1/y1 exclusive
    object_id: int
    distance_m: float  # camera to the object's centre, on the ground plane
    visible_fraction: float
    in_image_fraction: float
    ignore: bool  # True: a "don't care" region, not a training target
    reason: str = ""  # why it is ignored

    @property
    def name(self) -> str:
        return CLASSES[self.cls]

    def yolo_line(self, width: int, height: int) -> str:
        """``cls cx cy w h``, normalised to the image size (the YOLO label format)."""
        x0, y0, x1, y1 = self.box
        return (f"{self.cls} {(x0 + x1) / 2 / width:.6f} {(y0 + y1) / 2 / height:.6f} "
                f"{(x1 - x0) / width:.6f} {(y1 - y0) / height:.6f}")

    def as_dict(self) -> dict:
        return {"cls": self.cls, "name": self.name, "box": list(self.box), "id": self.object_id,
                "distance_m": round(self.distance_m, 2), "visible": round(self.visible_fraction, 3),
                "in_image": round(self.in_image_fraction, 3), "ignore": self.ignore, "reason": self.reason}


# --------------------------------------------------------------------------- geometry
@dataclass(frozen=True)
class CameraPose:
    """Camera eye and axes in pybullet's world frame (z up), as the renderer uses them."""

    eye: np.ndarray
    forward: np.ndarray
    right: np.ndarray
    down: np.ndarray
    camera: CameraConfig

    @classmethod
    def of(cls, renderer: SceneRenderer, vehicle_pose: tuple[float, float, float], camera: CameraConfig) -> CameraPose:
        eye, forward = renderer.camera_position(vehicle_pose, camera)
        norm = math.hypot(forward[0], forward[1])
        right = np.array([forward[1] / norm, -forward[0] / norm, 0.0])
        down = np.cross(forward, right)
        return cls(np.asarray(eye, float), np.asarray(forward, float), right, down, camera)

    def to_camera(self, points_world: np.ndarray) -> np.ndarray:
        """N x 3 world points -> N x 3 camera coordinates (x right, y down, z forward)."""
        rel = points_world - self.eye
        return np.stack([rel @ self.right, rel @ self.down, rel @ self.forward], axis=1)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        k = self.camera.intrinsics()
        return np.stack([k[0, 0] * points_cam[:, 0] / points_cam[:, 2] + k[0, 2],
                         k[1, 1] * points_cam[:, 1] / points_cam[:, 2] + k[1, 2]], axis=1)

    def ground_distance(self, x: float, y: float) -> float:
        """Distance on the ground from the camera to map point (x, y)."""
        return math.hypot(x - self.eye[0], -y - self.eye[1])


_EDGES = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7)]


def box_corners(x: float, y: float, heading: float, length: float, width: float, z0: float, z1: float) -> np.ndarray:
    """8 world-frame (z-up) corners of an oriented box standing on map point (x, y)."""
    c, s = math.cos(heading), math.sin(heading)
    local = np.array([[0.5, 0.5], [0.5, -0.5], [-0.5, -0.5], [-0.5, 0.5]]) * [length, width]
    mx = x + local[:, 0] * c - local[:, 1] * s
    my = y + local[:, 0] * s + local[:, 1] * c
    bottom = np.stack([to_world(a, b, z0) for a, b in zip(mx, my, strict=True)])
    top = np.stack([to_world(a, b, z1) for a, b in zip(mx, my, strict=True)])
    return np.concatenate([bottom, top])


def projected_hull(pose: CameraPose, corners_world: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Image polygon of a 3D box clipped to the near plane, and the box's nearest z-depth (None if behind)."""
    cam = pose.to_camera(corners_world)
    near = pose.camera.near_m
    pts = [cam[k] for k in range(8) if cam[k, 2] >= near]
    for a, b in _EDGES:  # where an edge crosses the near plane, its crossing point is a vertex of the clipped box
        za, zb = cam[a, 2], cam[b, 2]
        if (za - near) * (zb - near) < 0:
            t = (near - za) / (zb - za)
            pts.append(cam[a] + t * (cam[b] - cam[a]))
    if len(pts) < 3:
        return None
    pts_arr = np.array(pts)
    uv = pose.project(pts_arr)
    hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2)
    return hull, float(pts_arr[:, 2].min())


def in_view_fraction(pose: CameraPose, corners_world: np.ndarray) -> float:
    """Share of a box's horizontal view angle times share of its vertical view angle that the image covers.

    Angles, not projected areas: a car beside the camera projects to an enormous area near the near
    plane, which would call it 99% truncated while half of it fills the image.
    """
    cam = pose.to_camera(corners_world)
    cfg = pose.camera
    k = cfg.intrinsics()
    centre = cam.mean(axis=0)
    az0 = math.atan2(centre[0], centre[2])  # angles about the centre's direction, so a box behind does not wrap
    az = az0 + np.remainder(np.arctan2(cam[:, 0], cam[:, 2]) - az0 + np.pi, 2 * np.pi) - np.pi
    el = np.arctan2(cam[:, 1], np.hypot(cam[:, 0], cam[:, 2]))  # positive down, like image rows
    half_h = math.atan((cfg.width / 2) / k[0, 0])
    top, bottom = math.atan((0 - k[1, 2]) / k[1, 1]), math.atan((cfg.height - k[1, 2]) / k[1, 1])

    def share(lo: float, hi: float, view_lo: float, view_hi: float) -> float:
        return max(0.0, min(hi, view_hi) - max(lo, view_lo)) / max(hi - lo, 1e-9)

    return share(float(az.min()), float(az.max()), -half_h, half_h) * share(float(el.min()), float(el.max()), top, bottom)


# --------------------------------------------------------------------------- labelling
def _object_boxes(ids: np.ndarray) -> dict[int, tuple[int, int, int, int, int]]:
    """object id -> (x0, y0, x1, y1, pixel count) of its visible pixels (ids > 0 only)."""
    flat = np.flatnonzero(ids.ravel() > 0)
    if len(flat) == 0:
        return {}
    vals = ids.ravel()[flat]
    order = np.argsort(vals, kind="stable")
    flat, vals = flat[order], vals[order]
    starts = np.flatnonzero(np.r_[True, vals[1:] != vals[:-1]])
    w = ids.shape[1]
    rows, cols = flat // w, flat % w
    x0, x1 = np.minimum.reduceat(cols, starts), np.maximum.reduceat(cols, starts)
    y0, y1 = np.minimum.reduceat(rows, starts), np.maximum.reduceat(rows, starts)
    counts = np.diff(np.r_[starts, len(vals)])
    return {int(v): (int(a), int(b), int(c) + 1, int(d) + 1, int(n))
            for v, a, b, c, d, n in zip(vals[starts], x0, y0, x1, y1, counts, strict=True)}


def _pedestrian_base(renderer: SceneRenderer, x: float, y: float) -> float:
    """Pedestrians on a raised surface (sidewalk, park) stand on it, as the renderer places them."""
    surface = renderer.ground_map.lookup(np.array([x]), np.array([y]))
    return Z_SLAB if bool(SURFACE_RAISED[surface][0]) else 0.0


SIGN_THICKNESS_M = 0.12  # the plate's box for occlusion and truncation: a little deeper than the plate and post


def sign_class_index(sign: Sign) -> int | None:
    """The detector class of a town's sign (None: no class for its kind and value)."""
    name = sign_class(sign.kind.name, sign.value_kmh)
    return None if name is None else CLASSES.index(name)


def sign_view_angle(sign: Sign, pose: CameraPose) -> float:
    """Degrees between the way the sign's face looks (at the traffic that reads it) and the way to the camera:
    0 head-on, 90 edge-on, 180 from straight behind."""
    cx, cy = float(sign.position[0]), float(sign.position[1])
    face = sign.facing + math.pi
    to_cam = math.atan2(-pose.eye[1] - cy, pose.eye[0] - cx)  # map frame: world y flipped back
    return abs(math.degrees(math.remainder(to_cam - face, 2 * math.pi)))


def label_frame(segmentation: np.ndarray, depth_m: np.ndarray, pose: CameraPose, renderer: SceneRenderer,
                snapshots: list[ObjectSnapshot], town: Town, light_states: list[LightState],
                rules: LabelRules | None = None) -> list[ObjectLabel]:
    """Labels (and ignore regions) for every car, truck, pedestrian, traffic light and road sign with visible
    pixels."""
    rules = rules or LabelRules()
    h, w = segmentation.shape[:2]
    ids = segmentation[..., 1]
    boxes = _object_boxes(ids)
    snaps = {s.object_id: s for s in snapshots}
    out: list[ObjectLabel] = []
    for oid, (x0, y0, x1, y1, count) in boxes.items():
        reason = ""
        min_h, min_w, min_n = rules.min_height_px, rules.min_width_px, rules.min_pixels
        if oid >= LIGHT_ID_BASE:
            ap = town.approaches[oid - LIGHT_ID_BASE]
            hx, hy, hz = HOUSING_HALF
            zc = ap.head_height_m
            corners = box_corners(float(ap.light_head[0]), float(ap.light_head[1]), ap.travel_heading + math.pi,
                                  2 * hx, 2 * hy, zc - hz, zc + hz)
            cx, cy = float(ap.light_head[0]), float(ap.light_head[1])
            face = ap.travel_heading + math.pi  # the lamps look at the oncoming traffic
            to_cam = math.atan2(-pose.eye[1] - cy, pose.eye[0] - cx)  # map frame: world y flipped back
            angle = abs(math.degrees(math.remainder(to_cam - face, 2 * math.pi)))
            if angle > rules.light_side_deg:
                continue  # seen from behind: no lamps, no state; background
            cls = _STATE_CLASS[LightState(light_states[ap.index])]
            if angle > rules.light_facing_deg:
                reason = "side view"
            elif not np.any((ids[y0:y1, x0:x1] == oid)
                            & (segmentation[y0:y1, x0:x1, 0] == int(SemanticClass.TRAFFIC_LAMP))):
                reason = "lamps hidden"
        elif SIGN_ID_BASE <= oid < SIGN_ID_BASE + len(town.signs):
            sign = town.signs[oid - SIGN_ID_BASE]
            angle = sign_view_angle(sign, pose)
            if angle > rules.sign_side_deg:
                continue  # only the plate's back: background
            known = sign_class_index(sign)
            cls = known if known is not None else CLASSES.index(SIGN_CLASSES[0])
            half = sign.plate_size_m / 2
            cx, cy = float(sign.position[0]), float(sign.position[1])
            corners = box_corners(cx, cy, sign.facing, SIGN_THICKNESS_M, sign.plate_size_m,
                                  sign.plate_height_m - half, sign.plate_height_m + half)
            min_h = min_w = rules.min_sign_px
            min_n = rules.min_sign_pixels
            if known is None:
                reason = "unknown sign"
            elif angle > rules.sign_facing_deg:
                reason = "side view"
        elif oid in snaps:
            s = snaps[oid]
            cls = _KIND_CLASS.get(SemanticClass(s.kind))
            if cls is None:
                continue
            base = _pedestrian_base(renderer, s.x, s.y) if s.kind == SemanticClass.PEDESTRIAN else 0.0
            corners = box_corners(s.x, s.y, s.heading, s.length_m, s.width_m, base, base + s.height_m)
            cx, cy = s.x, s.y
        else:
            continue
        hull = projected_hull(pose, corners)
        in_image, visible = in_view_fraction(pose, corners), 1.0
        if hull is not None:
            poly, z_near = hull
            mask = np.zeros((h, w), np.uint8)
            cv2.fillConvexPoly(mask, np.round(poly * 16).astype(np.int32), 1, lineType=cv2.LINE_8, shift=4)
            inside = mask.astype(bool)
            occluded = int(np.count_nonzero(inside & (ids != oid) & (depth_m < z_near - rules.occluder_margin_m)))
            visible = count / max(count + occluded, 1)
        bw, bh = x1 - x0, y1 - y0
        if not reason:
            if visible < rules.min_visible_fraction:
                reason = "occluded"
            elif in_image < rules.min_in_image_fraction:
                reason = "truncated"
            elif bh < min_h or bw < min_w or count < min_n:
                reason = "small"
            elif CLASSES[cls] in LIMIT_CLASSES and min(bw, bh) < rules.min_limit_px:
                reason = "value unreadable"
        out.append(ObjectLabel(cls, (x0, y0, x1, y1), oid, pose.ground_distance(cx, cy), visible, in_image,
                               bool(reason), reason))
    return out


def render_and_label(renderer: SceneRenderer, world, camera: CameraConfig, weather: str,
                     rules: LabelRules | None = None):  # -> tuple[CameraFrame, list[ObjectLabel]]
    """Render the ego camera's frame of ``world`` (a ``sim.world.World``) and label it."""
    x, y, heading = float(world.ego.position[0]), float(world.ego.position[1]), float(world.ego.heading)
    renderer.sync(world.object_snapshots(), world.lights.states, view=(x, y, heading, camera.hfov_deg, camera.far_m))
    frame = renderer.render((x, y, heading), camera, weather)
    pose = CameraPose.of(renderer, (x, y, heading), camera)
    labels = label_frame(frame.segmentation, frame.depth_m, pose, renderer, world.object_snapshots(), world.town,
                         world.lights.states, rules)
    return frame, labels


# --------------------------------------------------------------------------- dataset generation
WEATHERS: tuple[str, ...] = ("noon", "dusk", "overcast", "night")


@dataclass(frozen=True)
class RigRange:
    """The cameras other cars carry: each sampled frame is rendered from one drawn uniformly from these ranges.

    Why: a detector trained on one mount sees a different picture on another car (objects sit at other heights
    and sizes in the image, the road fills another share of it, and the image's edges show what the training
    camera never showed) and invents objects there. The ranges cover a hatchback's to a van's mount and a
    narrow to a wide lens; the default rig (``sim.spec.CameraConfig``) lies inside them."""

    mount_height_m: tuple[float, float] = (1.1, 1.8)
    hfov_deg: tuple[float, float] = (70.0, 110.0)
    pitch_deg: tuple[float, float] = (-8.0, 0.0)

    def draw(self, rng: np.random.Generator, camera: CameraConfig) -> CameraConfig:
        """``camera`` with a mount height, field of view and pitch drawn from the ranges."""
        return replace(camera, mount_height_m=float(rng.uniform(*self.mount_height_m)),
                       hfov_deg=float(rng.uniform(*self.hfov_deg)), pitch_deg=float(rng.uniform(*self.pitch_deg)))


def camera_fields(camera: CameraConfig) -> dict[str, float]:
    """What a frame's meta line records of a camera that is not the env's own: the fields ``RigRange`` draws."""
    return {"mount_height_m": round(camera.mount_height_m, 3), "hfov_deg": round(camera.hfov_deg, 2),
            "pitch_deg": round(camera.pitch_deg, 2)}


@dataclass(frozen=True)
class SplitSpec:
    """Which towns and weathers one split is drawn from, and how many frames."""

    name: str
    town_seeds: tuple[int, ...]
    weathers: tuple[str, ...]
    frames: int
    frames_per_episode: int = 40
    pedestrian_count: int | None = None  # the world's pedestrians before the traffic density (None: its default)
    town_style: str | None = None  # sim.town_style's name (None: the env's default town, classic)
    sign_boost: bool = False  # sample more often while a sign faces the ego close ahead (see generate_split)
    rigs: RigRange | None = None  # each frame from a camera drawn from this range (None: the env's own camera)
    driver: str = "autopilot"  # who drives: "autopilot", or "agent" (frames of the camera-only agent's own runs)


def default_splits(train_frames: int = 6000, val_frames: int = 1200, test_frames: int = 1200,
                   peds_frames: int = 6000, peds_count: int = 60, peds2_frames: int = 6000,
                   rigs_frames: int = 8000, agent_frames: int = 3000) -> list[SplitSpec]:
    """Training towns 0-29; validation (checkpoint choice) towns 100-109; test (the reported figures) towns
    200-209. Neither held-out set shares a town with training; all four weathers are in each.
    ``train_peds`` and ``train_peds2`` are extra training data: towns 30-59 and 60-99 with ``peds_count``
    pedestrians per town (the world's default is 24), for the detector's weakest class; only generated when
    asked for by name. ``train_rigs``, ``val_rigs`` and ``test_rigs`` draw each frame's camera from ``RigRange``
    (other cars' mounts and lenses): training towns 30-99 with ``peds_count`` pedestrians, and the validation and
    test towns. ``train_agent`` is on-policy: the camera-only agent drives (one drawn car per episode) and each
    frame is what its detector gets, so the places it stands in (inside a junction, at an angle the autopilot never
    takes) are in the data, labelled from ground truth. These are classic towns and predate ``sim/splits.py``;
    ``styled_splits`` follows it."""
    return [SplitSpec("train", tuple(range(30)), WEATHERS, train_frames),
            SplitSpec("val", tuple(range(100, 110)), WEATHERS, val_frames),
            SplitSpec("test", tuple(range(200, 210)), WEATHERS, test_frames),
            SplitSpec("train_peds", tuple(range(30, 60)), WEATHERS, peds_frames, pedestrian_count=peds_count),
            SplitSpec("train_peds2", tuple(range(60, 100)), WEATHERS, peds2_frames, pedestrian_count=peds_count),
            SplitSpec("train_rigs", tuple(range(30, 100)), WEATHERS, rigs_frames, pedestrian_count=peds_count,
                      rigs=RigRange()),
            SplitSpec("train_agent", tuple(range(30, 100)), WEATHERS, agent_frames, pedestrian_count=peds_count,
                      rigs=RigRange(), driver="agent"),
            SplitSpec("val_rigs", tuple(range(100, 110)), WEATHERS, val_frames, rigs=RigRange()),
            SplitSpec("test_rigs", tuple(range(200, 210)), WEATHERS, test_frames, rigs=RigRange())]


# The dataset's split names -> sim/splits.py's town-seed ranges.
TOWN_SPLIT_OF = {"train": "train", "val": "validation", "test": "test"}
STYLED_TOWNS = {"train": 30, "val": 10, "test": 10}  # towns per split (the first of its range), as the classic ones


def styled_splits(style: str, train_frames: int, val_frames: int, test_frames: int,
                  towns: dict[str, int] | None = None) -> list[SplitSpec]:
    """``train_STYLE``, ``val_STYLE`` and ``test_STYLE``: towns of a town style from the town-seed splits of
    ``sim/splits.py`` (train 0-3999, validation 4000-4999, test 5000-5999; the first 30, 10 and 10 seeds unless
    ``towns`` says otherwise), all four weathers, and frames sampled more often near signs (``sign_boost``)."""
    from towndrive.sim.splits import split_towns
    from towndrive.sim.town_style import style_named

    style_named(style)  # one sentence if unknown
    towns = {**STYLED_TOWNS, **(towns or {})}
    frames = {"train": train_frames, "val": val_frames, "test": test_frames}
    return [SplitSpec(f"{part}_{style}", tuple(split_towns(TOWN_SPLIT_OF[part], towns[part])), WEATHERS, frames[part],
                      town_style=style, sign_boost=True) for part in ("train", "val", "test")]


SIGN_BOOST_M = (4.0, 30.0)  # a sign this far ahead of the camera...
SIGN_BOOST_DEG = 40.0  # ...within this angle of the heading, whose face looks at the ego within sign_facing_deg


def sign_ahead(world, rules: LabelRules | None = None) -> bool:
    """Whether a sign faces the ego within ``SIGN_BOOST_M`` ahead: where the sampling of a styled split speeds up."""
    signs = world.town.signs
    if not signs or world.ego.speed < 1.0:  # standing still, more frames would be copies
        return False
    rules = rules or LabelRules()
    ex, ey, heading = float(world.ego.position[0]), float(world.ego.position[1]), float(world.ego.heading)
    for sign in signs:
        dx, dy = float(sign.position[0]) - ex, float(sign.position[1]) - ey
        dist = math.hypot(dx, dy)
        if not SIGN_BOOST_M[0] <= dist <= SIGN_BOOST_M[1]:
            continue
        if abs(math.degrees(math.remainder(math.atan2(dy, dx) - heading, 2 * math.pi))) > SIGN_BOOST_DEG:
            continue
        face = sign.facing + math.pi  # the face looks back along the traffic that reads it
        if abs(math.degrees(math.remainder(math.atan2(-dy, -dx) - face, 2 * math.pi))) <= rules.sign_facing_deg:
            return True
    return False


def generate_split(root, spec: SplitSpec, seed: int, progress: bool = True) -> dict:
    """Drive the autopilot through ``spec``'s towns and weathers and write sampled frames in the YOLO layout.

    The env steps without pictures (fast); only sampled frames are rendered, by this function's own
    renderer, with segmentation and depth for the labels. Frames are sampled every 0.4-1.25 s of driving;
    while the car stands still most samples are skipped, so a long red light does not fill the set with
    copies. With ``spec.sign_boost``, while a sign faces the ego 4-30 m ahead the next sample comes after
    0.2-0.5 s instead, unless it stands still (signs are few, and a car passes one in a couple of seconds).
    Returns counts per class (labels and ignore regions).
    """
    import json
    from pathlib import Path

    from tqdm import tqdm

    from towndrive.agent.drivers import make_driver
    from towndrive.agent.perception.model_view import model_camera
    from towndrive.envs.drive_env import DriveConfig, DriveEnv

    root = Path(root)
    img_dir, lab_dir = root / "images" / spec.name, root / "labels" / spec.name
    img_dir.mkdir(parents=True, exist_ok=True)
    lab_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng((seed, sum(map(ord, spec.name))))
    on_policy = spec.driver == "agent"
    if spec.driver not in ("autopilot", "agent"):
        raise ValueError(f"unknown driver {spec.driver!r} for split {spec.name}; use 'autopilot' or 'agent'.")
    # the agent drives from its camera's pictures; the autopilot needs none (only sampled frames are rendered)
    config = DriveConfig(render_camera=on_policy, terminate_on_route_deviation=False, terminate_on_infraction=True)
    if spec.pedestrian_count is not None:
        config = replace(config, world=replace(config.world, pedestrian_count=spec.pedestrian_count))
    env = DriveEnv(config)
    camera = env.config.camera
    agent = make_driver("agent", stage_threads=1) if on_policy else None
    renderer: SceneRenderer | None = None
    renderer_town: int | None = None
    counts: dict = {"frames": 0, "labels": dict.fromkeys(CLASSES, 0), "ignored": dict.fromkeys(CLASSES, 0)}
    index = 0
    episode = 0
    bar = tqdm(total=spec.frames, desc=f"dataset {spec.name}", unit="frame", disable=not progress)
    with open(root / f"{spec.name}_meta.jsonl", "w") as meta:
        while index < spec.frames:
            town_seed = spec.town_seeds[episode % len(spec.town_seeds)]
            weather = spec.weathers[(episode // len(spec.town_seeds) + episode) % len(spec.weathers)]
            density = float(rng.uniform(1.0, 2.2))
            options = {"town_seed": town_seed, "weather": weather, "traffic_density": density}
            if spec.town_style is not None:
                options["town_style"] = spec.town_style
            seen: CameraConfig | None = None
            if on_policy:
                # The agent's camera is one car's for the whole episode (its stages are built for it); the frame
                # kept is what its detector gets: the trained lens and pitch at this car's mounting height.
                mount = camera if spec.rigs is None else spec.rigs.draw(rng, camera)
                if mount != env.config.camera:
                    env.close()
                    env = DriveEnv(replace(config, camera=mount))
                seen = model_camera(mount)
            obs, _ = env.reset(seed=int(rng.integers(2**31 - 1)), options=options)
            world = env.world
            assert world is not None
            if renderer is None or renderer_town != id(world.town):
                if renderer is not None:
                    renderer.close()
                renderer, renderer_town = SceneRenderer(world.town, seed=world.town.seed), id(world.town)
            driver = agent if agent is not None else make_driver("autopilot")
            driver.reset(env)
            next_sample = int(rng.integers(10, 40))
            taken, step, stopped_before = 0, 0, False
            while taken < spec.frames_per_episode and index < spec.frames and step < 4000:
                obs, _, terminated, truncated, _ = env.step(driver.act(obs))
                step += 1
                if terminated or truncated:
                    break
                if spec.sign_boost and step % 4 == 0 and next_sample - step > 10 and sign_ahead(world):
                    next_sample = step + int(rng.integers(4, 11))
                if step < next_sample:
                    continue
                next_sample = step + int(rng.integers(8, 26))
                if spec.sign_boost and sign_ahead(world):
                    next_sample = step + int(rng.integers(4, 11))
                stopped = world.ego.speed < 0.3
                if stopped and stopped_before and rng.random() < 0.75:
                    continue
                stopped_before = stopped
                # the agent's episode keeps one car's camera; else the env's, or one drawn per frame
                shot = seen or (camera if spec.rigs is None else spec.rigs.draw(rng, camera))
                frame, labels = render_and_label(renderer, world, shot, weather)
                name = f"{spec.name}_{index:06d}"
                cv2.imwrite(str(img_dir / f"{name}.png"), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
                kept = [lab for lab in labels if not lab.ignore]
                (lab_dir / f"{name}.txt").write_text("".join(lab.yolo_line(camera.width, camera.height) + "\n"
                                                             for lab in kept))
                rig = {"camera": camera_fields(shot)} if on_policy or spec.rigs is not None else {}
                meta.write(json.dumps({"image": f"images/{spec.name}/{name}.png", "town_seed": town_seed,
                                       "town_style": world.town.config.style, "weather": weather,
                                       "time_s": round(world.time_s, 2),
                                       **rig, "objects": [lab.as_dict() for lab in labels]}) + "\n")
                for lab in labels:
                    counts["ignored" if lab.ignore else "labels"][lab.name] += 1
                index += 1
                taken += 1
                counts["frames"] += 1
                bar.update(1)
            episode += 1
    bar.close()
    if renderer is not None:
        renderer.close()
    env.close()
    return counts


def write_dataset_yaml(root) -> None:
    """The dataset YAML any YOLO tool reads (ultralytics' layout: path, train, val, names), written by hand:
    it is five keys, not worth a YAML dependency."""
    from pathlib import Path

    root = Path(root)
    lines = [f"path: {root.resolve()}", "train: images/train", "val: images/val", "test: images/test", "names:"]
    lines += [f"  {k}: {name}" for k, name in enumerate(CLASSES)]
    (root / "dataset.yaml").write_text("\n".join(lines) + "\n")
