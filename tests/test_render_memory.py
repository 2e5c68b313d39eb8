"""What a town's renderer built is freed with it (issue 26): pybullet's caches do not keep a town's meshes, the
mesh files are gone once the bodies exist, and loading meshes from files draws what vertex lists drew.

bench/bench_memory_soak.py measures the whole env over 30 towns; these tests check the renderer's part quickly.
The heap test reads glibc's count of bytes in use (``mallinfo2``), which, unlike resident memory, does not
depend on when freed pages go back to the OS."""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import math
import os
import sys

import numpy as np
import pytest

import towndrive.sim.render as render
from towndrive.sim.objects import LightState, SemanticClass
from towndrive.sim.town import generate_town
from towndrive.sim.world import WorldConfig


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
                 "keepcost")]


def _heap_in_use() -> int | None:
    """Bytes malloc has handed out and not had back (glibc 2.33+), or None where that cannot be read."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallinfo2 = libc.mallinfo2
    except (OSError, AttributeError):
        return None
    mallinfo2.restype = _MallInfo2
    return int(mallinfo2().uordblks)


def test_renderers_of_new_towns_leave_no_native_memory_behind():
    if _heap_in_use() is None:
        pytest.skip("needs glibc's mallinfo2")
    config = WorldConfig().town
    in_use = []
    for seed in range(2000, 2006):
        town = generate_town(config, seed)
        renderer = render.SceneRenderer(town, seed=seed)
        renderer.render((0.0, 0.0, 0.0))
        renderer.close()
        del renderer, town
        gc.collect()
        in_use.append(_heap_in_use())
    # Before the fix pybullet's cache of parsed OBJ files kept about 1 MB of every town's meshes (4 MB here).
    growth_mb = (in_use[-1] - in_use[1]) / 2**20
    assert growth_mb < 1.0, f"heap in use grew {growth_mb:.1f} MB over 4 towns' renderers: {in_use}"


def test_mesh_files_are_deleted_once_the_bodies_are_built(town):
    renderer = render.SceneRenderer(town)
    try:
        assert renderer._mesh_files == []
        assert not [name for name in os.listdir(render._mesh_dir()) if name.endswith(".obj")]
    finally:
        renderer.close()


def _frames(town, from_lists: bool, monkeypatch) -> list[render.CameraFrame]:
    """Frames facing six traffic lights (their lamp discs are meshes too) at noon and at night."""
    monkeypatch.setattr(render, "MESH_FROM_LISTS", from_lists)
    renderer = render.SceneRenderer(town)
    try:
        renderer.set_light_states([LightState.RED, LightState.GREEN, LightState.YELLOW] * len(town.approaches))
        frames = []
        for ap in town.approaches[:6]:
            x, y = ap.light_head
            h = ap.travel_heading
            for lighting in ("noon", "night"):
                frames.append(renderer.render((x - 14.0 * math.cos(h), y - 14.0 * math.sin(h), h), lighting=lighting))
        return frames
    finally:
        renderer.close()


def test_meshes_from_files_draw_what_vertex_lists_drew(town, monkeypatch):
    from_files, from_lists = _frames(town, False, monkeypatch), _frames(town, True, monkeypatch)
    assert all((f.segmentation[..., 0] == SemanticClass.TRAFFIC_LAMP).sum() > 50 for f in from_files)
    for a, b in zip(from_files, from_lists, strict=True):
        assert np.array_equal(a.rgb, b.rgb)
        assert np.array_equal(a.depth_m, b.depth_m)
        assert np.array_equal(a.segmentation, b.segmentation)
