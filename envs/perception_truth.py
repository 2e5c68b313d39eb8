"""Ground truth for measuring perception, and the metrics that compare against it. Evaluation only.

The perception modules in ``agent/`` (lanes, stop lines, tracking, stereo) never import this file:
they see pixels and the camera's calibration, nothing else. The evaluations in ``bench/`` use it to
turn the simulator's state into labels:

- lane lines: the painted boundaries of the ego's lane, found in the renderer's own ground map (so the
  truth is where the paint is, not where the lane model says it should be), projected into the image
  with an independent pinhole model built from the renderer's camera pose, occluded points dropped;
- the lateral offset both from the lane model's centre (``World.lane_offset_m``) and from the middle
  of the two painted lines (the markings are not symmetric about the lane centre: the edge line is
  painted 0.28 m inside the lane's outer edge);
- the distance from the camera to the next stop line on the route, and whether any of it is visible;
- object boxes with ids (from the segmentation map: channel 1 = object id);
- the left camera's metric depth, hence disparity ``f B / Z``.

Metrics: TuSimple lane accuracy with false and missed lanes, KITTI's D1 disparity outlier rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from towndrive.sim.ego import EgoVehicle
from towndrive.sim.objects import SemanticClass
from towndrive.sim.render import CameraConfig, SceneRenderer
from towndrive.sim.scene_meshes import GroundMap, Surface, to_world
from towndrive.sim.town import LaneIndex, Town
from towndrive.sim.world import World

OBJECT_CLASSES = ("car", "truck", "pedestrian")


# --------------------------------------------------------------------------- camera model (independent of agent/)
@dataclass(frozen=True)
class CameraPose:
    """The renderer's camera in pybullet's world frame: eye and orthonormal right, down, forward axes."""

    eye: np.ndarray
    right: np.ndarray
    down: np.ndarray
    forward: np.ndarray
    k: np.ndarray

    def to_camera(self, points_world: np.ndarray) -> np.ndarray:
        """N x 3 world points -> N x 3 camera coordinates (x right, y down, z forward)."""
        d = np.asarray(points_world, float) - self.eye
        return np.stack([d @ self.right, d @ self.down, d @ self.forward], axis=-1)

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N x 2) and z-depth (N) of world points."""
        c = self.to_camera(points_world)
        z = c[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (self.k @ c.T).T
            uv = uv[:, :2] / uv[:, 2:3]
        return uv, z


def camera_pose(world: World, camera: CameraConfig, lateral_m: float = 0.0) -> CameraPose:
    """Where the renderer puts the camera for the ego's current pose (same formulas as ``SceneRenderer``)."""
    x, y, h = float(world.ego.position[0]), float(world.ego.position[1]), float(world.ego.heading)
    cx = x + camera.mount_forward_m * math.cos(h) - lateral_m * math.sin(h)
    cy = y + camera.mount_forward_m * math.sin(h) + lateral_m * math.cos(h)
    eye = to_world(cx, cy, camera.mount_height_m)
    yaw, pitch = -h, math.radians(camera.pitch_deg)
    forward = np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return CameraPose(eye, right, down, forward, camera.intrinsics())


# --------------------------------------------------------------------------- lane lines
@lru_cache(maxsize=4096)
def _marking_laterals_cached(town_id: int, lane: LaneIndex) -> tuple[float, float]:
    town, gm = _TOWNS[town_id]
    return _scan_markings(town, gm, lane)


_TOWNS: dict[int, tuple[Town, GroundMap]] = {}


def marking_laterals(town: Town, ground_map: GroundMap, lane: LaneIndex) -> tuple[float, float]:
    """Lateral positions (m, relative to the lane's centre, positive right) of the painted lines left and
    right of a lane, read from the ground map: the middle of the paint runs nearest each lane edge,
    median over the lane's length. nan where a side has no paint."""
    _TOWNS[id(town)] = (town, ground_map)
    return _marking_laterals_cached(id(town), lane)


def _scan_markings(town: Town, gm: GroundMap, index: LaneIndex) -> tuple[float, float]:
    lane = town.lane(index)
    half = town.lane_width / 2
    lats = np.arange(-half - 0.6, half + 0.6, 0.02)
    found: list[list[float]] = [[], []]
    for s in np.linspace(1.0, max(1.0, lane.length - 1.0), 40):
        pts = np.array([lane.position(float(s), float(t)) for t in lats])
        surf = gm.lookup(pts[:, 0], pts[:, 1])
        paint = (surf == Surface.WHITE) | (surf == Surface.YELLOW)
        if not paint.any():
            continue
        edges = np.diff(np.r_[0, paint.astype(np.int8), 0])
        starts, ends = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
        centres = 0.5 * (lats[starts] + lats[ends - 1])
        for side, target in ((0, -half), (1, half)):
            d = np.abs(centres - target)
            if d.min() < 0.45:
                found[side].append(float(centres[np.argmin(d)]))
    return (float(np.median(found[0])) if found[0] else math.nan, float(np.median(found[1])) if found[1] else math.nan)


def lane_z_range_rows(camera: CameraConfig, z_min_m: float, z_max_m: float, step_px: int = 2) -> np.ndarray:
    """Image rows (TuSimple's h_samples) whose road lies between ``z_min_m`` and ``z_max_m`` ahead of the camera."""
    k = camera.intrinsics()
    theta = math.radians(-camera.pitch_deg)

    def row(z: float) -> float:
        return k[1, 2] + k[1, 1] * math.tan(math.atan2(camera.mount_height_m, z) - theta)

    lo, hi = int(math.ceil(row(z_max_m))), int(math.floor(min(row(z_min_m), camera.height - 1)))
    return np.arange(hi, lo - 1, -step_px)


@dataclass
class LaneTruth:
    """The ego lane's painted boundaries in one frame."""

    lanes_x: list[np.ndarray]  # per line: image x at each h_sample, -2 where there is no visible line
    lateral_m: tuple[float, float]  # the lines' lateral positions relative to the lane centre
    offset_m: float  # World.lane_offset_m: vehicle centre right of the lane model's centre
    painted_offset_m: float  # vehicle centre right of the middle of the two painted lines
    on_road: bool  # on a plain road or bend lane (painted), not inside a junction
    radius_m: float = math.inf  # the lane's curvature radius (magnitude) where the car is; inf on straight roads


def lane_truth(world: World, camera: CameraConfig, ground_map: GroundMap, depth_m: np.ndarray,
               h_samples: np.ndarray, look_ahead_m: float = 45.0) -> LaneTruth:
    """Project the ego lane's painted lines into the image along the route ahead (until a junction)."""
    town = world.town
    offset = world.lane_offset_m()
    loc = world.ego_lane
    empty = LaneTruth([], (math.nan, math.nan), offset, math.nan, False)
    if loc is None:
        return empty
    index, s0, _ = loc
    if town.lane_info[index].kind == "connector":
        return empty
    lat = marking_laterals(town, ground_map, index)
    painted = offset - 0.5 * (lat[0] + lat[1]) if all(map(math.isfinite, lat)) else math.nan
    # Lanes to follow: this one, then the route's next edges while they are painted (road or bend).
    chain: list[tuple[LaneIndex, float]] = [(index, max(0.0, s0 - 4.0))]
    edge = index[:2]
    if edge in world.route:
        k = world.route.index(edge)
        prev = index
        for nxt in world.route[k + 1:k + 3]:
            nidx = town.next_lane(prev, nxt)
            prev = nidx
            if town.lane_info.get(nidx) is None or town.lane_info[nidx].kind == "connector":
                break
            chain.append((nidx, 0.0))
    pose = camera_pose(world, camera)
    lanes_x = []
    for side in (0, 1):
        pts = []
        left_m = look_ahead_m + 4.0
        for lane_index, s_start in chain:
            lane = town.lane(lane_index)
            lat_here = marking_laterals(town, ground_map, lane_index)[side]
            if not math.isfinite(lat_here):
                break
            s_end = min(lane.length, s_start + left_m)
            for s in np.arange(s_start, s_end, 0.25):
                pts.append(lane.position(float(s), lat_here))
            left_m -= s_end - s_start
            if left_m <= 0:
                break
        if len(pts) < 2:
            continue
        p = np.array(pts)
        uv, z = pose.project(to_world(p[:, 0], p[:, 1], 0.0))
        keep = z > 0.5
        uv, z = uv[keep], z[keep]
        if len(z) < 2:
            continue
        order = np.argsort(uv[:, 1])
        v, u, zz = uv[order, 1], uv[order, 0], z[order]
        x = np.full(len(h_samples), -2.0)
        inside = (h_samples >= v[0]) & (h_samples <= v[-1])
        x[inside] = np.interp(h_samples[inside], v, u)
        zr = np.interp(h_samples, v, zz)
        h, w = depth_m.shape
        for j in np.nonzero(inside)[0]:
            col = int(round(x[j]))
            if not 0 <= col < w:
                x[j] = -2.0
                continue
            if depth_m[int(h_samples[j]), col] < 0.97 * zr[j] - 0.3:  # something stands in front of the paint
                x[j] = -2.0
        if (x >= 0).sum() >= 2:
            lanes_x.append(x)
    radius = float(getattr(town.lane(index), "radius", math.inf))
    return LaneTruth(lanes_x, lat, offset, painted, True, radius)


# --------------------------------------------------------------------------- TuSimple metric
def tusimple_angle(xs: np.ndarray, ys: np.ndarray) -> float:
    """Angle of a lane's image line from the vertical (TuSimple's threshold correction)."""
    ok = xs >= 0
    if ok.sum() > 1:
        k = np.polyfit(ys[ok], xs[ok], 1)[0]
        return float(math.atan(k))
    return 0.0


@dataclass
class TuSimpleFrame:
    accuracy: float  # mean over GT lanes of the best-matching prediction's share of correct points
    false_positives: int
    false_negatives: int
    n_pred: int
    n_gt: int


def tusimple_frame(pred: list[np.ndarray], gt: list[np.ndarray], h_samples: np.ndarray, thresh_px: float,
                   match_accuracy: float = 0.85) -> TuSimpleFrame:
    """TuSimple's per-image evaluation: a point is correct within ``thresh_px / cos(angle)``; a GT lane is
    matched when some prediction gets at least ``match_accuracy`` of its points."""
    if not gt:
        return TuSimpleFrame(1.0, len(pred), 0, len(pred), 0)
    matched, total = 0, 0.0
    for g in gt:
        thresh = thresh_px / math.cos(tusimple_angle(g, h_samples))
        valid = g >= 0
        best = 0.0
        for p in pred:
            correct = (np.abs(np.where(p >= 0, p, -1e6) - g) < thresh) & valid
            best = max(best, float(correct.sum()) / max(1, int(valid.sum())))
        if best >= match_accuracy:
            matched += 1
        total += best
    fp = max(0, len(pred) - matched)
    return TuSimpleFrame(total / len(gt), fp, len(gt) - matched, len(pred), len(gt))


# --------------------------------------------------------------------------- stop lines
@dataclass
class StopLineTruth:
    distance_m: float  # camera to the stop bar's near edge, along the lane (nan: none within the horizon)
    visible: bool  # some of the bar across the ego lane is in the image and not hidden


def stop_line_truth(world: World, camera: CameraConfig, segmentation: np.ndarray, horizon_m: float = 60.0) -> StopLineTruth:
    """The next stop line on the route: distance from the camera and whether it can be seen."""
    nl = world.next_light(horizon_m)
    if nl is None:
        return StopLineTruth(math.nan, False)
    # NextLight is measured from the front bumper; the camera is mount_forward_m ahead of the centre.
    dist = float(nl.distance_m) + EgoVehicle.LENGTH / 2 - camera.mount_forward_m
    ap = world.town.approaches[nl.approach]
    travel = np.array([math.cos(ap.travel_heading), math.sin(ap.travel_heading)])
    right = np.array([-travel[1], travel[0]])
    lane_k = world.ego_lane[0][2] if world.ego_lane is not None else 0
    w = world.town.lane_width
    pts = np.array([ap.stop_line_center + travel * 0.25 + right * ((lane_k - 0.5) * w + t)
                    for t in np.linspace(-1.2, 1.2, 9)])
    uv, z = camera_pose(world, camera).project(to_world(pts[:, 0], pts[:, 1], 0.0))
    h, wd = segmentation.shape[:2]
    visible = False
    for (u, v), zc in zip(uv, z, strict=True):
        if zc <= 0.5 or not (0 <= u < wd and 0 <= v < h):
            continue
        r0, r1 = max(0, int(v) - 1), min(h, int(v) + 2)
        if (segmentation[r0:r1, int(u), 0] == SemanticClass.STOP_LINE).any():
            visible = True
            break
    return StopLineTruth(dist, visible)


@dataclass
class ZebraTruth:
    bar_m: float  # camera to the near edge of the stop (or give-way) line of the entry ahead, along the heading; nan: none
    near_m: float  # camera to the near edge of that entry's zebra along the car's heading; nan when none or missed
    far_m: float  # ... and to its far edge


def zebra_truth(world: World, camera: CameraConfig) -> ZebraTruth:
    """The zebra across the arm by which the car's current road enters a junction, where the camera's forward
    ray crosses its painted area (``Town.crosswalks``, matched to the entry by node and arm)."""
    nan = math.nan
    if world.ego_lane is None:
        return ZebraTruth(nan, nan, nan)
    town = world.town
    entry = town.entry_for_edge(world.ego_lane[0][:2])
    if entry is None:
        return ZebraTruth(nan, nan, nan)
    ahead = np.array([math.cos(world.ego.heading), math.sin(world.ego.heading)])
    cam = world.ego.position + ahead * camera.mount_forward_m
    bar = float((entry.line_center - cam) @ ahead)
    hits: list[float] = []
    for cw in town.crosswalks:
        if cw.node != entry.node or cw.arm != entry.arm:
            continue
        poly = cw.polygon
        for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
            m = np.array([[ahead[0], a[0] - b[0]], [ahead[1], a[1] - b[1]]])
            if abs(np.linalg.det(m)) < 1e-9:
                continue
            t, u = np.linalg.solve(m, a - cam)
            if 0.0 <= u <= 1.0:
                hits.append(float(t))
    if len(hits) < 2:
        return ZebraTruth(bar, nan, nan)
    return ZebraTruth(bar, min(hits), max(hits))


# --------------------------------------------------------------------------- objects
def object_boxes(info: dict, min_pixels: int = 25) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth boxes (N x 4: x0, y0, x1, y1 in pixels) and simulator object ids of the cars, trucks
    and pedestrians visible in a frame (``info['objects']`` is built from the segmentation map)."""
    objs = [o for o in info.get("objects", []) if o["class"] in OBJECT_CLASSES and o["pixels"] >= min_pixels]
    if not objs:
        return np.zeros((0, 4)), np.zeros(0, np.int64)
    return np.array([o["bbox"] for o in objs], float), np.array([o["id"] for o in objs], np.int64)


def boxes_from_segmentation(segmentation: np.ndarray, min_pixels: int = 25) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes, ids and pixel masks' object ids (for distances) of moving objects straight from a segmentation map."""
    cls, oid = segmentation[..., 0], segmentation[..., 1]
    movers = np.isin(cls, [SemanticClass.CAR, SemanticClass.TRUCK, SemanticClass.PEDESTRIAN]) & (oid > 0)
    ids, counts = np.unique(oid[movers], return_counts=True)
    boxes, keep = [], []
    for i, n in zip(ids, counts, strict=True):
        if n < min_pixels:
            continue
        rr, cc = np.nonzero(movers & (oid == i))
        boxes.append([cc.min(), rr.min(), cc.max() + 1, rr.max() + 1])
        keep.append(i)
    return np.array(boxes, float).reshape(-1, 4), np.array(keep, np.int64), oid


# --------------------------------------------------------------------------- stereo
@dataclass
class StereoTruth:
    left: np.ndarray
    right: np.ndarray
    depth_m: np.ndarray  # the left camera's z-depth
    segmentation: np.ndarray  # the left camera's (class, id)
    disparity_px: np.ndarray  # f B / Z; 0 where there is only sky (no ground truth)


def stereo_truth(renderer: SceneRenderer, world: World, camera: CameraConfig, weather: str) -> StereoTruth:
    """Render the stereo pair again with its depth (the env's observation keeps only the pictures)."""
    pose = (float(world.ego.position[0]), float(world.ego.position[1]), float(world.ego.heading))
    left, right = renderer.render_stereo(pose, camera, weather)
    depth = left.depth_m
    sky = (left.segmentation[..., 0] == SemanticClass.SKY) | ~np.isfinite(depth) | (depth >= 0.99 * camera.far_m)
    disp = np.where(sky, 0.0, camera.focal_px * camera.stereo_baseline_m / np.maximum(depth, 1e-3)).astype(np.float32)
    return StereoTruth(left.rgb, right.rgb, depth, left.segmentation, disp)


def d1_all(estimate_px: np.ndarray, truth_px: np.ndarray, valid: np.ndarray) -> float:
    """KITTI 2015 D1: share of ground-truth pixels whose disparity is off by more than 3 px and 5 %."""
    err = np.abs(estimate_px - truth_px)
    bad = (err > 3.0) & (err > 0.05 * truth_px)
    n = int(valid.sum())
    return float((bad & valid).sum()) / max(1, n)
