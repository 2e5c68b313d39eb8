"""Triangle meshes of the static town, grouped by (semantic class, colour), for the camera renderer.

TinyRenderer's cost grows with triangles and bodies, so the static scene is a handful of merged
meshes: one per semantic class and colour. This module also owns THE mapping from the 2D map
frame (x right, y down, heading = atan2(dy, dx)) to pybullet's z-up right-handed world frame:
``(x, y) -> (x, -y, z)`` and ``heading -> yaw = -heading``. Nothing else converts frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from sim.objects import SemanticClass
from sim.town import Town

# Heights of the layered ground (metres). The camera's near plane (0.5 m) keeps these apart.
Z_GROUND = -0.05
Z_ROAD = 0.0
Z_MARKING = 0.03
Z_SLAB = 0.15
Z_PARK = 0.17

FLOOR_HEIGHT_M = 3.2
WINDOW_BOTTOM_M = 0.9  # above each floor's base
WINDOW_TOP_M = 2.3
WINDOW_OFFSET_M = 0.08  # in front of the wall, to win the depth test
WINDOW_LIT_FRACTION = 0.35  # share of window bands that glow at night

POLE_HALF_M = 0.14
ARM_HALF_M = 0.09
HOUSING_HALF = (0.25, 0.25, 0.75)  # x (depth), y (width), z (height) of a light's housing
LAMP_RADIUS_M = 0.2
LAMP_SPACING_M = 0.46


def to_world(x: float | np.ndarray, y: float | np.ndarray, z: float | np.ndarray = 0.0) -> np.ndarray:
    """Map-frame point(s) to pybullet world coordinates: (x, y) -> (x, -y, z). The one place it happens."""
    x, y, z = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float), np.asarray(z, float))
    return np.stack([x, -y, z], axis=-1)


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

    def prism_sides(self, poly: np.ndarray, z0: float, z1: float) -> None:
        """Outward-facing vertical walls of a convex map-frame polygon between two heights."""
        pts = to_world(poly[:, 0], poly[:, 1], 0.0)
        centre = pts.mean(axis=0)
        for k in range(len(pts)):
            p, q = pts[k], pts[(k + 1) % len(pts)]
            if float(np.linalg.norm(q - p)) < 1e-6:
                continue
            n = np.array([q[1] - p[1], -(q[0] - p[0]), 0.0])
            if float(np.dot(n, (p + q) / 2 - centre)) < 0:
                n = -n
            dz0, dz1 = np.array([0, 0, z0]), np.array([0, 0, z1])
            self.quad(p + dz0, q + dz0, q + dz1, p + dz1, n)

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


@dataclass
class MeshGroup:
    """One static body: a merged mesh of one semantic class and one colour."""

    name: str
    semantic: SemanticClass
    rgba: tuple[float, float, float, float]
    mesh: Mesh
    emissive_at_night: tuple[float, float, float] | None = None  # lit windows


GRASS_RGB = (0.30, 0.42, 0.22)
PARK_RGB = (0.34, 0.52, 0.26)
ROAD_RGB = (0.24, 0.24, 0.26)
WHITE_RGB = (0.92, 0.92, 0.90)
YELLOW_RGB = (0.95, 0.75, 0.18)
SIDEWALK_RGB = (0.66, 0.65, 0.62)
KERB_RGB = (0.80, 0.79, 0.76)
GLASS_RGB = (0.14, 0.18, 0.25)
LIT_WINDOW_RGB = (1.0, 0.82, 0.5)
TRUNK_RGB = (0.36, 0.26, 0.17)
POLE_RGB = (0.22, 0.23, 0.24)


def _rgba(rgb: tuple[float, float, float]) -> tuple[float, float, float, float]:
    return (float(rgb[0]), float(rgb[1]), float(rgb[2]), 1.0)


def build_static_groups(town: Town, seed: int = 0) -> list[MeshGroup]:
    """All static scenery (no traffic-light housings or lamps) as merged per-colour meshes."""
    rng = np.random.default_rng(seed)
    groups: dict[str, MeshGroup] = {}

    def group(name: str, semantic: SemanticClass, rgb: tuple[float, float, float]) -> Mesh:
        if name not in groups:
            groups[name] = MeshGroup(name, semantic, _rgba(rgb), Mesh())
        return groups[name].mesh

    # Ground: one quad well past the far plane from any point of the town.
    xmin, ymin, xmax, ymax = town.extent
    m = 300.0
    group("ground", SemanticClass.GROUND, GRASS_RGB).polygon_top(
        np.array([[xmin - m, ymin - m], [xmax + m, ymin - m], [xmax + m, ymax + m], [xmin - m, ymax + m]]), Z_GROUND)
    road = group("road", SemanticClass.ROAD, ROAD_RGB)
    for poly in town.road_polygons:
        road.polygon_top(poly, Z_ROAD)
    marking_groups = {"dashed_white": ("white_lines", SemanticClass.LANE_MARKING, WHITE_RGB),
                      "solid_white": ("white_lines", SemanticClass.LANE_MARKING, WHITE_RGB),
                      "solid_yellow": ("yellow_lines", SemanticClass.LANE_MARKING, YELLOW_RGB),
                      "stop_line": ("stop_lines", SemanticClass.STOP_LINE, WHITE_RGB),
                      "crosswalk": ("crosswalks", SemanticClass.CROSSWALK, WHITE_RGB)}
    for kind, quads in town.markings.items():
        name, sem, rgb = marking_groups[kind]
        mesh = group(name, sem, rgb)
        for q in quads:
            mesh.polygon_top(q, Z_MARKING)
    top, kerb = group("sidewalk", SemanticClass.SIDEWALK, SIDEWALK_RGB), group("kerb", SemanticClass.SIDEWALK, KERB_RGB)
    for poly in town.slab_polygons:
        top.polygon_top(poly, Z_SLAB)
        kerb.prism_sides(poly, Z_ROAD - 0.02, Z_SLAB)
    park = group("park", SemanticClass.GROUND, PARK_RGB)
    for poly in town.grass_polygons:
        park.polygon_top(poly, Z_PARK)

    # Buildings: walls (and roof) in their palette colour, a dark glass band per floor per facade.
    for b in town.buildings:
        key = "building_" + "_".join(f"{c:.2f}" for c in b.color)
        walls = group(key, SemanticClass.BUILDING, b.color)
        walls.prism_sides(b.footprint, Z_SLAB - 0.05, b.height_m)
        walls.polygon_top(b.footprint, b.height_m)
        floors = int((b.height_m - 1.0) // FLOOR_HEIGHT_M)
        pts = to_world(b.footprint[:, 0], b.footprint[:, 1], 0.0)
        centre = pts.mean(axis=0)
        for k in range(len(pts)):
            p, q = pts[k], pts[(k + 1) % len(pts)]
            length = float(np.linalg.norm(q - p))
            if length < 4.0:
                continue
            along = (q - p) / length
            n = np.array([along[1], -along[0], 0.0])
            if float(np.dot(n, (p + q) / 2 - centre)) < 0:
                n = -n
            inset = min(1.2, 0.15 * length)
            a, c = p + along * inset + n * WINDOW_OFFSET_M, q - along * inset + n * WINDOW_OFFSET_M
            for f in range(floors):
                lit = rng.random() < WINDOW_LIT_FRACTION
                mesh = group("windows_lit" if lit else "windows", SemanticClass.BUILDING, GLASS_RGB)
                z0 = Z_SLAB + f * FLOOR_HEIGHT_M + WINDOW_BOTTOM_M
                z1 = Z_SLAB + f * FLOOR_HEIGHT_M + WINDOW_TOP_M
                mesh.quad(a + [0, 0, z0], c + [0, 0, z0], c + [0, 0, z1], a + [0, 0, z1], n)
    if "windows_lit" in groups:
        groups["windows_lit"].emissive_at_night = LIT_WINDOW_RGB

    # Trees: a square trunk and a six-sided bipyramid canopy, grouped by three shades of green.
    trunk = group("trunks", SemanticClass.VEGETATION, TRUNK_RGB)
    shades = [(0.17, 0.36, 0.14), (0.22, 0.44, 0.16), (0.28, 0.50, 0.18)]
    for t in town.trees:
        base = to_world(t.position[0], t.position[1], Z_SLAB)
        r = t.canopy_radius_m
        z_canopy = max(1.6, t.height_m - 2.0 * r)
        trunk.box(base + [0, 0, z_canopy / 2], np.array([Town.TRUNK_RADIUS_M, Town.TRUNK_RADIUS_M, z_canopy / 2]),
                  top=False)
        g = t.color[1]
        shade = 0 if g < 0.47 else (1 if g < 0.53 else 2)
        canopy = group(f"canopy_{shade}", SemanticClass.VEGETATION, shades[shade])
        mid = base + [0, 0, z_canopy + 0.9 * r]
        apex_up, apex_down = base + [0, 0, t.height_m], base + [0, 0, z_canopy]
        phase = float(rng.uniform(0, math.pi / 3))
        ring = [mid + r * np.array([math.cos(phase + k * math.pi / 3), math.sin(phase + k * math.pi / 3), 0.0])
                for k in range(6)]
        for k in range(6):
            p, q = ring[k], ring[(k + 1) % 6]
            out = (p + q) / 2 - mid
            canopy.tri(p, q, apex_up, out + np.array([0, 0, 0.6 * r]))
            canopy.tri(p, q, apex_down, out - np.array([0, 0, 0.6 * r]))

    # Light poles and mast arms (the housings and lamps are per-light bodies, see render.py).
    poles = group("poles", SemanticClass.POLE, POLE_RGB)
    top_z = Town.LIGHT_HEAD_HEIGHT_M + HOUSING_HALF[2] + 2 * ARM_HALF_M
    for ap in town.approaches:
        foot = to_world(ap.light_pole[0], ap.light_pole[1], Z_SLAB)
        poles.box(foot + [0, 0, (top_z - Z_SLAB) / 2], np.array([POLE_HALF_M, POLE_HALF_M, (top_z - Z_SLAB) / 2]))
        head = to_world(ap.light_head[0], ap.light_head[1], top_z - ARM_HALF_M)
        arm_foot = foot.copy()
        arm_foot[2] = head[2]
        span = head - arm_foot
        length = float(np.linalg.norm(span))
        if length > 1e-6:
            d = span / length
            end = head + d * 0.3
            centre = (arm_foot + end) / 2
            half = np.abs(end - arm_foot) / 2 + ARM_HALF_M
            half[2] = ARM_HALF_M
            poles.box(centre, half, top=True, bottom=True)
    return [g for g in groups.values() if g.mesh.triangle_count > 0]


def light_lamp_disc(radius: float = LAMP_RADIUS_M, sides: int = 8) -> tuple[list[list[float]], list[int], list[list[float]]]:
    """A flat polygonal lamp disc in its own frame, facing +x (toward the traffic it signals)."""
    mesh = Mesh()
    n = np.array([1.0, 0.0, 0.0])
    rim = [np.array([0.0, radius * math.cos(2 * math.pi * k / sides), radius * math.sin(2 * math.pi * k / sides)])
           for k in range(sides)]
    for k in range(1, sides - 1):
        mesh.tri(rim[0], rim[k], rim[k + 1], n)
    return mesh.arrays()
