"""Camera renderer: pybullet TinyRenderer (CPU, headless) plus a numpy post-process.

The static town is a few merged meshes (see ``sim.scene_meshes``); each traffic light and each
moving object is one multibody whose links carry lamps, cabins and wheels. ``render`` returns RGB,
metric z-depth, per-pixel (semantic class, object id) and the intrinsics, all from one
``getCameraImage`` call. Sky, colour grade, fog and night headlights are numpy post-processing,
since TinyRenderer has no sky, no emissive materials and only one directional light.
"""

from __future__ import annotations

import contextlib
import math
import os
import weakref
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import cv2
import numpy as np

from towndrive.sim import render_kernels as kernels
from towndrive.sim.checks import check_number
from towndrive.sim.objects import LIGHT_ID_BASE, MAX_SIGNS, SIGN_ID_BASE, LightState, ObjectSnapshot, SemanticClass
from towndrive.sim.scene_meshes import (
    HOUSING_HALF,
    LAMP_SPACING_M,
    SURFACE_CLASS,
    SURFACE_RAISED,
    SURFACE_RGB,
    Z_GROUND,
    Z_SLAB,
    GroundMap,
    Mesh,
    build_ground_map,
    build_static_groups,
    light_lamp_disc,
    to_world,
    world_point,
    yaw_of,
)
from towndrive.sim.sign_meshes import SIGN_CLASS, sign_parts
from towndrive.sim.spec import IMAGE_PX, WEATHERS, CameraConfig, check_image_size  # noqa: F401 (re-exported)
from towndrive.sim.town import Town


def _import_pybullet() -> Any:
    """pybullet, imported without the "pybullet build time" line its C module prints (on stderr): every command
    would print it, ``--help`` included."""
    import ctypes
    import sys

    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            os.dup2(null.fileno(), 2)
            import pybullet

            with contextlib.suppress(OSError, AttributeError):
                ctypes.CDLL(None).fflush(None)  # what the C library still holds goes to /dev/null too
    finally:
        for fd, copy in zip((1, 2), saved, strict=True):
            os.dup2(copy, fd)
            os.close(copy)
    return pybullet


p = _import_pybullet()

MAX_LINKS = 8  # links per body the segmentation lookup tables can tell apart
BOX_CAPACITY = 64  # object ids a frame's boxes are gathered for while shading (more: object_boxes afterwards)
HIDDEN_Z = -500.0  # where pooled, unused object bodies wait (below the ground, beyond the far plane)
CALIBRATION_Z = -3000.0  # a grass patch far below the town, rendered once per preset to learn the grass colour
MESH_FROM_LISTS = False  # True: the old way (pybullet keeps the vertex lists for ever); for comparisons only


# --------------------------------------------------------------------------- camera
@dataclass(frozen=True)
class CameraFrame:
    """One camera image with its ground truth."""

    rgb: np.ndarray  # HxWx3 uint8
    depth_m: np.ndarray  # HxW float32, z-depth along the optical axis (far_m where there is only sky)
    segmentation: np.ndarray  # HxWx2 int32: [..., 0] SemanticClass, [..., 1] object id (0 = static scenery)
    intrinsics: np.ndarray  # 3x3 K
    # kernels.object_boxes(segmentation[..., 1]), found while shading (None: ask object_boxes)
    object_boxes: tuple[np.ndarray, ...] | None = None


# --------------------------------------------------------------------------- lighting
@dataclass(frozen=True)
class LightingPreset:
    """TinyRenderer's sun and shading coefficients plus the numpy post-process of one time of day."""

    light_direction: tuple[float, float, float]  # towards the sun, world frame (z up)
    light_color: tuple[float, float, float]
    ambient: float
    diffuse: float
    specular: float
    sky_top: tuple[int, int, int]  # RGB at the top row of the image
    sky_horizon: tuple[int, int, int]  # RGB at the horizon
    gain: tuple[float, float, float] = (1.0, 1.0, 1.0)  # per-channel colour grade
    lift: tuple[float, float, float] = (0.0, 0.0, 0.0)  # added after the gain, 0..255 units
    fog_distance_m: float = 0.0  # 0 = no fog; else colour = mix(colour, sky_horizon, 1 - exp(-d / fog))
    headlights: bool = False  # night: the ego's headlight cone lights the lower middle of the image
    headlight_ambient: float = 1.0  # scene brightness outside the cone (multiplies the graded colour)
    headlight_gain: float = 0.0  # extra brightness at the cone's centre, before distance falloff
    emissive_windows: bool = False  # lit window bands glow
    glow: float = 0.0  # strength of the bloom around emissive pixels


LIGHTING_PRESETS: dict[str, LightingPreset] = {
    "noon": LightingPreset(light_direction=(0.35, 0.25, 0.9), light_color=(1.0, 0.98, 0.92), ambient=0.55,
                           diffuse=0.55, specular=0.05, sky_top=(70, 130, 215), sky_horizon=(175, 205, 235),
                           fog_distance_m=600.0),
    "dusk": LightingPreset(light_direction=(-0.9, 0.3, 0.18), light_color=(1.0, 0.7, 0.45), ambient=0.42,
                           diffuse=0.6, specular=0.05, sky_top=(55, 60, 120), sky_horizon=(245, 150, 90),
                           gain=(1.0, 0.82, 0.72), lift=(8.0, 2.0, 10.0), fog_distance_m=350.0, glow=0.6),
    "overcast": LightingPreset(light_direction=(0.1, 0.2, 1.0), light_color=(0.9, 0.92, 0.95), ambient=0.72,
                               diffuse=0.28, specular=0.0, sky_top=(150, 155, 162), sky_horizon=(196, 198, 202),
                               gain=(0.95, 0.97, 1.0), fog_distance_m=180.0),
    "night": LightingPreset(light_direction=(0.3, 0.5, 0.8), light_color=(0.6, 0.7, 1.0), ambient=0.6,
                            diffuse=0.25, specular=0.0, sky_top=(3, 5, 14), sky_horizon=(22, 26, 44),
                            gain=(0.55, 0.62, 0.85), fog_distance_m=0.0, headlights=True, headlight_ambient=0.22,
                            headlight_gain=2.6, emissive_windows=True, glow=1.0),
}
assert tuple(sorted(LIGHTING_PRESETS)) == WEATHERS, "sim.spec.WEATHERS names the presets"


# --------------------------------------------------------------------------- lamps and vehicles
LAMP_ON_RGB = {LightState.RED: (1.0, 0.12, 0.08), LightState.YELLOW: (1.0, 0.72, 0.05),
               LightState.GREEN: (0.15, 1.0, 0.35)}
LAMP_OFF_RGB = {LightState.RED: (0.22, 0.06, 0.05), LightState.YELLOW: (0.22, 0.17, 0.04),
                LightState.GREEN: (0.05, 0.18, 0.08)}
LAMP_ORDER = (LightState.RED, LightState.YELLOW, LightState.GREEN)  # links 0, 1, 2: top to bottom
HOUSING_RGB = (0.10, 0.10, 0.11)
GLASS_RGB = (0.10, 0.13, 0.17)
TYRE_RGB = (0.06, 0.06, 0.06)
HEADLAMP_RGB = (1.0, 0.97, 0.85)
TAILLAMP_RGB = (0.85, 0.05, 0.04)
PANTS_RGB = (0.16, 0.17, 0.22)
SKIN_RGB = (0.80, 0.62, 0.50)


def _sun(preset: LightingPreset) -> np.ndarray:
    d = np.asarray(preset.light_direction, float)
    return d / np.linalg.norm(d)


@dataclass
class _Body:
    """A pooled moving-object body and what it currently shows."""

    uid: int
    kind: SemanticClass
    dims: tuple[float, float, float]
    color: tuple[float, float, float] = (-1.0, -1.0, -1.0)
    body_links: tuple[int, ...] = (-1,)  # links painted in the object's colour
    lamp_links: dict[int, tuple[float, float, float]] = field(default_factory=dict)  # link -> emissive colour
    link_rgb: dict[int, tuple[float, float, float]] = field(default_factory=dict)  # each link's own paint
    shown: bool = True  # False: alpha 0 on every link, so TinyRenderer skips the body


