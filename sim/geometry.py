"""Small 2D helpers in highway-env's road frame (x right, y down, heading = atan2(dy, dx)).

In this frame the right-hand side of a heading h is (-sin h, cos h): with y pointing down on a
map, that is the driver's right. Right-hand traffic keeps each direction's lanes on its right.
"""

from __future__ import annotations

import math

import numpy as np

Vec = np.ndarray


def right_of(direction: Vec) -> Vec:
    """The driver's right of a direction vector (see module docstring)."""
    return np.array([-direction[1], direction[0]])


def wrap_to_pi(angle: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


def rect_corners(center: Vec, heading: float, length: float, width: float) -> Vec:
    """Corners (4x2) of an oriented rectangle, front-left first, clockwise on the map."""
    c, s = math.cos(heading), math.sin(heading)
    # The NumPy expression center + fwd - side (and so on) per coordinate, in plain floats (same
    # operations, same order; four small arrays cost more in calls than in arithmetic).
    fx, fy = c * (length / 2), s * (length / 2)
    sx, sy = -s * (width / 2), c * (width / 2)
    x, y = float(center[0]), float(center[1])
    return np.array([[x + fx - sx, y + fy - sy], [x + fx + sx, y + fy + sy],
                     [x - fx + sx, y - fy + sy], [x - fx - sx, y - fy - sy]])


def polygons_intersect(a: Vec, b: Vec) -> bool:
    """Separating-axis test for two convex polygons given as (N, 2) arrays."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.stack([-edges[:, 1], edges[:, 0]], axis=1)
        pa = a @ normals.T
        pb = b @ normals.T
        if np.any(pa.max(axis=0) < pb.min(axis=0)) or np.any(pb.max(axis=0) < pa.min(axis=0)):
            return False
    return True


def circle_polygon_intersect(center: Vec, radius: float, poly: Vec) -> bool:
    """Whether a circle touches a convex polygon (counter- or clockwise)."""
    n = len(poly)
    inside = True
    sign = 0.0
    best = math.inf
    for i in range(n):
        p, q = poly[i], poly[(i + 1) % n]
        e = q - p
        t = min(1.0, max(0.0, float(np.dot(center - p, e)) / max(float(np.dot(e, e)), 1e-12)))
        gap = center - (p + t * e)
        best = min(best, math.hypot(gap[0], gap[1]))
        cross = e[0] * (center[1] - p[1]) - e[1] * (center[0] - p[0])
        if sign == 0.0:
            sign = cross
        elif cross * sign < 0:
            inside = False
    return inside or best <= radius
