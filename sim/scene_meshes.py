"""Triangle meshes of the static town, grouped by (semantic class, colour), for the camera renderer.

TinyRenderer's cost grows with triangles and bodies, so the static scene is a handful of merged
meshes: one per semantic class and colour. This module also owns THE mapping from the 2D map
frame (x right, y down, heading = atan2(dy, dx)) to pybullet's z-up right-handed world frame:
``(x, y) -> (x, -y, z)`` and ``heading -> yaw = -heading``. Nothing else converts frames.
"""

from __future__ import annotations

import itertools
import math
import mmap
from dataclasses import dataclass, field
from enum import IntEnum

import cv2
import numpy as np

from towndrive.sim.objects import SemanticClass
from towndrive.sim.spec import ROAD
from towndrive.sim.town import Town

# Heights (metres). The flat layers are not meshes: TinyRenderer shades ~100 ns per pixel per layer
# and tests every pixel of each triangle's bounding box, so ground meshes cost more than the rest of
# the town together. ``GroundMap`` rasterises them top-down once; the renderer ray-casts each pixel
# to two planes (road level, slab level) and looks the surface up.
Z_GROUND = 0.0  # grass, asphalt and paint share the road plane
Z_ROAD = 0.0
Z_SLAB = 0.15  # sidewalks, block slabs and parks

FLOOR_HEIGHT_M = 3.2
WINDOW_BOTTOM_M = 0.9  # above each floor's base
WINDOW_TOP_M = 2.3
WINDOW_OFFSET_M = 0.08  # in front of the wall, to win the depth test
WINDOW_LIT_FRACTION = 0.25  # share of window bands that glow at night

POLE_HALF_M = 0.14
ARM_HALF_M = 0.09
HOUSING_HALF = (0.3, 0.42, ROAD.signal_housing_height_m / 2)  # x (depth), y (width), z (height) of a light's housing
LAMP_RADIUS_M = 0.3
LAMP_SPACING_M = 0.68


def _dz(z: float) -> np.ndarray:
    """A vertical offset (world frame)."""
    return np.array([0.0, 0.0, z])


def to_world(x: float | np.ndarray, y: float | np.ndarray, z: float | np.ndarray = 0.0) -> np.ndarray:
    """Map-frame point(s) to pybullet world coordinates: (x, y) -> (x, -y, z). The one place it happens."""
    x, y, z = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float), np.asarray(z, float))
    return np.stack([x, -y, z], axis=-1)


def world_point(x: float, y: float, z: float = 0.0) -> list[float]:
    """One map-frame point as a pybullet position list; the scalar twin of ``to_world`` for hot loops."""
    return [float(x), -float(y), float(z)]


def yaw_of(heading: float) -> float:
    """Map-frame heading to pybullet yaw about +z (the y flip reverses the sense of rotation)."""
    return -heading