@dataclass(frozen=True)
class _FrameSetup:
    """What a frame needs that depends only on the camera and the lighting preset (see ``SceneRenderer._setup``)."""

    camera_args: dict  # getCameraImage's keyword arguments other than the view matrix
    palette: np.ndarray  # ground surfaces' shaded RGB
    grade: np.ndarray  # float32 constants of the shading kernel
    flags: np.ndarray
    cone: np.ndarray  # headlight footprint (1x1 zeros without headlights)
    sky: np.ndarray  # sky gradient image
    geo_tail: tuple[float, ...]  # the pose-independent end of the kernel's ``geo`` vector
    glow_sigma: float  # bloom blur (0: no bloom)
    intrinsics: np.ndarray


SIGN_NIGHT_GLOW = 0.45  # at night a plate's face shows this share of its colour (the headlights' retroreflection)
SIGN_RANGE_M = 150.0  # signs farther than this are not drawn (a 0.75 m plate is about a pixel wide there at 320 px)
COST_PER_TRIANGLE = 30.0  # TinyRenderer's work for one triangle's vertices, in pixels of a bounding box (balancing)
TILE_M = 120.0  # static meshes are split into tiles of this size for view culling (few bodies: resets stay cheap)


@dataclass
class _Tile:
    """One static body: a mesh group's triangles within one tile, and its map-frame footprint."""

    uid: int
    rgba: tuple[float, ...]
    lo: np.ndarray
    hi: np.ndarray


