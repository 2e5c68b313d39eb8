"""Road signs as meshes: a post and a plate of a few flat coloured parts, in the sign's own frame.

Why a module of its own: each sign is a body of its own in the renderer, so that its pixels carry the
sign's class and id in the segmentation (as a traffic light's do), and TinyRenderer paints one colour per
link, so each colour of a plate (border, field, legend, back) is a link. The parts are built here once per
kind, size and value and shared by every sign alike.

The frame: origin at the post's foot on the road plane, z up, the plate in the y-z plane with its face
looking along +x (the body is turned so that +x looks at the traffic that reads the sign; +y is then that
traffic's right). TinyRenderer culls back faces, so the plate's back is a part of its own facing -x, in the
post's grey. A border is a ring round the field, not a bigger shape behind it, so no two parts share a plane
(no z-fighting); the legend (the limit's digits, STOP) floats a little in front of the field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from towndrive.sim.objects import SemanticClass
from towndrive.sim.scene_meshes import Mesh, MeshArrays

POST_HALF_M = 0.035  # a square post, 7 cm
POST_RGB = (0.55, 0.56, 0.58)  # galvanised steel
BACK_RGB = (0.62, 0.63, 0.64)
SIGN_RED = (0.78, 0.06, 0.07)
SIGN_WHITE = (0.95, 0.95, 0.93)
SIGN_BLACK = (0.05, 0.05, 0.06)
BACK_X = POST_HALF_M + 0.005  # the plate's back, just in front of the post
FACE_X = BACK_X + 0.015  # the border and field
LEGEND_X = FACE_X + 0.012  # digits and letters

SIGN_CLASS = {0: SemanticClass.STOP_SIGN, 1: SemanticClass.YIELD_SIGN, 2: SemanticClass.SPEED_LIMIT_SIGN}  # SignKind


@dataclass(frozen=True)
class SignPart:
    """One link of a sign's body: its colour and triangles (sign frame)."""

    name: str
    rgb: tuple[float, float, float]
    mesh: MeshArrays


# Seven segments (a-g) plus a centre stroke (i), as (u0, v0, u1, v1) in a unit cell (u right, v up).
_SEGMENTS = {"a": (0, 1, 1, 1), "b": (1, 0.5, 1, 1), "c": (1, 0, 1, 0.5), "d": (0, 0, 1, 0), "e": (0, 0, 0, 0.5),
             "f": (0, 0.5, 0, 1), "g": (0, 0.5, 1, 0.5), "i": (0.5, 0, 0.5, 1)}
GLYPHS = {"0": "abcdef", "1": "bc", "2": "abged", "3": "abgcd", "4": "fgbc", "5": "afgcd", "6": "afgedc", "7": "abc",
          "8": "abcdefg", "9": "abcdfg", "S": "afgcd", "T": "ai", "O": "abcdef", "P": "abfge"}


def _face(mesh: Mesh, poly: list[tuple[float, float]], x: float, normal_x: float) -> None:
    """A convex polygon of plate coordinates (u right as the reader sees it, v up) as a fan at depth x."""
    pts = [np.array([x, u, v]) for u, v in poly]
    n = np.array([normal_x, 0.0, 0.0])
    for k in range(1, len(pts) - 1):
        mesh.tri(pts[0], pts[k], pts[k + 1], n)


def _ring(mesh: Mesh, outer: list[tuple[float, float]], inner: list[tuple[float, float]], x: float) -> None:
    """The band between two polygons of as many corners (inner inside outer), facing +x."""
    for k in range(len(outer)):
        j = (k + 1) % len(outer)
        _face(mesh, [outer[k], outer[j], inner[j], inner[k]], x, 1.0)


def _regular(n: int, radius: float, centre: tuple[float, float], phase: float) -> list[tuple[float, float]]:
    return [(centre[0] + radius * math.cos(phase + 2 * math.pi * k / n),
             centre[1] + radius * math.sin(phase + 2 * math.pi * k / n)) for k in range(n)]


