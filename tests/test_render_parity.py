"""The renderer's shortcuts give what the plain computations give: boxes gathered while shading equal
``object_boxes``' pass over the id image, the compiled view-wedge test equals the NumPy formula, and the
one-point ground lookup equals the array one."""

from __future__ import annotations

import math

import numpy as np

import towndrive.sim.render as render
import towndrive.sim.render_kernels as kernels
from towndrive.envs.drive_env import DriveConfig, DriveEnv
from towndrive.sim.objects import SemanticClass, snapshot_of
from towndrive.sim.render import CameraConfig
from towndrive.sim.render_kernels import object_boxes


def numpy_in_view(objects, view) -> list[bool]:
    """``_in_view`` as it was, in NumPy."""
    x, y, heading, hfov_deg, range_m = view
    pos = np.array([[o.x, o.y] for o in objects]) - np.array([x, y])
    radius = np.array([0.5 * math.hypot(o.length_m, o.width_m) for o in objects]) + 1.0
    dist = np.hypot(pos[:, 0], pos[:, 1])
    ang = np.abs((np.arctan2(pos[:, 1], pos[:, 0]) - heading + np.pi) % (2 * np.pi) - np.pi)
    reach = math.radians(hfov_deg) / 2 + np.arcsin(np.clip(radius / np.maximum(dist, 1e-6), 0.0, 1.0)) + math.radians(5)
    return ((dist <= radius + 3.0) | ((dist <= range_m + radius) & (ang <= reach))).tolist()


def test_boxes_gathered_while_shading_equal_object_boxes(monkeypatch):
    env = DriveEnv(DriveConfig(camera=CameraConfig(width=200, height=66)))
    env.reset(seed=4, options={"traffic_density": 2.0})
    fallbacks = 0
    for capacity in (render.BOX_CAPACITY, 4):  # 4: most frames have more ids, and fall back
        monkeypatch.setattr(render, "BOX_CAPACITY", capacity)
        for _ in range(40):
            env.step([0.0, 0.4])
            frame = env.frame
            assert frame is not None
            expected = object_boxes(frame.segmentation[..., 1])
            if frame.object_boxes is None:
                fallbacks += 1
                continue
            for got, want in zip(frame.object_boxes, expected, strict=True):
                assert got.dtype == want.dtype and np.array_equal(got, want)
    assert fallbacks > 0
    env.close()


def test_view_wedge_equals_the_numpy_formula(town):
    rng = np.random.default_rng(0)
    xmin, ymin, xmax, ymax = town.extent
    for _ in range(300):
        objects = [snapshot_of(k, SemanticClass.CAR, float(rng.uniform(xmin, xmax)), float(rng.uniform(ymin, ymax)),
                               0.0, float(rng.choice([4.5, 8.0, 0.35])), float(rng.choice([1.9, 2.5, 0.55])), 1.5,
                               (1.0, 0.0, 0.0)) for k in range(40)]
        view = (float(rng.uniform(xmin, xmax)), float(rng.uniform(ymin, ymax)), float(rng.uniform(-4.0, 4.0)),
                float(rng.choice([60.0, 90.0])), 250.0)
        assert render._in_view(objects, view) == numpy_in_view(objects, view)


def test_one_point_ground_lookup_equals_the_array_lookup(town):
    gm = render._ground_map(town)
    rng = np.random.default_rng(1)
    xmin, ymin, xmax, ymax = town.extent
    xs, ys = rng.uniform(xmin - 20, xmax + 20, 5000), rng.uniform(ymin - 20, ymax + 20, 5000)
    assert gm.lookup(xs, ys).tolist() == [gm.lookup_point(x, y) for x, y in zip(xs.tolist(), ys.tolist(), strict=True)]


def test_sorted_boxes_equal_the_numpy_sort():
    rng = np.random.default_rng(2)
    for n in list(range(0, 65)) * 5:
        seen = np.empty(64, np.int64)
        seen[:n] = rng.permutation(np.arange(1, 20000))[:n]
        box = rng.integers(0, 640, (64, 5))
        order = np.argsort(seen[:n])
        b = box[order]
        want = (seen[order], b[:, 0], b[:, 1], b[:, 2], b[:, 3], b[:, 4])
        got = kernels.sorted_boxes(seen, box, n)
        assert len(got) == 6
        for g, w in zip(got, want, strict=True):
            assert g.dtype == w.dtype and g.tolist() == w.tolist()