@dataclass
class Mesh:
    """A flat-shaded triangle soup: every triangle owns its three vertices (normals per face)."""

    vertices: list[np.ndarray] = field(default_factory=list)
    normals: list[np.ndarray] = field(default_factory=list)

    @property
    def triangle_count(self) -> int:
        return len(self.vertices) // 3

    def tri(self, a: np.ndarray, b: np.ndarray, c: np.ndarray, normal: np.ndarray) -> None:
        """Add a world-frame triangle, wound counter-clockwise about ``normal`` (whatever order it came in)."""
        n = np.asarray(normal, float)
        n = n / max(float(np.linalg.norm(n)), 1e-12)
        if float(np.dot(np.cross(b - a, c - a), n)) < 0:
            b, c = c, b
        self.vertices += [a, b, c]
        self.normals += [n, n, n]

    def quad(self, a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray, normal: np.ndarray) -> None:
        """A planar convex quad a-b-c-d (in order round its rim)."""
        self.tri(a, b, c, normal)
        self.tri(a, c, d, normal)

    def polygon_top(self, poly: np.ndarray, z: float) -> None:
        """A convex map-frame polygon as an upward-facing fan at height z."""
        pts = to_world(poly[:, 0], poly[:, 1], z)
        up = np.array([0.0, 0.0, 1.0])
        for k in range(1, len(pts) - 1):
            self.tri(pts[0], pts[k], pts[k + 1], up)

    def prism_sides(self, poly: np.ndarray, z0: float, z1: float, max_len_m: float = 1e9) -> None:
        """Outward-facing vertical walls of a convex map-frame polygon between two heights."""
        pts = to_world(poly[:, 0], poly[:, 1], 0.0)
        centre = pts.mean(axis=0)
        for k in range(len(pts)):
            p, q = pts[k], pts[(k + 1) % len(pts)]
            length = float(np.linalg.norm(q - p))
            if length < 1e-6:
                continue
            n = np.array([q[1] - p[1], -(q[0] - p[0]), 0.0])
            if float(np.dot(n, (p + q) / 2 - centre)) < 0:
                n = -n
            dz0, dz1 = np.array([0, 0, z0]), np.array([0, 0, z1])
            cuts = np.linspace(0.0, 1.0, math.ceil(length / max_len_m) + 1)
            for t0, t1 in itertools.pairwise(cuts):
                a, b = p + (q - p) * t0, p + (q - p) * t1
                self.quad(a + dz0, b + dz0, b + dz1, a + dz1, n)

    def box(self, centre: np.ndarray, half: np.ndarray, top: bool = True, bottom: bool = False) -> None:
        """An axis-aligned world-frame box (the camera never sees bottoms, so they are optional)."""
        c, h = np.asarray(centre, float), np.asarray(half, float)
        for axis in range(3):
            for sign in (-1.0, 1.0):
                if axis == 2 and ((sign > 0 and not top) or (sign < 0 and not bottom)):
                    continue
                n = np.zeros(3)
                n[axis] = sign
                u, v = [a for a in range(3) if a != axis]
                corners = []
                for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                    p = c.copy()
                    p[axis] += sign * h[axis]
                    p[u] += su * h[u]
                    p[v] += sv * h[v]
                    corners.append(p)
                self.quad(*corners, normal=n)

    def arrays(self) -> tuple[list[list[float]], list[int], list[list[float]]]:
        """(vertices, indices, normals) as pybullet's createVisualShape wants them."""
        v = np.asarray(self.vertices, float).round(4)
        n = np.asarray(self.normals, float).round(5)
        return v.tolist(), list(range(len(v))), n.tolist()


class Surface(IntEnum):
    """Texel values of the ground map, in paint order."""

    GRASS = 0
    ROAD = 1
    SIDEWALK = 2
    PARK = 3
    WHITE = 4
    YELLOW = 5
    STOP = 6
    CROSSWALK = 7


GRASS_RGB = (0.30, 0.42, 0.22)
SURFACE_RGB = np.array([GRASS_RGB, (0.24, 0.24, 0.26), (0.66, 0.65, 0.62), (0.34, 0.52, 0.26),
                        (0.92, 0.92, 0.90), (0.95, 0.75, 0.18), (0.95, 0.95, 0.93), (0.92, 0.92, 0.90)], np.float32)
SURFACE_CLASS = np.array([SemanticClass.GROUND, SemanticClass.ROAD, SemanticClass.SIDEWALK, SemanticClass.GROUND,
                          SemanticClass.LANE_MARKING, SemanticClass.LANE_MARKING, SemanticClass.STOP_LINE,
                          SemanticClass.CROSSWALK], np.int32)
SURFACE_RAISED = np.array([False, False, True, True, False, False, False, False])  # at Z_SLAB, not Z_ROAD


