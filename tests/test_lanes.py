"""Lane and stop-line detection: the bird's-eye geometry against the renderer, and the detectors on
synthetic roads whose lines are placed in metres (so the expected offset and radius are known)."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from towndrive.agent.perception.lanes import BirdsEye, BirdsEyeConfig, LaneDetector, LaneLine, ground_homography
from towndrive.agent.perception.lanes_hough import HoughLaneDetector
from towndrive.agent.perception.stop_line import StopLineDetector
from towndrive.envs.perception_truth import lane_z_range_rows, tusimple_frame
from towndrive.sim.render import CameraConfig

CAM = CameraConfig()


def synthetic_road(lines: list[tuple[float, float, float]], stop_at_m: float | None = None, noise: int = 0,
                   seed: int = 0) -> np.ndarray:
    """A camera image of a flat grey road with white lines x = a z^2 + b z + c (metres), rendered by warping a
    fine top-down canvas through the camera homography."""
    cfg = BirdsEyeConfig(x_min_m=-10, x_max_m=10, z_min_m=0.5, z_max_m=80, px_per_m_x=50, px_per_m_z=50)
    scale = 4  # render 4x larger and shrink with area averaging, so far thin lines are not aliased away
    be = BirdsEye(CAM, cfg)
    # small-image pixel (u, v) covers big-image pixels whose centres average to scale * (u + 0.5) - 0.5
    to_big = np.array([[scale, 0, (scale - 1) / 2], [0, scale, (scale - 1) / 2], [0, 0, 1.0]])
    w, h = cfg.size
    canvas = np.full((h, w, 3), (62, 62, 66), np.uint8)
    z = be.z_of_row
    for a, b, c in lines:
        x = a * z ** 2 + b * z + c
        u = (x - cfg.x_min_m) * cfg.px_per_m_x
        for du in range(-3, 4):  # 0.14 m wide line
            cols = np.round(u + du).astype(int)
            ok = (cols >= 0) & (cols < w)
            canvas[np.arange(h)[ok], cols[ok]] = (235, 235, 230)
    if stop_at_m is not None:
        r0, r1 = int((cfg.z_max_m - stop_at_m - 0.5) * cfg.px_per_m_z), int((cfg.z_max_m - stop_at_m) * cfg.px_per_m_z)
        c0, c1 = int((-3.4 - cfg.x_min_m) * cfg.px_per_m_x), int((3.4 - cfg.x_min_m) * cfg.px_per_m_x)
        canvas[r0:r1, c0:c1] = (240, 240, 238)
    img = cv2.warpPerspective(canvas, to_big @ be.bev_to_image, (CAM.width * scale, CAM.height * scale),
                              flags=cv2.INTER_LINEAR, borderValue=(120, 160, 210))
    img = cv2.resize(img, (CAM.width, CAM.height), interpolation=cv2.INTER_AREA)
    if noise:
        rng = np.random.default_rng(seed)
        img = np.clip(img.astype(np.int16) + rng.integers(-noise, noise + 1, img.shape), 0, 255).astype(np.uint8)
    return img


def test_homography_matches_renderer_depth(town) -> None:
    """Road pixels mapped to the ground with our homography have the renderer's metric depth."""
    from towndrive.sim.objects import SemanticClass
    from towndrive.sim.render import SceneRenderer

    renderer = SceneRenderer(town, seed=town.seed)
    lane = town.lane(town.road_lanes()[0])
    x, y = lane.position(10.0, 0.0)
    frame = renderer.render((float(x), float(y), float(lane.heading_at(10.0))), CAM)
    renderer.close()
    be = BirdsEye(CAM)
    h_inv = np.linalg.inv(ground_homography(CAM))
    theta = math.radians(-CAM.pitch_deg)
    rows, cols = np.nonzero(frame.segmentation[..., 0] == SemanticClass.ROAD)
    assert len(rows) > 1000
    g = h_inv @ np.vstack([cols, rows, np.ones(len(rows))])
    gz = g[1] / g[2]
    predicted = gz * math.cos(theta) + CAM.mount_height_m * math.sin(theta)  # camera z of (x, -h, z)
    err = np.abs(predicted - frame.depth_m[rows, cols]) / frame.depth_m[rows, cols]
    assert np.median(err) < 0.01 and np.percentile(err, 95) < 0.03
    # Rows and distances agree both ways.
    z = np.array([4.0, 8.0, 15.0, 25.0])
    uv = be.image_of_ground(np.zeros(4), z)
    assert np.allclose(be.ground_z_of_row(uv[:, 1]), z, rtol=1e-6)
    assert math.isnan(be.ground_z_of_row(np.array([0.0]))[0])  # the top row is sky


