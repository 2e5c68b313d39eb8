"""Stereo depth: SGBM on a synthetic pair with a known disparity, depth from f B / d, the robust object
distance, KITTI's D1 metric and its background fill, and the simulator's ground-truth disparity."""

from __future__ import annotations

import numpy as np
import pytest

from agent.stereo import StereoDepth, fill_invalid
from envs.perception_truth import d1_all
from sim.render import CameraConfig

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
    from sim.render import SceneRenderer
    from sim.world import World, WorldConfig

    world = World(town, WorldConfig(npc_count=0, pedestrian_count=0), seed=0)
    renderer = SceneRenderer(town, seed=town.seed)
    from envs.perception_truth import stereo_truth

    truth = stereo_truth(renderer, world, CAM, "noon")
    renderer.close()
    stereo = StereoDepth(CAM)
    disp = stereo.disparity(truth.left, truth.right)
    valid = (truth.disparity_px > 1.0) & (disp > 0)
    assert valid.sum() > 2000
    err = np.abs(disp - truth.disparity_px)[valid]
    assert np.median(err) < 0.5
    assert d1_all(fill_invalid(disp), truth.disparity_px, truth.disparity_px > 0) < 0.05