@dataclass
class GroundMap:
    """The town's flat layers as a top-down texel grid of ``Surface`` values (map frame, row = y)."""

    texels: np.ndarray  # uint8 HxW
    origin: np.ndarray  # map (x, y) of texel (0, 0)'s corner
    texels_per_m: float

    def lookup(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Surface under map points, nearest texel. The map's border texels are grass, so clamping
        the index sends every point outside the map to grass without a separate test."""
        h, w = self.texels.shape
        ix = ((x - self.origin[0]) * self.texels_per_m).astype(np.int32)
        iy = ((y - self.origin[1]) * self.texels_per_m).astype(np.int32)
        np.clip(ix, 0, w - 1, out=ix)
        np.clip(iy, 0, h - 1, out=iy)
        return self.texels[iy, ix]

    def lookup_point(self, x: float, y: float) -> int:
        """``lookup`` for one point, without arrays (the same float operations, truncation and clamping)."""
        h, w = self.texels.shape
        ix = min(max(int((float(x) - float(self.origin[0])) * self.texels_per_m), 0), w - 1)
        iy = min(max(int((float(y) - float(self.origin[1])) * self.texels_per_m), 0), h - 1)
        return int(self.texels[iy, ix])


def build_ground_map(town: Town, texels_per_m: float = 10.0) -> GroundMap:
    """Rasterise asphalt, slabs, parks and markings (sub-texel accurate) into a ``GroundMap``."""
    xmin, ymin, xmax, ymax = town.extent
    origin = np.array([xmin, ymin])
    w, h = math.ceil((xmax - xmin) * texels_per_m), math.ceil((ymax - ymin) * texels_per_m)
    tex = _own_pages(h, w)
    shift = 4

    def fill(poly: np.ndarray, value: Surface) -> None:
        pts = np.round((poly - origin) * texels_per_m * (1 << shift) - 0.5 * (1 << shift)).astype(np.int32)
        cv2.fillConvexPoly(tex, pts, int(value), lineType=cv2.LINE_8, shift=shift)

    for poly in town.road_polygons:
        fill(poly, Surface.ROAD)
    for poly in town.slab_polygons:
        fill(poly, Surface.SIDEWALK)
    for poly in town.grass_polygons:
        fill(poly, Surface.PARK)
    # Give-way triangles are the stop bar's paint and class: both mark where the entry's traffic waits, which is
    # what a labeller of "the line to stop at" wants; the sign beside the road says whether to stop or yield.
    kinds = {"dashed_white": Surface.WHITE, "solid_white": Surface.WHITE, "solid_yellow": Surface.YELLOW,
             "stop_line": Surface.STOP, "crosswalk": Surface.CROSSWALK, "yield_line": Surface.STOP}
    for kind, quads in town.markings.items():
        for quad in quads:
            fill(quad, kinds[kind])
    tex[[0, -1], :] = Surface.GRASS  # a grass border: lookups clamp onto it (see GroundMap.lookup)
    tex[:, [0, -1]] = Surface.GRASS
    return GroundMap(tex, origin, texels_per_m)


def _own_pages(h: int, w: int) -> np.ndarray:
    """A zeroed HxW uint8 array in its own anonymous memory map, unmapped (given back to the OS) when freed.

    Why: a ground map is about 16 MB and there is one per town. glibc serves the first from its own mmap,
    but freeing it raises glibc's mmap threshold above its size, so every later map came from the heap;
    freed there it stayed resident (a process that renders town after town held one or two dead maps,
    about 30 MB, bench/bench_memory_soak.py). A map of its own goes back to the OS when the last renderer
    of its town lets go of it, whatever malloc's thresholds."""
    if h * w == 0:
        return np.zeros((h, w), np.uint8)
    return np.frombuffer(mmap.mmap(-1, h * w), np.uint8).reshape(h, w)


@dataclass
class MeshGroup:
    """One static body: a merged mesh of one semantic class and one colour."""

    name: str
    semantic: SemanticClass
    rgba: tuple[float, float, float, float]
    mesh: Mesh
    emissive_at_night: tuple[float, float, float] | None = None  # lit windows


KERB_RGB = (0.80, 0.79, 0.76)
GLASS_RGB = (0.14, 0.18, 0.25)
LIT_WINDOW_RGB = (0.78, 0.62, 0.36)  # warm, dimmer than lamps: lit offices, not floodlights
TRUNK_RGB = (0.36, 0.26, 0.17)
POLE_RGB = (0.22, 0.23, 0.24)


def _rgba(rgb: tuple[float, float, float]) -> tuple[float, float, float, float]:
    return (float(rgb[0]), float(rgb[1]), float(rgb[2]), 1.0)


def build_static_groups(town: Town, seed: int = 0) -> list[MeshGroup]:
    """All standing static scenery (not the flat ground layers, not the light housings/lamps).

    Groups come back in draw order, nearest-to-the-eye layers first: TinyRenderer rejects a pixel
    on the depth test before running its costly shader, so windows go before the walls they cover.
    """
    rng = np.random.default_rng(seed)
    groups: dict[str, MeshGroup] = {}
    order = ["windows_lit", "windows", "building", "canopy", "trunks", "poles", "kerb"]

    def group(name: str, semantic: SemanticClass, rgb: tuple[float, float, float]) -> Mesh:
        if name not in groups:
            groups[name] = MeshGroup(name, semantic, _rgba(rgb), Mesh())
        return groups[name].mesh

    # Buildings: walls (and roof) in their palette colour, a dark glass band per floor on each
    # street-facing facade (back facades face the block interior, which no street camera sees).
    sw = town.config.sidewalk_width_m
    for b in town.buildings:
        key = "building_" + "_".join(f"{c:.2f}" for c in b.color)
        walls = group(key, SemanticClass.BUILDING, b.color)
        walls.prism_sides(b.footprint, Z_SLAB - 0.05, b.height_m)
        walls.polygon_top(b.footprint, b.height_m)
        floors = int((b.height_m - 1.0) // FLOOR_HEIGHT_M)
        centre2 = b.footprint.mean(axis=0)
        for k in range(len(b.footprint)):
            p2, q2 = b.footprint[k], b.footprint[(k + 1) % len(b.footprint)]
            length = float(np.linalg.norm(q2 - p2))
            if length < 4.0:
                continue
            along2 = (q2 - p2) / length
            out2 = np.array([-along2[1], along2[0]])
            if float(np.dot(out2, (p2 + q2) / 2 - centre2)) < 0:
                out2 = -out2
            if not town.on_road((p2 + q2) / 2 + out2 * (sw + 3.0), margin_m=2.0):
                continue
            p, q = to_world(p2[0], p2[1]), to_world(q2[0], q2[1])
            n = to_world(out2[0], out2[1])
            inset = min(1.2, 0.15 * length)
            step = (q - p) * inset / length
            a, c = p + step + n * WINDOW_OFFSET_M, q - step + n * WINDOW_OFFSET_M
            pieces = math.ceil(float(np.linalg.norm(c - a)) / 6.0)
            for f in range(floors):
                lit = rng.random() < WINDOW_LIT_FRACTION
                mesh = group("windows_lit" if lit else "windows", SemanticClass.BUILDING, GLASS_RGB)
                z0 = Z_SLAB + f * FLOOR_HEIGHT_M + WINDOW_BOTTOM_M
                z1 = Z_SLAB + f * FLOOR_HEIGHT_M + WINDOW_TOP_M
                for t in range(pieces):
                    u, v = a + (c - a) * t / pieces, a + (c - a) * (t + 1) / pieces
                    mesh.quad(u + _dz(z0), v + _dz(z0), v + _dz(z1), u + _dz(z1), n)
    if "windows_lit" in groups:
        groups["windows_lit"].emissive_at_night = LIT_WINDOW_RGB

    # Trees: a square trunk and a six-sided bipyramid canopy, grouped by three shades of green.
    trunk = group("trunks", SemanticClass.VEGETATION, TRUNK_RGB)
    shades = [(0.17, 0.36, 0.14), (0.22, 0.44, 0.16), (0.28, 0.50, 0.18)]
    for t in town.trees:
        base = to_world(t.position[0], t.position[1], Z_SLAB)
        r = t.canopy_radius_m
        z_canopy = max(1.6, t.height_m - 2.0 * r)
        trunk.box(base + _dz(z_canopy / 2), np.array([Town.TRUNK_RADIUS_M, Town.TRUNK_RADIUS_M, z_canopy / 2]),
                  top=False)
        g = t.color[1]
        shade = 0 if g < 0.47 else (1 if g < 0.53 else 2)
        canopy = group(f"canopy_{shade}", SemanticClass.VEGETATION, shades[shade])
        _canopy(canopy, base, z_canopy, t.height_m, r, float(rng.uniform(0, math.pi / 3)))

    # Light poles and mast arms (the housings and lamps are per-light bodies, see render.py). A mast arm reaches
    # over the lanes above the head; a post-mounted head hangs on the post's side, which ends at the head's top.
    poles = group("poles", SemanticClass.POLE, POLE_RGB)
    for ap in town.approaches:
        foot = to_world(ap.light_pole[0], ap.light_pole[1], Z_SLAB)
        if ap.mount != "mast_arm":
            top_z = ap.head_height_m + HOUSING_HALF[2]
            poles.box(foot + _dz((top_z - Z_SLAB) / 2), np.array([POLE_HALF_M, POLE_HALF_M, (top_z - Z_SLAB) / 2]))
            continue
        top_z = ap.head_height_m + HOUSING_HALF[2] + 2 * ARM_HALF_M
        poles.box(foot + _dz((top_z - Z_SLAB) / 2), np.array([POLE_HALF_M, POLE_HALF_M, (top_z - Z_SLAB) / 2]))
        head = to_world(ap.light_head[0], ap.light_head[1], top_z - ARM_HALF_M)
        arm_foot = foot.copy()
        arm_foot[2] = head[2]
        span = head - arm_foot
        length = float(np.linalg.norm(span))
        if length > 1e-6:
            end = head + span / length * 0.3
            half = np.abs(end - arm_foot) / 2 + ARM_HALF_M
            half[2] = ARM_HALF_M
            poles.box((arm_foot + end) / 2, half, top=True, bottom=True)

    # Kerb faces only: the flat layers (asphalt, markings, sidewalk and park tops, grass) are the
    # ground map below, drawn in numpy.
    kerb = group("kerb", SemanticClass.SIDEWALK, KERB_RGB)
    for poly in town.kerb_outlines or town.slab_polygons:  # a bent town's slabs are cut in pieces: kerbs go round
        kerb.prism_sides(poly, Z_ROAD - 0.02, Z_SLAB, max_len_m=8.0)

    def rank(g: MeshGroup) -> int:
        return next(k for k, prefix in enumerate(order) if g.name.startswith(prefix))

    return sorted((g for g in groups.values() if g.mesh.triangle_count > 0), key=rank)


def _canopy(mesh: Mesh, base: np.ndarray, z0: float, z1: float, r: float, phase: float) -> None:
    """A low-poly rounded crown: two offset hexagonal rings between a bottom and a top apex."""
    lo, hi = base + _dz(z0 + 0.45 * (z1 - z0) * 0.6), base + _dz(z0 + 0.72 * (z1 - z0))

    def ring(centre: np.ndarray, radius: float, offset: float) -> list[np.ndarray]:
        angles = offset + np.arange(6) * math.pi / 3
        return [centre + radius * np.array([math.cos(a), math.sin(a), 0.0]) for a in angles]

    low, high = ring(lo, r, phase), ring(hi, 0.8 * r, phase + math.pi / 6)
    bottom, top = base + _dz(z0), base + _dz(z1)
    mid = (lo + hi) / 2
    for k in range(6):
        j = (k + 1) % 6
        mesh.tri(low[k], low[j], bottom, (low[k] + low[j]) / 2 - lo - np.array([0, 0, 0.8 * r]))
        mesh.tri(high[k], high[j], top, (high[k] + high[j]) / 2 - hi + np.array([0, 0, 0.9 * r]))
        mesh.tri(low[k], low[j], high[k], (low[k] + low[j] + high[k]) / 3 - mid)
        mesh.tri(high[k], high[j], low[j], (high[k] + high[j] + low[j]) / 3 - mid)


MeshArrays = tuple[list[list[float]], list[int], list[list[float]]]


def light_lamp_disc(radius: float = LAMP_RADIUS_M, sides: int = 8) -> MeshArrays:
    """A flat polygonal lamp disc in its own frame, facing +x (toward the traffic it signals)."""
    mesh = Mesh()
    n = np.array([1.0, 0.0, 0.0])
    rim = [np.array([0.0, radius * math.cos(2 * math.pi * k / sides), radius * math.sin(2 * math.pi * k / sides)])
           for k in range(sides)]
    for k in range(1, sides - 1):
        mesh.tri(rim[0], rim[k], rim[k + 1], n)
    return mesh.arrays()