@pytest.mark.parametrize("car_offset_m", [-0.6, 0.0, 0.45])
def test_sliding_windows_offset_on_straight_road(car_offset_m: float) -> None:
    # Lane lines at +-1.75 m about the lane centre; the car is car_offset_m right of the centre.
    img = synthetic_road([(0, 0, -1.75 - car_offset_m), (0, 0, 1.75 - car_offset_m), (0, 0, 5.25 - car_offset_m)], noise=6)
    det = LaneDetector(CAM)
    res = det.detect(img)
    assert res.detected and res.left is not None and res.right is not None
    assert abs(res.offset_m - car_offset_m) < 0.05
    assert abs(res.lane_width_m - 3.5) < 0.1 or abs((res.right.x_at(0) - res.left.x_at(0)) - 3.5) < 0.1
    assert abs(res.curvature_radius_m) > 500  # straight


def test_curvature_radius_and_tracking_mode() -> None:
    radius = 60.0  # x = z^2 / (2 R): a right-hand bend seen from its start
    a = 1 / (2 * radius)
    img = synthetic_road([(a, 0, -1.75), (a, 0, 1.75)])
    det = LaneDetector(CAM)
    first = det.detect(img)
    second = det.detect(img)
    assert first.detected and second.detected
    assert not first.used_previous and second.used_previous
    assert 0.7 * radius < second.curvature_radius_m < 1.4 * radius  # positive: bends right
    mirrored = LaneDetector(CAM).detect(synthetic_road([(-a, 0, -1.75), (-a, 0, 1.75)]))
    assert mirrored.curvature_radius_m < 0


def test_no_lane_when_no_paint() -> None:
    res = LaneDetector(CAM).detect(synthetic_road([], noise=8))
    assert not res.detected and math.isnan(res.offset_m)


def test_hough_offset() -> None:
    img = synthetic_road([(0, 0, -1.75 - 0.3), (0, 0, 1.75 - 0.3)])
    res = HoughLaneDetector(CAM).detect(img)
    assert res.detected
    assert abs(res.offset_m - 0.3) < 0.15


@pytest.mark.parametrize("distance_m", [5.0, 9.0, 14.0])
def test_stop_line_distance(distance_m: float) -> None:
    img = synthetic_road([(0, 0, -1.75), (0, 0, 1.75)], stop_at_m=distance_m)
    det = LaneDetector(CAM)
    lanes = det.detect(img)
    line = StopLineDetector(CAM).detect(img, lanes)
    assert line is not None
    assert abs(line.distance_m - distance_m) < 0.5
    assert StopLineDetector(CAM).detect(synthetic_road([(0, 0, -1.75), (0, 0, 1.75)]), lanes) is None


def test_stop_line_needs_the_lane_the_car_is_in() -> None:
    """Lines that bound a lane beside the car (the oncoming one, locked onto at night) give no corridor for a bar,
    even where that corridor would find one (here it still overlaps the painted bar)."""
    img = synthetic_road([(0, 0, -1.75), (0, 0, 1.75)], stop_at_m=9.0)
    lanes = LaneDetector(CAM).detect(img)
    assert StopLineDetector(CAM).detect(img, lanes) is not None
    assert lanes.left is not None and lanes.right is not None
    over = np.array([0.0, 0.0, 2.5])  # both lines 2.5 m to the left: the right one 0.75 m left of the camera
    beside = dataclasses.replace(lanes, left=dataclasses.replace(lanes.left, coeffs=lanes.left.coeffs - over),
                                 right=dataclasses.replace(lanes.right, coeffs=lanes.right.coeffs - over))
    assert StopLineDetector(CAM).detect(img, beside) is None


def test_tusimple_metric() -> None:
    rows = lane_z_range_rows(CAM, 3.0, 30.0)
    gt = [np.linspace(100, 150, len(rows)), np.linspace(220, 170, len(rows))]
    perfect = tusimple_frame([g.copy() for g in gt], gt, rows, 5.0)
    assert perfect.accuracy == 1.0 and perfect.false_positives == 0 and perfect.false_negatives == 0
    shifted = tusimple_frame([gt[0] + 12.0, gt[1]], gt, rows, 5.0)
    assert shifted.false_negatives == 1 and shifted.false_positives == 1 and shifted.accuracy == pytest.approx(0.5)
    missing = tusimple_frame([gt[0]], gt, rows, 5.0)
    assert missing.false_negatives == 1 and missing.false_positives == 0


