"""Frames drawn by two processes (``render_processes=2``: a helper process draws a share of the bodies, the main one
folds its buffers in) are the frames of one process, bit for bit: RGB, depth and segmentation, over a drive with
traffic, at night (bloom, headlights, lit windows) and with stereo; and the helper goes away at ``close``."""

from __future__ import annotations

import numpy as np
import pytest

import towndrive.sim.render_kernels as kernels
from towndrive.envs.drive_env import DriveConfig, DriveEnv
from towndrive.sim.render import CameraConfig


def _drive(config: DriveConfig, steps: int, seed: int = 3) -> list[dict]:
    env = DriveEnv(config)
    env.reset(seed=seed, options={"traffic_density": 2.0})
    frames = []
    for k in range(steps):
        obs, _, term, trunc, _ = env.step([0.05 * np.sin(k / 7), 0.5])
        frames.append({key: obs[key].copy() for key in ("image", "depth", "segmentation", "stereo")})
        if term or trunc:
            env.reset(seed=seed + k + 1)
    partners = list(env.renderer._partners) if env.renderer is not None else []
    env.close()
    for partner in partners:
        assert partner.proc.poll() is not None, "the helper process outlived close()"
    return frames


@pytest.mark.parametrize("weather", ["noon", "night"])
def test_two_processes_draw_the_frames_of_one(weather):
    config = DriveConfig(camera=CameraConfig(width=160, height=80), weather=weather, observe_depth=True,
                         observe_segmentation=True, observe_stereo=True)
    one = _drive(config, 40)
    two = _drive(DriveConfig(**{**config.__dict__, "render_processes": 2}), 40)
    for k, (a, b) in enumerate(zip(one, two, strict=True)):
        for key in a:
            assert np.array_equal(a[key], b[key]), f"step {k}: {key} differs"


def test_merge_takes_the_nearer_fragment_then_the_later_body():
    h, w = 1, 5
    rgba = np.zeros((h, w, 4), np.uint8)
    buf = np.array([[0.5, 0.5, 0.5, 0.5, 1.0]], np.float32)
    seg = np.array([[7, 7, 7, -1, -1]], np.int32)
    rgba_b = np.full((h, w, 4), 9, np.uint8)
    buf_b = np.array([[0.4, 0.6, 0.5, 0.9, 1.0]], np.float32)
    seg_b = np.array([[8, 8, 6 + (2 << 24), 8, -1]], np.int32)
    # nearer: taken; farther: kept; equal depth, earlier body (6 < 7) despite its link bits: kept; only b: taken
    assert kernels.merge_share(rgba, buf, seg, rgba_b, buf_b, seg_b) == 2
    assert seg.tolist() == [[8, 7, 7, 8, -1]]
    assert buf.tolist() == [[np.float32(0.4), 0.5, 0.5, np.float32(0.9), 1.0]]
    seg[0, 2], buf_b[0, 2], seg_b[0, 2] = 7, 0.5, 9  # equal depth, later body: taken
    assert kernels.merge_share(rgba, buf, seg, rgba_b, buf_b, seg_b) >= 1 and seg[0, 2] == 9