def _text(mesh: Mesh, text: str, centre: tuple[float, float], height: float, width: float, stroke: float,
          gap: float) -> None:
    """Glyphs of segment strokes, centred on a point of the plate, in front of the field."""
    total = len(text) * width + (len(text) - 1) * gap
    u0 = centre[0] - total / 2
    v0 = centre[1] - height / 2
    h = stroke / 2
    for k, ch in enumerate(text):
        left = u0 + k * (width + gap)
        for seg in GLYPHS[ch]:
            a0, b0, a1, b1 = _SEGMENTS[seg]
            # the stroke's centre line, inset by half a stroke so the glyph keeps its box
            p0 = (left + h + a0 * (width - stroke), v0 + h + b0 * (height - stroke))
            p1 = (left + h + a1 * (width - stroke), v0 + h + b1 * (height - stroke))
            _face(mesh, [(min(p0[0], p1[0]) - h, min(p0[1], p1[1]) - h), (max(p0[0], p1[0]) + h, min(p0[1], p1[1]) - h),
                         (max(p0[0], p1[0]) + h, max(p0[1], p1[1]) + h), (min(p0[0], p1[0]) - h, max(p0[1], p1[1]) + h)],
                  LEGEND_X, 1.0)


@lru_cache(maxsize=64)
def sign_parts(kind: int, plate_size_m: float, plate_height_m: float, value_kmh: int = 0) -> tuple[SignPart, ...]:
    """The post and the plate's parts of a sign (``SignKind``): post first, then back, border, field, legend.

    Stop: a red octagon in a white border with STOP in white; yield: a white triangle, point down, in a red
    border; speed limit: a white disc in a red ring with the limit in black digits. ``plate_size_m`` is the
    plate's width, ``plate_height_m`` the height of its centre above the road."""
    s, zc = plate_size_m, plate_height_m
    c = (0.0, zc)
    post = Mesh()
    top = zc + 0.15 * s
    post.box(np.array([0.0, 0.0, top / 2]), np.array([POST_HALF_M, POST_HALF_M, top / 2]))
    back, border, field, legend = Mesh(), Mesh(), Mesh(), Mesh()
    if kind == 0:  # stop: octagon with flat top, width s across the flats
        r_out = s / 2 / math.cos(math.pi / 8)
        r_in = r_out * (1 - 0.07)
        outer = _regular(8, r_out, c, math.pi / 8)
        inner = _regular(8, r_in, c, math.pi / 8)
        _face(back, outer, BACK_X, -1.0)
        _ring(border, outer, inner, FACE_X)
        _face(field, inner, FACE_X, 1.0)
        _text(legend, "STOP", c, 0.26 * s, 0.15 * s, 0.05 * s, 0.035 * s)
        colours = (SIGN_WHITE, SIGN_RED, SIGN_WHITE)
    elif kind == 1:  # yield: equilateral triangle, side s, point down
        r_out = s / math.sqrt(3)
        band = 0.13 * s
        outer = _regular(3, r_out, c, -math.pi / 2)
        inner = _regular(3, r_out - 2 * band, c, -math.pi / 2)
        _face(back, outer, BACK_X, -1.0)
        _ring(border, outer, inner, FACE_X)
        _face(field, inner, FACE_X, 1.0)
        colours = (SIGN_RED, SIGN_WHITE, SIGN_WHITE)
    else:  # speed limit: disc of diameter s
        outer = _regular(20, s / 2, c, 0.0)
        inner = _regular(20, s / 2 * (1 - 0.24), c, 0.0)
        _face(back, outer, BACK_X, -1.0)
        _ring(border, outer, inner, FACE_X)
        _face(field, inner, FACE_X, 1.0)
        _text(legend, str(int(value_kmh)), c, 0.42 * s, 0.2 * s, 0.06 * s, 0.06 * s)
        colours = (SIGN_RED, SIGN_WHITE, SIGN_BLACK)
    parts = [SignPart("post", POST_RGB, post.arrays()), SignPart("back", BACK_RGB, back.arrays()),
             SignPart("border", colours[0], border.arrays()), SignPart("field", colours[1], field.arrays())]
    if legend.triangle_count:
        parts.append(SignPart("legend", colours[2], legend.arrays()))
    return tuple(parts)