def test_ground_truth_lines_lie_on_painted_pixels() -> None:
    """The evaluation's lane truth (projected from the ground map) falls on lane-marking pixels of the render."""
    from towndrive.envs.drive_env import DriveConfig, DriveEnv
    from towndrive.envs.perception_truth import lane_truth
    from towndrive.sim.objects import SemanticClass

    env = DriveEnv(DriveConfig(observe_depth=True, observe_segmentation=True))
    obs, _ = env.reset(seed=4, options={"traffic_density": 0.0})
    rows = lane_z_range_rows(CAM, 3.0, 15.0)
    assert env.world is not None and env.renderer is not None
    gt = lane_truth(env.world, CAM, env.renderer.ground_map, obs["depth"], rows)
    env.close()
    assert gt.on_road and len(gt.lanes_x) == 2
    paint = obs["segmentation"][..., 0] == SemanticClass.LANE_MARKING
    shares = []
    for x in gt.lanes_x:
        ok = x >= 0
        hit = [paint[int(r), max(0, int(round(c)) - 2):int(round(c)) + 3].any() for r, c in zip(rows[ok], x[ok], strict=True)]
        shares.append(float(np.mean(hit)))
    assert max(shares) > 0.9  # the solid line (edge or centre line)
    assert min(shares) > 0.2  # a dashed line: paint on about a third of its length
    assert abs(gt.lateral_m[1] - gt.lateral_m[0] - 3.3) < 0.15  # painted lines are 3.2-3.4 m apart


def marked_road(car_offset_m: float, lane: str) -> np.ndarray:
    """A camera image of the town's two-lane carriageway painted by its marking spec (sim/town.py): a double
    yellow centre line (0.14 m lines 0.06-0.20 m either side of the boundary), a dashed white divider (3 m dashes,
    6 m gaps) on the boundary, a solid white edge line 0.21-0.35 m inside the outer edge. The car is in the
    ``lane`` ("inner" or "outer") at ``car_offset_m`` right of that lane's centre."""
    cfg = BirdsEyeConfig(x_min_m=-10, x_max_m=10, z_min_m=0.5, z_max_m=80, px_per_m_x=50, px_per_m_z=50)
    scale = 4
    be = BirdsEye(CAM, cfg)
    to_big = np.array([[scale, 0, (scale - 1) / 2], [0, scale, (scale - 1) / 2], [0, 0, 1.0]])
    w, h = cfg.size
    canvas = np.full((h, w, 3), (62, 62, 66), np.uint8)
    # lateral positions of the paint's middle, relative to the car's lane centre (positive right)
    inner_centre = 0.0 if lane == "inner" else -3.5
    lines = [(inner_centre - 1.75 - 0.13, (235, 195, 40), False), (inner_centre - 1.75 + 0.13, (235, 195, 40), False),
             (inner_centre + 1.75, (235, 235, 230), True), (inner_centre + 5.25 - 0.28, (235, 235, 230), False)]
    z = be.z_of_row
    for lat, color, dashed in lines:
        u = (lat - car_offset_m - cfg.x_min_m) * cfg.px_per_m_x
        paint = ((z + 2.3) % 9.0 < 3.0) if dashed else np.ones_like(z, bool)
        for du in range(-3, 4):  # 0.14 m wide
            cols = np.full(h, int(round(u + du)))
            ok = (cols >= 0) & (cols < w) & paint
            canvas[np.arange(h)[ok], cols[ok]] = color
    img = cv2.warpPerspective(canvas, to_big @ be.bev_to_image, (CAM.width * scale, CAM.height * scale),
                              flags=cv2.INTER_LINEAR, borderValue=(120, 160, 210))
    return cv2.resize(img, (CAM.width, CAM.height), interpolation=cv2.INTER_AREA)


@pytest.mark.parametrize(("lane", "car_offset_m"), [("outer", 0.0), ("outer", 0.4), ("outer", -0.5), ("inner", 0.0),
                                                    ("inner", 0.35), ("inner", -0.4)])
