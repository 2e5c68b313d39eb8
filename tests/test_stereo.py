"""Stereo depth: SGBM on a synthetic pair with a known disparity, depth from f B / d, the robust object
distance, KITTI's D1 metric and its background fill, and the simulator's ground-truth disparity."""

from __future__ import annotations

import numpy as np
import pytest

from towndrive.agent.perception.stereo import StereoDepth, fill_invalid
from towndrive.envs.perception_truth import d1_all
from towndrive.sim.render import CameraConfig

CAM = CameraConfig(stereo=True)


def textured_pair(disparity_px: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A random-texture plane seen by the left camera and shifted by a whole-pixel disparity in the right one."""
    rng = np.random.default_rng(seed)
    tex = rng.integers(0, 255, (CAM.height // 2, (CAM.width + disparity_px) // 2, 1), np.uint8)
    tex = np.repeat(np.repeat(tex, 2, 0), 2, 1)[:, :, [0, 0, 0]]
    left = np.ascontiguousarray(tex[:, :CAM.width])  # a texture column c is at x = c on the left ...
    right = np.ascontiguousarray(tex[:, disparity_px:disparity_px + CAM.width])  # ... and at x = c - d on the right
    return left, right


@pytest.mark.parametrize("d", [4, 12])
def test_sgbm_recovers_a_known_disparity(d: int) -> None:
    stereo = StereoDepth(CAM)
    left, right = textured_pair(d)
    disp = stereo.disparity(left, right)
    inner = disp[10:-10, stereo.config.num_disparities + 5:-10]
    valid = inner > 0
    assert valid.mean() > 0.9
    assert np.median(np.abs(inner[valid] - d)) < 0.25
    depth = stereo.depth(disp)
    expected = CAM.focal_px * CAM.stereo_baseline_m / d
    assert np.median(depth[10:-10, stereo.config.num_disparities + 5:-10][valid]) == pytest.approx(expected, rel=0.05)
    assert np.isinf(stereo.depth(np.array([[0.0, -1.0]]))).all()


def test_object_distance_ignores_background_in_the_box() -> None:
    stereo = StereoDepth(CAM)
    depth = np.full((CAM.height, CAM.width), 40.0, np.float32)
    depth[60:100, 100:160] = 12.0  # the object fills the box's middle; the box is larger than it
    depth[70:80, 120:130] = np.inf  # some unmatched pixels on it
    box = np.array([90.0, 50.0, 170.0, 110.0])
    assert stereo.object_distance(depth, box) == pytest.approx(12.0)
    assert np.isnan(stereo.object_distance(np.full_like(depth, np.inf), box))


def test_d1_and_background_fill() -> None:
    truth = np.full((4, 6), 10.0)
    est = truth.copy()
    est[0, 0] = 14.0  # off by 4 px and 40 %: wrong
    est[0, 1] = 12.5  # off by 2.5 px: right
    est[1, 0] = 0.0  # no match
    valid = np.ones_like(truth, bool)
    assert d1_all(est, truth, valid) == pytest.approx(2 / 24)
    filled = fill_invalid(np.array([[0.0, 8.0, 0.0, 3.0, 0.0]]))
    assert filled.tolist() == [[8.0, 8.0, 3.0, 3.0, 3.0]]  # the farther (smaller) neighbour wins


def test_ground_truth_disparity_matches_sgbm_on_the_simulator(town) -> None:
    """On a rendered pair, SGBM agrees with f B / Z from the renderer's depth on most road pixels
    (a check of the ground truth's geometry: baseline direction, focal length, left camera)."""
    from towndrive.sim.render import SceneRenderer
    from towndrive.sim.world import World, WorldConfig

    world = World(town, WorldConfig(npc_count=0, pedestrian_count=0), seed=0)
    renderer = SceneRenderer(town, seed=town.seed)
    from towndrive.envs.perception_truth import stereo_truth

    truth = stereo_truth(renderer, world, CAM, "noon")
    renderer.close()
    stereo = StereoDepth(CAM)
    disp = stereo.disparity(truth.left, truth.right)
    valid = (truth.disparity_px > 1.0) & (disp > 0)
    assert valid.sum() > 2000
    err = np.abs(disp - truth.disparity_px)[valid]
    assert np.median(err) < 0.5
    assert d1_all(fill_invalid(disp), truth.disparity_px, truth.disparity_px > 0) < 0.05


def object_pair(object_px: float, background_px: float, seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A faint random texture on a background plane at ``background_px`` of disparity and, in front of it, a
    textured box-shaped object (rows 60-100, columns 130-190) at ``object_px``; sub-pixel shifts by bicubic
    interpolation. Returns left, right and the object's box with a margin of background round it."""
    import cv2

    rng = np.random.default_rng(seed)
    h, w = CAM.height, CAM.width

    def texture(sigma: float, low: float, high: float) -> np.ndarray:
        t = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + 64)).astype(np.float32), (0, 0), sigma)
        return cv2.normalize(t, None, low, high, cv2.NORM_MINMAX)

    # The background is faint and smooth, as the road and sky behind the simulator's objects are (a strongly
    # textured background beside the object pulls the refined disparity towards its own by about 0.15 px).
    bg, obj = texture(4.0, 70, 130), texture(1.2, 20, 235)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)

    def shifted(tex: np.ndarray, d: float) -> np.ndarray:  # what the right camera sees: x_right = x_left - d
        return cv2.remap(tex, xs + np.float32(d) + 32, ys, cv2.INTER_CUBIC)

    left, right = shifted(bg, 0.0), shifted(bg, background_px)
    inside = (ys >= 60) & (ys < 100)
    left = np.where(inside & (xs >= 130) & (xs < 190), shifted(obj, 0.0), left)
    right = np.where(inside & (xs >= 130 - object_px) & (xs < 190 - object_px), shifted(obj, object_px), right)
    to_rgb = lambda g: np.repeat(np.clip(g, 0, 255).astype(np.uint8)[..., None], 3, axis=2)  # noqa: E731
    return to_rgb(left), to_rgb(right), np.array([122.0, 54.0, 198.0, 106.0])


@pytest.mark.parametrize("object_px", [1.3, 2.6, 0.8])
def test_refined_object_distance_is_sub_pixel(object_px: float) -> None:
    """An object between whole-pixel disparities, in a box that also holds background: the nearest disparity
    mode refined by matching lands within 4% of its distance (7-24 m with the 0.12 m rig), where SGBM's own
    sub-pixel disparity, pulled to whole pixels, is up to 22% off."""
    stereo = StereoDepth(CAM)
    left, right, box = object_pair(object_px, 0.3)
    disp = stereo.disparity(left, right)
    truth = stereo.focal_baseline / object_px
    assert stereo.object_distance_refined(left, right, disp, box) == pytest.approx(truth, rel=0.04)
    assert np.isnan(stereo.object_distances_refined(left, right, np.zeros_like(disp), box[None])[0])  # nothing matched