# --------------------------------------------------------------------------- renderer
class SceneRenderer:
    """Renders a town and its moving objects with its own pybullet DIRECT client.

    ``processes`` > 1 shares each frame's TinyRenderer work with ``processes - 1`` helper processes
    (``sim.render_share``), each holding the same scene: every process draws the bodies whose unique id modulo
    ``processes`` is its rank, and the main one folds the others' buffers into its own (nearer fragment first, then
    the later-drawn body), so the frame is the one a single call gives, bit for bit, but for one case: two bodies of
    different shares whose fragments at a pixel are so close in depth that TinyRenderer's float32 depth buffer holds
    the same value for both, where the earlier-drawn body was nearer (none in the runs of bench/README.md). It pays
    only with a free core per helper: a helper inherits the caller's CPU affinity, and each helper costs a second
    copy of the scene (one more process, its memory, about a second to start)."""

    def __init__(self, town: Town, seed: int = 0, processes: int = 1, *,
                 _share: tuple[int, int] | None = None) -> None:
        processes = check_number("render processes", processes, 1, 16, integer=True)
        self.town = town
        # This process draws the bodies whose unique id is rank modulo count (see render_share); (0, 1): all.
        self._rank, self._count = _share if _share is not None else (0, processes)
        self._partners: list = []  # render_share.SharePartner of each helper process (main renderer only)
        if _share is None and processes > 1:
            from towndrive.sim.render_share import SharePartner, stop_partners

            # Started first: each helper builds its copy of the scene while this process builds its own.
            self._partners = [SharePartner(town, seed, rank, processes) for rank in range(1, processes)]
            self._stop_partners = weakref.finalize(self, stop_partners, self._partners)
        self.client = p.connect(p.DIRECT)
        self._cid = {"physicsClientId": self.client}
        # Disconnects when close() is called, when the renderer is collected, or at interpreter exit (atexit,
        # before modules are torn down): a __del__ running during teardown found pybullet half-unloaded and
        # printed an "Exception ignored" traceback when an env was not closed.
        self._finalizer = weakref.finalize(self, _disconnect, self.client)
        n = 4096
        # Per (uid, link) lookup tables, index = uid * (MAX_LINKS + 1) + (link + 1); the last row is the sky.
        self._class_lut = np.zeros(n * (MAX_LINKS + 1) + 1, np.int32)
        self._id_lut = np.zeros_like(self._class_lut)
        self._emissive = np.zeros((len(self._class_lut), 3), np.float32)  # 0..1 RGB, only where _emit_mask
        self._emit_mask = np.zeros(len(self._class_lut), bool)
        self._night_emit = np.zeros(len(self._class_lut), bool)  # emissive only when the preset says so
        self.triangle_count = 0
        self.ground_map = _ground_map(town)
        self._light_bodies: list[int] = []
        self._light_states: list[LightState | None] = []
        self._light_shown: list[bool] = []
        self._light_input: tuple = ()  # the states last passed to set_light_states
        self._last_cull: tuple[np.ndarray, float, tuple[float, float]] | None = None
        self._mesh_files: list[str] = []  # written by _mesh_shape; pybullet reads them when a body is created
        try:
            self._build_static(seed)
            self._build_calibration_patch()
            self._build_lights()
            self._build_signs()
        finally:
            _forget_mesh_files(self._mesh_files, self.client)
        self._light_xy = np.array([ap.light_head for ap in town.approaches]).reshape(-1, 2)
        self._pool: dict[tuple[SemanticClass, tuple[float, float, float]], list[_Body]] = {}
        self._active: dict[int, _Body] = {}
        self._last_pose: dict[int, tuple] = {}  # skip resets of still objects
        self._look: dict[int, tuple] = {}  # kind, size and colour each object's body was fitted to
        self._shapes: dict[tuple, int] = {}
        self._new_bodies = False  # bodies were added since the broadphase was last settled
        self._settle_broadphase()
        if self._count > 1:
            self._hide_others_static()

    # ----------------------------------------------------------------- shares (processes > 1)
    def _mine(self, uid: int) -> bool:
        """Whether this process draws body ``uid`` (always, with one process), for all bodies but the static tiles
        (``_tile_owner``). The calibration patch is the main process's: only it learns the ground palette."""
        return self._count == 1 or (self._rank == 0 if uid == self._calibration_uid else uid % self._count == self._rank)

    def _hide_others_static(self) -> None:
        """Alpha 0 on the static tiles, lights, signs and calibration patch another process draws."""
        self._draw_tiles(self._tile_shown, self._tile_owner)
        tiles = {t.uid for t in self._tiles}
        for uid in range(p.getNumBodies(**self._cid)):
            if uid not in tiles and not self._mine(uid):
                for entry in p.getVisualShapeData(uid, **self._cid):
                    p.changeVisualShape(uid, int(entry[1]), rgbaColor=[*entry[7][:3], 0.0], **self._cid)

    # ----------------------------------------------------------------- lookup tables
    def _key(self, uid: int, link: int) -> int:
        return uid * (MAX_LINKS + 1) + link + 1

    def _ensure_lut(self, uid: int) -> None:
        need = (uid + 1) * (MAX_LINKS + 1) + 1
        if need <= len(self._class_lut):
            return
        size = max(need, 2 * len(self._class_lut))
        for name in ("_class_lut", "_id_lut", "_emit_mask", "_night_emit"):
            old = getattr(self, name)
            new = np.zeros(size, old.dtype)
            new[:len(old) - 1] = old[:-1]  # the sky row moves to the new end (it is all zeros)
            setattr(self, name, new)
        new_e = np.zeros((size, 3), np.float32)
        new_e[:len(self._emissive) - 1] = self._emissive[:-1]
        self._emissive = new_e

    def _label(self, uid: int, links: Sequence[int], semantic: SemanticClass, object_id: int) -> None:
        self._ensure_lut(uid)
        for link in links:
            k = self._key(uid, link)
            self._class_lut[k] = int(semantic)
            self._id_lut[k] = object_id

    def _set_emissive(self, uid: int, link: int, rgb: tuple[float, float, float] | None, night_only: bool) -> None:
        k = self._key(uid, link)
        self._emit_mask[k] = rgb is not None
        self._night_emit[k] = night_only and rgb is not None
        if rgb is not None:
            self._emissive[k] = rgb

    # ----------------------------------------------------------------- static scene
    def _build_static(self, seed: int) -> None:
        """One body per (mesh group, spatial tile), so that tiles out of view can be skipped."""
        self._tiles: list[_Tile] = []
        tris = []  # each tile's triangles, world frame (for the cost estimate that balances processes' shares)
        for g in build_static_groups(self.town, seed):
            v, _, nrm = g.mesh.arrays()
            verts = np.asarray(v, float).reshape(-1, 3, 3)
            norms = np.asarray(nrm, float).reshape(-1, 3, 3)
            centre = verts.mean(axis=1)
            keys = np.floor(centre[:, :2] / TILE_M).astype(np.int64)
            for key in np.unique(keys, axis=0):
                sel = np.all(keys == key, axis=1)
                tv, tn = verts[sel].reshape(-1, 3), norms[sel].reshape(-1, 3)
                vs = self._mesh_shape(tv, tn, g.rgba)
                uid = p.createMultiBody(baseMass=0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=vs, **self._cid)
                self._no_collisions(uid)
                self._label(uid, [-1], g.semantic, 0)
                if g.emissive_at_night is not None:
                    self._set_emissive(uid, -1, g.emissive_at_night, night_only=True)
                # Footprint in the map frame (world y flipped back).
                lo, hi = tv[:, :2].min(axis=0), tv[:, :2].max(axis=0)
                self._tiles.append(_Tile(uid, tuple(g.rgba), np.array([lo[0], -hi[1]]), np.array([hi[0], -lo[1]])))
                tris.append(verts[sel])
            self.triangle_count += g.mesh.triangle_count
        self._tile_lo = np.array([t.lo for t in self._tiles])
        self._tile_hi = np.array([t.hi for t in self._tiles])
        self._tile_shown = np.ones(len(self._tiles), bool)  # in the view wedge
        self._tile_drawn = np.ones(len(self._tiles), bool)  # alpha 1: in view and this process's
        self._tile_owner = np.array([t.uid % self._count for t in self._tiles], np.int64)  # the process that draws it
        self._tile_tris = np.concatenate(tris) if tris else np.zeros((0, 3, 3))
        self._tile_first = np.cumsum([0] + [len(t) for t in tris]).astype(np.int64)

    def _mesh_shape(self, vertices: np.ndarray, normals: np.ndarray, rgba: Sequence[float],
                    specular: Sequence[float] | None = (0.0, 0.0, 0.0)) -> int:
        """A visual shape for a triangle soup (3 vertices per triangle), loaded from a Wavefront OBJ file.

        Why a file: pybullet never frees the vertex data of a mesh passed as ``vertices=`` lists, not at
        ``removeBody``, ``resetSimulation`` or ``disconnect`` (about 12 MB per town, which a long run over many
        towns kept), and it keeps a reference to every Python float of those lists. A mesh it loads from a file
        is freed with the client. pybullet reads the file when a body uses the shape, not here, so the file stays
        until the renderer's bodies are built (``_forget_mesh_files``, which also empties pybullet's own cache of
        parsed files). The numbers are written as the shortest text that reads back to the same float64
        (``repr``), so the values (and the pixels) are those the lists gave. ``specular`` None: pybullet's
        default specular colour."""
        paint = {"rgbaColor": list(rgba), **({} if specular is None else {"specularColor": list(specular)})}
        if MESH_FROM_LISTS:
            return p.createVisualShape(p.GEOM_MESH, vertices=vertices.tolist(), indices=list(range(len(vertices))),
                                       normals=normals.tolist(), **paint, **self._cid)
        global _MESH_FILES
        _MESH_FILES += 1
        name = os.path.join(_mesh_dir(), f"mesh_{_MESH_FILES}.obj")
        n = len(vertices)
        k = np.arange(1, n + 1).reshape(-1, 3)
        text = "".join(("".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in vertices.tolist()),
                        "".join(f"vn {x!r} {y!r} {z!r}\n" for x, y, z in normals.tolist()),
                        "".join(f"f {a}//{a} {b}//{b} {c}//{c}\n" for a, b, c in k.tolist())))
        with open(name, "x") as f:
            self._mesh_files.append(name)
            f.write(text)
        return p.createVisualShape(p.GEOM_MESH, fileName=name, **paint, **self._cid)

    def _cull(self, eye_xy: np.ndarray, heading: float, camera: CameraConfig) -> None:
        """Hide static tiles outside the camera's horizontal view wedge (alpha 0: TinyRenderer skips them).

        A tile is kept when the camera is inside its footprint, or when the angular span of its
        footprint's corners overlaps the field of view and its nearest corner is within the far plane.
        """
        lo, hi = self._tile_lo, self._tile_hi
        corners = np.stack([lo, np.stack([hi[:, 0], lo[:, 1]], 1), hi, np.stack([lo[:, 0], hi[:, 1]], 1)], axis=1)
        rel = corners - eye_xy
        ang = np.arctan2(rel[..., 1], rel[..., 0]) - heading
        ang = (ang + np.pi) % (2 * np.pi) - np.pi
        half = math.radians(camera.hfov_deg) / 2 + math.radians(6.0)
        # Corners straddling the back (+-pi) span the wedge's complement only if they wrap; a tile that
        # wraps round the camera contains it or is beside it, so keep it when the span exceeds pi.
        span_lo, span_hi = ang.min(axis=1), ang.max(axis=1)
        wraps = (span_hi - span_lo) > np.pi
        overlap = (span_hi >= -half) & (span_lo <= half)
        inside = np.all((eye_xy >= lo - 1.0) & (eye_xy <= hi + 1.0), axis=1)
        near = np.min(np.hypot(rel[..., 0], rel[..., 1]), axis=1) <= camera.far_m
        show = inside | (near & (overlap | wraps))
        self._draw_tiles(show, self._tile_owner)
        self._tile_shown = show

    def _draw_tiles(self, shown: np.ndarray, owner: np.ndarray) -> None:
        """Alpha 1 on the tiles in view that this process draws, 0 on the others (touching only those that change)."""
        want = shown & (owner == self._rank)
        for k in np.nonzero(want != self._tile_drawn)[0]:
            t = self._tiles[k]
            p.changeVisualShape(t.uid, -1, rgbaColor=[*t.rgba[:3], 1.0 if want[k] else 0.0], **self._cid)
        self._tile_drawn = want
        self._tile_owner = owner

    def _build_calibration_patch(self) -> None:
        """A grey quad out of every view: its lit colour tells how TinyRenderer shades flat ground."""
        mesh = Mesh()
        mesh.polygon_top(np.array([[-5.0, -5.0], [5.0, -5.0], [5.0, 5.0], [-5.0, 5.0]]), CALIBRATION_Z)
        v, _, nrm = mesh.arrays()
        vs = self._mesh_shape(np.array(v), np.array(nrm), (0.5, 0.5, 0.5, 1.0))
        self._calibration_uid = p.createMultiBody(baseMass=0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=vs,
                                                  **self._cid)
        self._no_collisions(self._calibration_uid)
        self._ground_palette: dict[str, np.ndarray] = {}
        self._setups: dict[tuple[str, CameraConfig], _FrameSetup] = {}
        self._last_setup: tuple[str, CameraConfig, _FrameSetup] | None = None  # the pair asked for last

    def _surface_palette(self, lighting: str, preset: LightingPreset) -> np.ndarray:
        """RGB (float, 0..255) of each ``Surface`` as TinyRenderer would shade it flat under a preset.

        Learned once per preset from the calibration patch, so ground and meshes match exactly.
        """
        if lighting not in self._ground_palette:
            eye = [0.0, 0.0, CALIBRATION_Z + 10.0]
            view = p.computeViewMatrix(eye, [0.0, 0.0, CALIBRATION_Z], [1.0, 0.0, 0.0], **self._cid)
            proj = p.computeProjectionMatrixFOV(30.0, 1.0, 1.0, 50.0, **self._cid)
            _, _, rgba, _, _ = p.getCameraImage(
                4, 4, viewMatrix=view, projectionMatrix=proj, renderer=p.ER_TINY_RENDERER,
                lightDirection=list(_sun(preset)), lightColor=list(preset.light_color),
                lightAmbientCoeff=preset.ambient, lightDiffuseCoeff=preset.diffuse,
                lightSpecularCoeff=preset.specular, shadow=0, **self._cid)
            factor = np.asarray(rgba, np.float32).reshape(4, 4, 4)[2, 2, :3] / 127.0
            self._ground_palette[lighting] = np.clip(SURFACE_RGB * 255.0 * factor, 0, 255).astype(np.float32)
        return self._ground_palette[lighting]

    def _build_lights(self) -> None:
        """One multibody per approach: housing base, lamp links 0-2 (red, yellow, green) facing the traffic."""
        hx, hy, hz = HOUSING_HALF
        housing = p.createVisualShape(p.GEOM_BOX, halfExtents=[hx, hy, hz], rgbaColor=[*HOUSING_RGB, 1.0],
                                      specularColor=[0.0, 0.0, 0.0], **self._cid)
        v, _, nrm = light_lamp_disc()
        lamps = [self._mesh_shape(np.array(v), np.array(nrm), (*LAMP_OFF_RGB[s], 1.0), specular=None) for s in LAMP_ORDER]
        for ap in self.town.approaches:
            pos = to_world(ap.light_head[0], ap.light_head[1], ap.head_height_m)
            # Local +x must look at the oncoming traffic, i.e. along -travel_heading on the map.
            orn = p.getQuaternionFromEuler([0.0, 0.0, yaw_of(ap.travel_heading + math.pi)])
            uid = p.createMultiBody(
                baseMass=0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=housing, basePosition=pos.tolist(),
                baseOrientation=orn, linkMasses=[0.0] * 3, linkCollisionShapeIndices=[-1] * 3,
                linkVisualShapeIndices=lamps,
                linkPositions=[[hx + 0.02, 0.0, LAMP_SPACING_M * (1 - k)] for k in range(3)],
                linkOrientations=[[0, 0, 0, 1]] * 3, linkInertialFramePositions=[[0, 0, 0]] * 3,
                linkInertialFrameOrientations=[[0, 0, 0, 1]] * 3, linkParentIndices=[0] * 3,
                linkJointTypes=[p.JOINT_FIXED] * 3, linkJointAxis=[[0, 0, 1]] * 3, **self._cid)
            self._no_collisions(uid)
            self._label(uid, [-1], SemanticClass.TRAFFIC_LIGHT, LIGHT_ID_BASE + ap.index)
            self._label(uid, [0, 1, 2], SemanticClass.TRAFFIC_LAMP, LIGHT_ID_BASE + ap.index)
            self._light_bodies.append(uid)
            self._light_states.append(None)
            self._light_shown.append(True)
            self.triangle_count += 12 + 3 * 6

    def set_light_states(self, states: Sequence[LightState]) -> None:
        """Recolour lamps, touching pybullet only for lights whose state changed."""
        if self._partners:
            message = ("lights", tuple(int(s) for s in states))
            for partner in self._partners:
                partner.send(message)
        self._set_light_states(states)

    def _set_light_states(self, states: Sequence[LightState]) -> None:
        states = tuple(states[:len(self._light_bodies)])
        if states == self._light_input:
            return  # most steps: no light changed (one tuple compare instead of an enum per light)
        self._light_input = states
        for k, state in enumerate(states):
            state = LightState(state)
            if self._light_states[k] == state:
                continue
            self._light_states[k] = state
            for link, lamp in enumerate(LAMP_ORDER):
                on = lamp == state
                self._set_emissive(self._light_bodies[k], link, LAMP_ON_RGB[lamp] if on else None, night_only=False)
            if self._light_shown[k]:
                self._paint_light(k)

    def _paint_light(self, k: int) -> None:
        """Apply light k's housing and lamp colours, or alpha 0 on all of it when it is out of view."""
        uid, state, alpha = self._light_bodies[k], self._light_states[k], 1.0 if self._light_shown[k] else 0.0
        if not self._mine(uid):
            return  # another process draws it; here it stays at alpha 0
        p.changeVisualShape(uid, -1, rgbaColor=[*HOUSING_RGB, alpha], **self._cid)
        for link, lamp in enumerate(LAMP_ORDER):
            rgb = LAMP_ON_RGB[lamp] if lamp == state else LAMP_OFF_RGB[lamp]
            p.changeVisualShape(uid, link, rgbaColor=[*rgb, alpha], **self._cid)

    def _cull_lights(self, eye_xy: np.ndarray, heading: float, camera: CameraConfig) -> None:
        """Hide traffic lights outside the camera's view wedge, as ``_cull`` does for static tiles."""
        rel = self._light_xy - eye_xy
        dist = np.hypot(rel[:, 0], rel[:, 1])
        ang = np.abs((np.arctan2(rel[:, 1], rel[:, 0]) - heading + np.pi) % (2 * np.pi) - np.pi)
        reach = math.radians(camera.hfov_deg) / 2 + np.arcsin(np.clip(2.0 / np.maximum(dist, 1e-6), 0, 1)) + 0.1
        show = (dist < 3.0) | ((dist < camera.far_m) & (ang <= reach))
        for k in np.nonzero(show != self._light_shown)[0]:
            self._light_shown[k] = bool(show[k])
            self._paint_light(int(k))

    # ----------------------------------------------------------------- signs
    def _build_signs(self) -> None:
        """One multibody per sign: the post (base, POLE) and the plate's parts as links, one colour each, labelled
        with the sign's class and ``SIGN_ID_BASE + index``. Bodies, not tiles of one mesh: the segmentation
        tells bodies (and links) apart, not triangles; out of view they are hidden like lights."""
        signs = self.town.signs
        if len(signs) > MAX_SIGNS:
            raise ValueError(f"A town may have at most {MAX_SIGNS} signs for the segmentation's ids; it has {len(signs)}.")
        self._sign_bodies: list[int] = []
        self._sign_paint: list[list[tuple[int, tuple[float, float, float]]]] = []
        shapes: dict[tuple, int] = {}
        for sign in signs:
            key = (int(sign.kind), round(sign.plate_size_m, 3), round(sign.plate_height_m, 3), int(sign.value_kmh))
            parts = sign_parts(*key)
            ids = []
            for k, part in enumerate(parts):
                if (key, k) not in shapes:
                    v, _, nrm = part.mesh
                    shapes[(key, k)] = self._mesh_shape(np.array(v), np.array(nrm), (*part.rgb, 1.0))
                ids.append(shapes[(key, k)])
            n = len(parts) - 1
            orn = p.getQuaternionFromEuler([0.0, 0.0, yaw_of(sign.facing + math.pi)])  # the face looks at its readers
            uid = p.createMultiBody(
                baseMass=0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=ids[0],
                basePosition=world_point(sign.position[0], sign.position[1], 0.0), baseOrientation=orn,
                linkMasses=[0.0] * n, linkCollisionShapeIndices=[-1] * n, linkVisualShapeIndices=ids[1:],
                linkPositions=[[0, 0, 0]] * n, linkOrientations=[[0, 0, 0, 1]] * n,
                linkInertialFramePositions=[[0, 0, 0]] * n, linkInertialFrameOrientations=[[0, 0, 0, 1]] * n,
                linkParentIndices=[0] * n, linkJointTypes=[p.JOINT_FIXED] * n, linkJointAxis=[[0, 0, 1]] * n,
                **self._cid)
            self._no_collisions(uid)
            self._label(uid, [-1], SemanticClass.POLE, 0)
            self._label(uid, list(range(n)), SIGN_CLASS[int(sign.kind)], SIGN_ID_BASE + sign.index)
            for link in range(1, n):  # the face's parts (not the back): retroreflective sheeting at night
                rgb = parts[link + 1].rgb
                self._set_emissive(uid, link, tuple(SIGN_NIGHT_GLOW * c for c in rgb), night_only=True)
            self._sign_bodies.append(uid)
            self._sign_paint.append([(link, part.rgb) for link, part in zip(range(-1, n), parts, strict=True)])
            self.triangle_count += sum(len(part.mesh[1]) // 3 for part in parts)
        self._sign_xy = np.array([s.position for s in signs], float).reshape(-1, 2)
        self._sign_shown = np.ones(len(signs), bool)

    def _cull_signs(self, eye_xy: np.ndarray, heading: float, camera: CameraConfig) -> None:
        """Hide signs outside the camera's view wedge or beyond ``SIGN_RANGE_M`` (where a plate is under a pixel
        wide at any camera this project uses), as ``_cull_lights`` does for lights."""
        if not self._sign_bodies:
            return
        rel = self._sign_xy - eye_xy
        dist = np.hypot(rel[:, 0], rel[:, 1])
        ang = np.abs((np.arctan2(rel[:, 1], rel[:, 0]) - heading + np.pi) % (2 * np.pi) - np.pi)
        reach = math.radians(camera.hfov_deg) / 2 + np.arcsin(np.clip(1.0 / np.maximum(dist, 1e-6), 0, 1)) + 0.1
        show = (dist < 2.0) | ((dist < min(camera.far_m, SIGN_RANGE_M)) & (ang <= reach))
        for k in np.nonzero(show != self._sign_shown)[0]:
            alpha = 1.0 if show[k] else 0.0
            if not self._mine(self._sign_bodies[k]):
                continue
            for link, rgb in self._sign_paint[k]:
                p.changeVisualShape(self._sign_bodies[k], link, rgbaColor=[*rgb, alpha], **self._cid)
        self._sign_shown = show

    # ----------------------------------------------------------------- moving objects
    def _box_shape(self, half: Sequence[float], offset: Sequence[float], rgb: Sequence[float]) -> int:
        key = ("box", tuple(round(float(h), 3) for h in half), tuple(round(float(o), 3) for o in offset),
               tuple(round(float(c), 3) for c in rgb))
        if key not in self._shapes:
            self._shapes[key] = p.createVisualShape(
                p.GEOM_BOX, halfExtents=list(key[1]), visualFramePosition=list(key[2]), rgbaColor=[*key[3], 1.0],
                specularColor=[0.0, 0.0, 0.0], **self._cid)
        return self._shapes[key]

    def _box_array(self, halves: list[Sequence[float]], offsets: list[Sequence[float]], rgb: Sequence[float]) -> int:
        key = ("array", tuple(tuple(round(float(h), 3) for h in hh) for hh in halves),
               tuple(tuple(round(float(o), 3) for o in oo) for oo in offsets), tuple(round(float(c), 3) for c in rgb))
        if key not in self._shapes:
            self._shapes[key] = p.createVisualShapeArray(
                shapeTypes=[p.GEOM_BOX] * len(halves), halfExtents=[list(h) for h in key[1]],
                visualFramePositions=[list(o) for o in key[2]], **self._cid)
        return self._shapes[key]

    def _multibody(self, base: int, links: list[int]) -> int:
        n = len(links)
        uid = p.createMultiBody(
            baseMass=0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=base, basePosition=[0, 0, HIDDEN_Z],
            linkMasses=[0.0] * n, linkCollisionShapeIndices=[-1] * n, linkVisualShapeIndices=links,
            linkPositions=[[0, 0, 0]] * n, linkOrientations=[[0, 0, 0, 1]] * n,
            linkInertialFramePositions=[[0, 0, 0]] * n, linkInertialFrameOrientations=[[0, 0, 0, 1]] * n,
            linkParentIndices=[0] * n, linkJointTypes=[p.JOINT_FIXED] * n, linkJointAxis=[[0, 0, 1]] * n, **self._cid)
        self._no_collisions(uid)
        return uid

    def _no_collisions(self, uid: int) -> None:
        """Take a body's links out of collision pairing (group and mask 0).

        pybullet gives every link a shapeless collider in its broadphase even without collision shapes,
        and each pose reset re-inserts the body's colliders and pairs them with every overlapping one
        (all links of a body share one point, and so do all static bodies). Nothing here uses
        collisions; unpaired, a reset of a moving object costs about half as much.
        """
        for link in range(-1, p.getNumJoints(uid, **self._cid)):
            p.setCollisionFilterGroupMask(uid, link, 0, 0, **self._cid)

    def _settle_broadphase(self) -> None:
        """Let pybullet update its collision broadphase once (nothing here collides; no pose changes).

        The world is never stepped, so pybullet never tidies its broadphase, and after the town's bodies
        are built a pose reset of a car cost about 14 us (2 us in a client without the town). One
        collision-detection pass (0.2-2 ms, once per new batch of bodies) brings it to about 3 us.
        Measured, not traced: presumably the pass moves the colliders that did not move into Bullet's
        static tree and rebalances the trees that each reset walks for every link.
        """
        p.performCollisionDetection(**self._cid)
        self._new_bodies = False

    def _new_body(self, kind: SemanticClass, dims: tuple[float, float, float]) -> _Body:
        """Build the multibody of one object kind and size (colours are set on use)."""
        self._new_bodies = True
        length, width, height = dims
        grey = (0.5, 0.5, 0.5)
        if kind == SemanticClass.PEDESTRIAN:
            w, d = max(width, 0.3), max(length, 0.2)
            legs = self._box_shape([d * 0.3, w * 0.3, height * 0.23], [0, 0, height * 0.23], PANTS_RGB)
            torso = self._box_shape([d * 0.42, w * 0.5, height * 0.19], [0, 0, height * 0.64], grey)
            head = self._box_shape([0.11, 0.1, height * 0.07], [0.01, 0, height * 0.9], SKIN_RGB)
            uid = self._multibody(legs, [torso, head])
            body = _Body(uid, kind, dims, body_links=(0,))
            links = [-1, 0, 1]
        else:
            truck = kind == SemanticClass.TRUCK
            wheel_r = 0.45 if truck else 0.33
            clear = 0.5 if truck else 0.22
            wx, wy = length / 2 - (0.9 if truck else 0.75), width / 2 - 0.16
            wheels = self._box_array([[wheel_r, 0.15, wheel_r]] * 4,
                                     [[sx * wx, sy * wy, wheel_r] for sx in (-1, 1) for sy in (-1, 1)], TYRE_RGB)
            lamp_z = clear + (0.55 if truck else 0.4)
            heads = self._box_array([[0.03, 0.16, 0.08]] * 2,
                                    [[length / 2 + 0.01, sy * (width / 2 - 0.28), lamp_z] for sy in (-1, 1)],
                                    HEADLAMP_RGB)
            tails = self._box_array([[0.03, 0.14, 0.08]] * 2,
                                    [[-length / 2 - 0.01, sy * (width / 2 - 0.25), lamp_z] for sy in (-1, 1)],
                                    TAILLAMP_RGB)
            if truck:
                cab_len = min(2.2, 0.3 * length)
                cargo = self._box_shape([(length - cab_len) / 2 - 0.05, width / 2, (height - clear) / 2],
                                        [-cab_len / 2, 0, (height + clear) / 2], grey)
                cab_h = 0.8 * height
                cab = self._box_shape([cab_len / 2, width / 2 - 0.05, (cab_h - clear) / 2],
                                      [length / 2 - cab_len / 2, 0, (cab_h + clear) / 2], grey)
                glass = self._box_shape([0.03, width / 2 - 0.2, 0.35 * (cab_h - clear) / 2],
                                        [length / 2 + 0.01, 0, cab_h - 0.38 * (cab_h - clear) / 2 - 0.1], GLASS_RGB)
                uid = self._multibody(cargo, [cab, wheels, heads, tails, glass])
                body = _Body(uid, kind, dims, body_links=(-1, 0))
                links = [-1, 0, 1, 2, 3, 4]
            else:
                belt = clear + 0.52 * (height - clear)
                hull = self._box_shape([length / 2, width / 2, (belt - clear) / 2], [0, 0, (belt + clear) / 2], grey)
                cabin = self._box_shape([0.27 * length, width / 2 - 0.1, (height - belt) / 2],
                                        [-0.06 * length, 0, (height + belt) / 2], GLASS_RGB)
                uid = self._multibody(hull, [cabin, wheels, heads, tails])
                body = _Body(uid, kind, dims, body_links=(-1,))
                links = [-1, 0, 1, 2, 3]
            body.lamp_links = {2: HEADLAMP_RGB, 3: (1.0, 0.1, 0.06)}
        self._label(uid, links, kind, 0)
        for entry in p.getVisualShapeData(uid, **self._cid):
            body.link_rgb.setdefault(int(entry[1]), tuple(float(c) for c in entry[7][:3]))
        for link, rgb in body.lamp_links.items():
            self._set_emissive(uid, link, rgb, night_only=True)
        if not self._mine(uid):
            for link in body.link_rgb:
                p.changeVisualShape(uid, link, rgbaColor=[0.5, 0.5, 0.5, 0.0], **self._cid)
        return body

    def sync(self, objects: Sequence[ObjectSnapshot], light_states: Sequence[LightState] = (),
             view: tuple[float, float, float, float, float] | None = None) -> None:
        """Make the scene's moving objects and lamp colours match the world's snapshot.

        ``view`` = (x, y, heading, hfov_deg, range_m) of the camera that renders next: objects
        outside that horizontal wedge are parked out of sight instead of posed, since a pose reset
        of a multi-link body costs tens of microseconds and most of the town is behind the camera.
        """
        if self._partners:  # the helpers replay the same sync, so their bodies get the same ids and poses
            message = ("sync", [(o.object_id, int(o.kind), o.x, o.y, o.heading, o.length_m, o.width_m, o.height_m,
                                 o.color) for o in objects], tuple(int(s) for s in light_states), view)
            for partner in self._partners:
                partner.send(message)
        if light_states:
            self._set_light_states(light_states)
        in_view = _in_view(objects, view)
        active, looks, last_pose, cid = self._active, self._look, self._last_pose, self._cid
        ped = SemanticClass.PEDESTRIAN
        for obj, shown in zip(objects, in_view, strict=True):
            oid = obj.object_id
            body = active.get(oid)
            look = (obj.kind, obj.length_m, obj.width_m, obj.height_m, obj.color)
            if body is None or looks.get(oid) != look:  # else: same body, same paint; only the pose may change
                body = self._fit_body(obj, body)
                looks[oid] = look
            pose = (obj.x, obj.y, obj.heading, body.uid) if shown else ("parked", body.uid)
            if last_pose.get(oid) == pose:
                continue  # standing still (or still out of view): nothing to move
            last_pose[oid] = pose
            if not shown:
                self._set_shown(body, False)
                continue
            if not body.shown:
                self._set_shown(body, True)
            # Pedestrians on a raised surface (sidewalk, park) stand on it.
            z = Z_SLAB if obj.kind == ped and SURFACE_RAISED[self.ground_map.lookup_point(obj.x, obj.y)] else 0.0
            orn = p.getQuaternionFromEuler([0.0, 0.0, yaw_of(obj.heading)])
            p.resetBasePositionAndOrientation(body.uid, world_point(obj.x, obj.y, z), orn, **cid)
        if len(active) > len(objects):  # every object has its body now; more bodies: some objects are gone
            seen = {obj.object_id for obj in objects}
            for oid in [k for k in active if k not in seen]:
                last_pose.pop(oid, None)
                looks.pop(oid, None)
                self._release(oid)
        if self._new_bodies:
            self._settle_broadphase()

    def _fit_body(self, obj: ObjectSnapshot, body: _Body | None) -> _Body:
        """The object's body with the right kind, size and paint (taken from the pool if needed)."""
        dims = (round(obj.length_m, 2), round(obj.width_m, 2), round(obj.height_m, 2))
        if body is not None and (body.kind != obj.kind or body.dims != dims):
            self._release(obj.object_id)
            body = None
        if body is None:
            pool = self._pool.setdefault((obj.kind, dims), [])
            body = pool.pop() if pool else self._new_body(obj.kind, dims)
            self._active[obj.object_id] = body
            self._label(body.uid, [-1, *range(MAX_LINKS)], obj.kind, obj.object_id)
        color = tuple(round(float(c), 4) for c in obj.color)
        if color != body.color:
            body.color = color  # type: ignore[assignment]
            if not self._mine(body.uid):
                return body
            for link in body.body_links:
                p.changeVisualShape(body.uid, link, rgbaColor=[*color, 1.0 if body.shown else 0.0], **self._cid)
        return body

    def _set_shown(self, body: _Body, shown: bool) -> None:
        """Show a body in its paint, or hide it with alpha 0 (cheaper for TinyRenderer than parking it far away)."""
        if body.shown == shown:
            return
        body.shown = shown
        if not self._mine(body.uid):
            return
        for link, rgb in body.link_rgb.items():
            paint = body.color if link in body.body_links else rgb
            p.changeVisualShape(body.uid, link, rgbaColor=[*paint, 1.0 if shown else 0.0], **self._cid)

    def _release(self, object_id: int) -> None:
        body = self._active.pop(object_id)
        p.resetBasePositionAndOrientation(body.uid, [0.0, 0.0, HIDDEN_Z], [0, 0, 0, 1], **self._cid)
        self._set_shown(body, False)
        self._label(body.uid, [-1, *range(MAX_LINKS)], body.kind, 0)
        self._pool.setdefault((body.kind, body.dims), []).append(body)

    # ----------------------------------------------------------------- cameras
    def camera_position(self, camera_pose: tuple[float, float, float], camera: CameraConfig,
                        lateral_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """World-frame eye and unit forward vector of the camera for a vehicle pose (x, y, heading)."""
        x, y, h = camera_pose
        cx = x + camera.mount_forward_m * math.cos(h) - lateral_m * math.sin(h)
        cy = y + camera.mount_forward_m * math.sin(h) + lateral_m * math.cos(h)
        eye = np.array(world_point(cx, cy, camera.mount_height_m))
        yaw, pitch = yaw_of(h), math.radians(camera.pitch_deg)
        forward = np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch)])
        return eye, forward

    def render(self, camera_pose: tuple[float, float, float], camera: CameraConfig | None = None,
               lighting: str = "noon", lateral_m: float = 0.0) -> CameraFrame:
        """One frame from the camera on a vehicle at ``camera_pose`` = (x, y, heading) on the map,
        mounted ``lateral_m`` to the right of the centre line (negative: left)."""
        return self._render(camera_pose, camera or CameraConfig(), lighting, lateral_m)

    def render_stereo(self, camera_pose: tuple[float, float, float], camera: CameraConfig | None = None,
                      lighting: str = "noon") -> tuple[CameraFrame, CameraFrame]:
        """Left (reference) and right frames, each half a baseline off the mount point."""
        camera = camera or CameraConfig(stereo=True)
        half = camera.stereo_baseline_m / 2
        return (self._render(camera_pose, camera, lighting, -half), self._render(camera_pose, camera, lighting, half))

    def _render(self, camera_pose: tuple[float, float, float], camera: CameraConfig, lighting: str,
                lateral_m: float) -> CameraFrame:
        if self._partners:
            eye, forward, view, setup = self._prepare(camera_pose, camera, lighting, lateral_m)
            owner = self._balance(eye, view, camera)
            for partner in self._partners:
                partner.ask(camera_pose, camera, lighting, lateral_m, owner)
            _, _, rgba, buf, seg = p.getCameraImage(camera.width, camera.height, viewMatrix=view, **setup.camera_args)
        else:
            rgba, buf, seg, eye, forward, setup = self._draw(camera_pose, camera, lighting, lateral_m)
        h, w = camera.height, camera.width
        rgba, buf, seg = np.asarray(rgba, np.uint8).reshape(h, w, 4), np.asarray(buf, np.float32).reshape(h, w), \
            np.asarray(seg, np.int32).reshape(h, w)
        for partner in self._partners:
            kernels.merge_share(rgba, buf, seg, *partner.collect(h, w))
        return self._shade(rgba, buf, seg, eye, forward, setup, camera)

    def draw(self, camera_pose: tuple[float, float, float], camera: CameraConfig, lighting: str,
             lateral_m: float = 0.0, tile_owner: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """TinyRenderer's raw RGBA, depth buffer and segmentation mask (flat arrays) of this process's bodies, as
        ``render`` would see them before shading (what a helper process of ``sim.render_share`` hands back);
        ``tile_owner``: which process draws each static tile (the main renderer's ``_balance``)."""
        if tile_owner is not None:
            self._draw_tiles(self._tile_shown, tile_owner)
        return self._draw(camera_pose, camera, lighting, lateral_m)[:3]

    def _balance(self, eye: np.ndarray, view: Sequence[float], camera: CameraConfig) -> np.ndarray:
        """Share the static tiles in view out between the processes by estimated TinyRenderer work
        (``render_kernels.tile_costs``, costliest first to the least loaded), draw this process's, and return the
        owners for the helpers. Only the speed depends on it: any share gives the same frame."""
        pv = (np.asarray(_projection(camera)).reshape(4, 4).T @ np.asarray(view).reshape(4, 4).T)
        cost = kernels.tile_costs(self._tile_tris, self._tile_first, self._tile_shown, pv, eye, camera.width,
                                  camera.height, camera.near_m, COST_PER_TRIANGLE)
        owner = self._tile_owner.copy()
        kernels.share_out(cost, self._tile_shown, owner, self._count, np.zeros(self._count))
        self._draw_tiles(self._tile_shown, owner)
        return owner

    def _draw(self, camera_pose: tuple[float, float, float], camera: CameraConfig, lighting: str,
              lateral_m: float) -> tuple[Any, Any, Any, np.ndarray, np.ndarray, _FrameSetup]:
        """Cull for the camera and call ``getCameraImage``: its buffers, the eye and forward vector, the setup."""
        eye, forward, view, setup = self._prepare(camera_pose, camera, lighting, lateral_m)
        _, _, rgba, buf, seg = p.getCameraImage(camera.width, camera.height, viewMatrix=view, **setup.camera_args)
        return rgba, buf, seg, eye, forward, setup

    def _prepare(self, camera_pose: tuple[float, float, float], camera: CameraConfig, lighting: str,
                 lateral_m: float) -> tuple[np.ndarray, np.ndarray, Any, _FrameSetup]:
        """Cull for the camera: the eye, forward vector, view matrix and the frame's setup."""
        eye, forward = self.camera_position(camera_pose, camera, lateral_m)
        eye_xy = np.array([eye[0], -eye[1]])
        cull_key = (camera.hfov_deg, camera.far_m)
        last = self._last_cull
        if last is None or last[2] != cull_key or math.hypot(*(eye_xy - last[0])) > 0.5 or abs(
                math.remainder(camera_pose[2] - last[1], 2 * math.pi)) > math.radians(1.0):
            # The wedges carry margins of several degrees, so half a metre or a degree of motion changes nothing.
            self._cull(eye_xy, camera_pose[2], camera)
            self._cull_lights(eye_xy, camera_pose[2], camera)
            self._cull_signs(eye_xy, camera_pose[2], camera)
            self._last_cull = (eye_xy, camera_pose[2], cull_key)
        fx, fy, fz = forward.tolist()
        ex, ey, ez = eye.tolist()
        view = p.computeViewMatrix([ex, ey, ez], [ex + fx, ey + fy, ez + fz], [0.0, 0.0, 1.0], **self._cid)
        return eye, forward, view, self._setup(lighting, camera)

    def _shade(self, rgba: np.ndarray, buf: np.ndarray, seg: np.ndarray, eye: np.ndarray, forward: np.ndarray,
               setup: _FrameSetup, camera: CameraConfig) -> CameraFrame:
        """TinyRenderer's buffers (HxW) to the frame: ray-cast ground, sky, grade, fog, headlights, bloom, boxes."""
        fx, fy, fz = forward.tolist()
        ex, ey, ez = eye.tolist()
        h, w = camera.height, camera.width
        depth = np.empty((h, w), np.float32)
        semantic = np.empty((h, w, 2), np.int32)
        rgb = np.empty((h, w, 3), np.uint8)
        bloom = setup.glow_sigma > 0  # the blur needs the whole graded image first; else one pass writes rgb
        img = np.empty((h, w, 3), np.float32) if bloom else _UNUSED_RGB
        glow_src = np.empty((h, w, 3), np.float32) if bloom else _UNUSED_RGB
        sky = np.empty((h, w), np.bool_) if bloom else _UNUSED_MASK
        # right = forward x up, down = forward x right (written out: np.cross is slow on 3-vectors)
        norm = math.hypot(fx, fy)
        rx, ry, rz = fy / norm, -fx / norm, 0.0
        geo = np.array([ex, ey, ez, fx, fy, fz, rx, ry, fy * rz - fz * ry, fz * rx - fx * rz, fx * ry - fy * rx,
                        *setup.geo_tail])
        seen, box = np.empty(BOX_CAPACITY, np.int64), np.empty((BOX_CAPACITY, 5), np.int64)
        any_emit, n_ids = kernels.shade_frame(
            rgba, buf, seg, self._class_lut, self._id_lut, self._emit_mask, self._night_emit,
            self._emissive, setup.palette, SURFACE_CLASS, SURFACE_RAISED, self.ground_map.texels, geo, setup.grade,
            setup.flags, setup.cone, setup.sky, img, depth, semantic, sky, glow_src, rgb, seen, box)
        if bloom:
            glow = cv2.GaussianBlur(glow_src, (0, 0), setup.glow_sigma) if any_emit else glow_src
            gain = setup.grade[kernels.P_GLOW:kernels.P_GLOW + 1] if any_emit else _NO_GLOW
            kernels.finish_frame(img, sky, setup.sky, glow, gain, rgb)
        boxes = kernels.sorted_boxes(seen, box, n_ids) if n_ids >= 0 else None
        return CameraFrame(rgb, depth, semantic, setup.intrinsics.copy(), boxes)

    def _setup(self, lighting: str, camera: CameraConfig) -> _FrameSetup:
        """Everything of a frame that depends only on the camera and the lighting, built once per pair."""
        last = self._last_setup
        if last is not None and last[0] is lighting and last[1] is camera:
            return last[2]  # the same objects as last frame (hashing a camera config costs more than this test)
        key = (lighting, camera)
        hit = self._setups.get(key)
        if hit is None:
            preset = LIGHTING_PRESETS[lighting]
            grade, flags = _grade(preset, camera)
            k = camera.intrinsics()  # the ray-cast uses TinyRenderer's own principal point (see intrinsics())
            gm = self.ground_map
            hit = self._setups[key] = _FrameSetup(
                camera_args=dict(
                    projectionMatrix=_projection(camera), renderer=p.ER_TINY_RENDERER,
                    flags=p.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX, lightDirection=list(_sun(preset)),
                    lightColor=list(preset.light_color), lightAmbientCoeff=preset.ambient,
                    lightDiffuseCoeff=preset.diffuse, lightSpecularCoeff=preset.specular, shadow=0, **self._cid),
                palette=self._surface_palette(lighting, preset), grade=grade, flags=flags,
                cone=_headlight_cone(camera) if preset.headlights else _NO_CONE, sky=_sky_image(camera, preset),
                geo_tail=(camera.focal_px, float(k[0, 2]), float(k[1, 2]), float(gm.origin[0]), float(gm.origin[1]),
                          gm.texels_per_m, Z_SLAB, Z_GROUND),
                glow_sigma=max(0.8, camera.width / 220.0) if preset.glow > 0 else 0.0, intrinsics=k)
        self._last_setup = (lighting, camera, hit)
        return hit

    def close(self) -> None:
        """Disconnect this renderer's pybullet client and stop its helper processes (once; later calls do nothing)."""
        if self._partners:
            self._stop_partners()
        self._finalizer()
        self.client = -1


_MESH_FILES = 0  # mesh files written by this process: each gets the next number (see _mesh_shape)
_MESH_DIR: str | None = None


def _mesh_dir() -> str:
    """A private temporary folder for mesh files, removed at exit."""
    global _MESH_DIR
    if _MESH_DIR is None or not os.path.isdir(_MESH_DIR):
        import atexit
        import shutil
        import tempfile

        _MESH_DIR = tempfile.mkdtemp(prefix="towndrive_meshes_")
        atexit.register(shutil.rmtree, _MESH_DIR, True)
    return _MESH_DIR


def _forget_mesh_files(names: list[str], client: int) -> None:
    """Delete a renderer's mesh files once its bodies are built, and empty pybullet's cache of parsed OBJ files.

    Why: pybullet keeps every OBJ file it parses in a process-wide cache keyed by the file's name
    (``LoadMeshFromObj.cpp``'s ``gCachedObjResults``: about 1.2 MB a town), which no disconnect empties;
    a run over many towns kept one entry per mesh file it ever loaded. The only call that empties it is
    switching the cache off (``enableFileCaching=0``); it is switched on again at once, since while a body
    is created the cache lets TinyRenderer reuse the parse of the file the body's importer made a moment
    before (off for good, every file would be parsed twice). Once the bodies exist nothing reads the files
    again: TinyRenderer keeps its own copy of the triangles. The cache is the whole process's, so this also
    drops entries of files other code loaded; they are parsed again when next used."""
    for name in names:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(name)
    names.clear()
    if p.isConnected(physicsClientId=client):
        p.setPhysicsEngineParameter(enableFileCaching=0, physicsClientId=client)
        p.setPhysicsEngineParameter(enableFileCaching=1, physicsClientId=client)


def _disconnect(client: int) -> None:
    if p.isConnected(physicsClientId=client):
        p.disconnect(physicsClientId=client)
        _return_freed_memory()


def _return_freed_memory() -> None:
    """Hand the heap a town's scene freed back to the OS (glibc's ``malloc_trim``; elsewhere nothing).

    Why: pybullet frees a client's tens of thousands of small mesh allocations at ``disconnect``, but glibc
    keeps freed small blocks in its heap, so a process that renders town after town kept a rising floor of
    freed memory (the soak in bench/bench_memory_soak.py). Trimming costs about a millisecond per town."""
    global _MALLOC_TRIM
    if _MALLOC_TRIM is None:
        import ctypes
        import ctypes.util
        import sys

        _MALLOC_TRIM = False
        if sys.platform.startswith("linux"):
            with contextlib.suppress(OSError, AttributeError):  # not glibc (musl has no malloc_trim)
                _MALLOC_TRIM = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    if _MALLOC_TRIM:
        _MALLOC_TRIM(0)


_MALLOC_TRIM: object = None


_GROUND_MAPS: weakref.WeakValueDictionary[tuple[int, int, object], GroundMap] = weakref.WeakValueDictionary()
_NO_CONE = np.zeros((1, 1), np.float32)  # the kernel's headlight cone when the preset has no headlights
_NO_CONE.setflags(write=False)  # read-only like the cached cones: one compiled kernel signature, not two
_NO_GLOW = np.zeros(1, np.float32)  # bloom gain 0: no blurred glow to add
_UNUSED_RGB = np.zeros((1, 1, 3), np.float32)  # the kernel's scratch images when a preset has no bloom
_UNUSED_MASK = np.zeros((1, 1), np.bool_)


def _grade(preset: LightingPreset, camera: CameraConfig) -> tuple[np.ndarray, np.ndarray]:
    """The shading kernel's float32 grading constants and int flags for a preset and camera.

    Each constant is rounded to float32 exactly where NumPy rounded it when it mixed a Python
    float with a float32 image, so the kernel reproduces its pixels bit for bit.
    """
    near, far = camera.near_m, camera.far_m
    gain = np.asarray(preset.gain, np.float32)
    grade = np.zeros(kernels.GRADE_SIZE, np.float32)
    grade[kernels.P_NEAR_FAR], grade[kernels.P_FAR], grade[kernels.P_FAR_MINUS_NEAR] = far * near, far, far - near
    grade[kernels.P_GAIN:kernels.P_GAIN + 3] = gain
    grade[kernels.P_FOG] = preset.fog_distance_m
    grade[kernels.P_FOG_RGB:kernels.P_FOG_RGB + 3] = np.asarray(preset.sky_horizon, np.float32) * gain
    grade[kernels.P_LIFT:kernels.P_LIFT + 3] = np.asarray(preset.lift, np.float32)
    grade[kernels.P_HL_AMBIENT], grade[kernels.P_HL_GAIN] = preset.headlight_ambient, preset.headlight_gain
    grade[kernels.P_GLOW] = preset.glow
    flags = np.array([preset.fog_distance_m > 0, any(preset.lift), preset.headlights, preset.emissive_windows,
                      preset.glow > 0], np.int64)
    return grade, flags


_RADII: dict[tuple[float, float], float] = {}  # an object's footprint radius plus margin, by (length, width)


def _in_view(objects: Sequence[ObjectSnapshot], view: tuple[float, float, float, float, float] | None) -> list[bool]:
    """Which objects may show in a camera's horizontal wedge (conservative: size and a 5 degree margin count)."""
    if view is None or not objects:
        return [True] * len(objects)
    x, y, heading, hfov_deg, range_m = view
    discs = []  # x, y and radius of each object, gathered in one pass into one array
    for o in objects:
        r = _RADII.get((o.length_m, o.width_m))
        if r is None:
            if len(_RADII) > 1024:
                _RADII.clear()
            r = _RADII[(o.length_m, o.width_m)] = 0.5 * math.hypot(o.length_m, o.width_m) + 1.0
        discs.append((o.x, o.y, r))
    xyr = np.array(discs)
    return kernels.in_view_wedge(xyr[:, :2], xyr[:, 2], float(x), float(y), float(heading), math.radians(hfov_deg) / 2,
                                 float(range_m), math.radians(5)).tolist()


def _ground_map(town: Town) -> GroundMap:
    """One ground map per town object, shared by all renderers of it (it is ~16 MB). The cache holds it weakly:
    it lives as long as a renderer uses it, and goes with the last one (a strong cache kept up to nine maps of
    towns no renderer used any more). The key has the town's seed and config besides its id, so a new town that
    reuses a freed one's id finds the map only if it is the same town."""
    key = (id(town), town.seed, town.config)
    hit = _GROUND_MAPS.get(key)
    if hit is None:
        hit = _GROUND_MAPS[key] = build_ground_map(town)
    return hit


@lru_cache(maxsize=32)
def _projection(camera: CameraConfig) -> tuple[float, ...]:
    """OpenGL projection for the camera (cached: it depends only on the config)."""
    return tuple(p.computeProjectionMatrixFOV(camera.vfov_deg, camera.width / camera.height,
                                              camera.near_m, camera.far_m))


@lru_cache(maxsize=32)
def _headlight_cone(camera: CameraConfig) -> np.ndarray:
    """Headlight footprint in the image: bright lower middle, soft edges, nothing above the horizon line."""
    u = (np.arange(camera.width, dtype=np.float32) - camera.width / 2) / camera.focal_px  # tan of azimuth
    v = (np.arange(camera.height, dtype=np.float32) - camera.height / 2) / camera.focal_px  # tan below axis
    v = v + math.tan(math.radians(-camera.pitch_deg))  # relative to the horizontal
    horiz = np.exp(-(u / 0.55) ** 2)
    vert = np.clip((v + 0.06) / 0.12, 0.0, 1.0)
    cone = (vert[:, None] * horiz[None, :]).astype(np.float32)
    cone.setflags(write=False)
    return cone


@lru_cache(maxsize=32)
def _sky_image(camera: CameraConfig, preset: LightingPreset) -> np.ndarray:
    """Vertical sky gradient from the zenith colour to the horizon colour at the true horizon row."""
    f = camera.focal_px
    rows = np.arange(camera.height, dtype=np.float32)
    elev = np.degrees(np.arctan((camera.height / 2 - rows) / f)) + camera.pitch_deg  # elevation of each row
    t = np.clip(elev / 35.0, 0.0, 1.0) ** 0.7
    top, hor = np.asarray(preset.sky_top, np.float32), np.asarray(preset.sky_horizon, np.float32)
    col = hor[None, :] * (1 - t[:, None]) + top[None, :] * t[:, None]
    img = np.repeat(col[:, None, :], camera.width, axis=1).astype(np.float32)
    img.setflags(write=False)
    return img