def test_lane_centre_from_marking_conventions(lane: str, car_offset_m: float) -> None:
    """The painted lines are classified from the image (colour, solid / dashed) and the lane boundaries placed
    beyond them by the marking spec, so the offset from the lane centre is right in either lane; the painted
    lines' own fields keep their meaning (the middle of the paint)."""
    img = marked_road(car_offset_m, lane)
    det = LaneDetector(CAM)
    for _ in range(3):  # the line styles are smoothed over frames
        res = det.detect(img)
    assert res.detected and res.left is not None and res.right is not None
    if lane == "outer":
        assert (res.left.color, res.left.style) == ("white", "dashed")
        assert (res.right.color, res.right.style) == ("white", "solid")
        painted_centre = (-1.75 + 1.47) / 2  # the edge line is painted 0.28 m inside the lane
    else:
        assert res.left.color == "yellow"
        assert (res.right.color, res.right.style) == ("white", "dashed")
        painted_centre = 0.0  # the double yellow line straddles the boundary
    # A misread line costs 0.14 m (edge line taken as dashed) or 0.065 m (double yellow taken as one line).
    assert abs(res.centre_offset_m - car_offset_m) < 0.05
    assert abs(res.offset_m - (car_offset_m - painted_centre)) < 0.05  # the painted centre, as before
    assert abs(res.boundary_width_m - 3.5) < 0.1
    assert res.centre_coeffs is not None and abs(-np.polyval(res.centre_coeffs, -CAM.mount_forward_m) - car_offset_m) < 0.05


def test_a_pair_of_lines_that_does_not_straddle_the_car_is_not_our_lane() -> None:
    """Following the last frame's lines can keep a pair the car is not between (the lane beside ours, taken after
    a turn): told the lines of the lane on its left, the car finds its own lane's again, at once (the lines it
    finds are not smoothed towards the ones it was told)."""
    img = synthetic_road([(0, 0, -5.25), (0, 0, -1.75), (0, 0, 1.75)])
    det = LaneDetector(CAM)
    det._prev = (LaneLine(np.array([0.0, 0.0, -5.25]), (3.0, 30.0), 1.0, 100, "white"),
                 LaneLine(np.array([0.0, 0.0, -1.75]), (3.0, 30.0), 1.0, 100, "white"))
    res = det.detect(img)
    assert res.left is not None and res.right is not None
    assert abs(res.left.x_at(0.0) + 1.75) < 0.1 and abs(res.right.x_at(0.0) - 1.75) < 0.1


def test_lane_centre_from_one_line_with_the_car_turned() -> None:
    """With only the solid edge line seen and the car turned 20 degrees to the lane (a lane change), the lane
    centre is half a lane across the boundary measured across the lane, not along the car's axis (which would be
    0.1 m off here)."""
    from towndrive.agent.perception.lanes import LaneLine

    det = LaneDetector(CAM)
    z0 = -CAM.mount_forward_m
    b = math.tan(math.radians(20.0))
    for car_offset_m in (-0.4, 0.0, 0.3):
        across = 1.47 - car_offset_m  # the edge line's middle, measured across the lane from the vehicle centre
        c = across * math.sqrt(1 + b * b) - b * z0
        edge = LaneLine(np.array([0.0, b, c]), (3.0, 20.0), 1.0, 500, "white", "solid", 1.0)
        _, offset = det._lane_centre(None, edge)
        assert abs(offset - car_offset_m) < 0.01


def test_a_line_with_less_paint_than_a_dashed_ones_is_unknown_not_dashed() -> None:
    """A line cut short by a stop bar a few metres ahead shows a few rows of paint: its pattern is not told
    (``MarkingSpec.dashed_min_coverage``), where the rule "solid or else dashed" called it dashed (a kerb lane
    then read as having a lane beyond it). A third of the rows painted is still dashed."""
    from towndrive.agent.perception.lanes import LaneLine

    def style_with_paint(z_painted: tuple[float, float]) -> tuple[str, float]:
        det = LaneDetector(CAM)
        be, bcfg = det.birdseye, det.config.birdseye
        w, h = be.size
        binary = np.zeros((h, w), np.uint8)
        col = int(round((1.75 - bcfg.x_min_m) * bcfg.px_per_m_x))
        rows = (be.z_of_row >= z_painted[0]) & (be.z_of_row <= z_painted[1])
        binary[rows, col - 1:col + 2] = 255
        line = LaneLine(np.array([0.0, 0.0, 1.75]), (3.0, 18.0), 0.9, 300, "white")
        _, right = det._classify(None, line, binary)
        assert right is not None
        return right.style, right.coverage

    style, coverage = style_with_paint((5.0, 5.8))
    assert style == "unknown" and coverage < LaneDetector(CAM).config.markings.dashed_min_coverage
    assert style_with_paint((5.0, 8.0))[0] == "dashed" and style_with_paint((3.0, 18.0))[0] == "solid"
