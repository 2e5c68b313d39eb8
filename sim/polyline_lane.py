"""A lane along a sampled centre line whose tangent headings are known at the samples.

Why: a sheared circle (a skewed town's junction turns and corner bends, ``sim.town_skew``) is no
circle, and no closed form gives its arc length. Sampling it every metre is exact enough for
driving, but a plain polyline's heading jumps at every sample and is off by half a segment's turn
at its ends, where it must join the straight roads smoothly. This lane interpolates the exact
tangent headings between samples, so its heading is continuous and exact at both ends, and it
projects points onto the segments in one vectorised pass (highway-env's ``PolyLaneFixedWidth``
re-samples the curve and takes headings from segment chords).
"""

from __future__ import annotations

import bisect
import math

import numba as nb
import numpy as np
from highway_env.road.lane import AbstractLane, LineType


class PolylineLane(AbstractLane):
    """Centre line through ``points`` (n x 2), with tangent ``headings`` (n) at them."""

    def __init__(self, points: np.ndarray, headings: np.ndarray, width: float) -> None:
        super().__init__()
        self.points = np.asarray(points, float)
        self.headings = np.unwrap(np.asarray(headings, float))
        if len(self.points) < 2 or len(self.headings) != len(self.points):
            raise ValueError("a polyline lane needs two or more points, each with a heading")
        self.width = width
        self.line_types = [LineType.NONE, LineType.NONE]
        self.forbidden = False
        self.speed_limit = 20.0
        self.priority = 0
        self._d = np.diff(self.points, axis=0)
        self._len = np.hypot(self._d[:, 0], self._d[:, 1])
        self._s = np.concatenate([[0.0], np.cumsum(self._len)])
        self._n = np.stack([-self._d[:, 1], self._d[:, 0]], axis=1) / self._len[:, None]
        self.length = float(self._s[-1])
        # plain floats for the per-call arithmetic (NumPy's calls on single numbers cost more than the sums)
        self._s_list = self._s.tolist()
        self._pts = self.points.tolist()
        self._h = self.headings.tolist()

    def _at(self, longitudinal: float) -> tuple[int, float]:
        k = min(max(bisect.bisect_right(self._s_list, longitudinal) - 1, 0), len(self._s_list) - 2)
        return k, (longitudinal - self._s_list[k]) / (self._s_list[k + 1] - self._s_list[k])

    def _heading(self, k: int, t: float) -> float:
        t = min(max(t, 0.0), 1.0)
        return self._h[k] + t * (self._h[k + 1] - self._h[k])

    def heading_at(self, longitudinal: float) -> float:
        return self._heading(*self._at(longitudinal))

    def position(self, longitudinal: float, lateral: float) -> np.ndarray:
        k, t = self._at(longitudinal)
        h = self._heading(k, t)
        (x0, y0), (x1, y1) = self._pts[k], self._pts[k + 1]
        return np.array([x0 + t * (x1 - x0) - lateral * math.sin(h), y0 + t * (y1 - y0) + lateral * math.cos(h)])

    def width_at(self, longitudinal: float) -> float:
        return self.width

    def local_coordinates(self, position: np.ndarray) -> tuple[float, float]:
        return _project(float(position[0]), float(position[1]), self.points, self._d, self._len, self._s, self._n)

    def tightest_turn(self) -> tuple[float, float]:
        """The smallest radius between two samples (a segment's length over its turn) and where that segment
        starts; inf for a centre line that does not turn."""
        turns = np.abs(np.diff(self.headings))
        radii = np.where(turns > 1e-9, self._len / np.maximum(turns, 1e-12), np.inf)
        k = int(np.argmin(radii))
        return float(radii[k]), float(self._s[k])

    def to_config(self) -> dict:
        return {"class_path": "towndrive.sim.polyline_lane.PolylineLane",
                "config": {"points": self.points.tolist(), "headings": self.headings.tolist(), "width": self.width}}


@nb.njit(cache=True, nogil=True)
def _project(px: float, py: float, points: np.ndarray, d: np.ndarray, lengths: np.ndarray, s: np.ndarray,
             normals: np.ndarray) -> tuple[float, float]:
    """(s, lateral) of a point on the nearest segment (the first of equals); beyond the first or the last
    segment's end, along that segment's line."""
    best, best_k, best_t = np.inf, 0, 0.0
    last = lengths.shape[0] - 1
    for k in range(lengths.shape[0]):
        rx, ry = px - points[k, 0], py - points[k, 1]
        raw = (rx * d[k, 0] + ry * d[k, 1]) / (lengths[k] * lengths[k])
        t = min(max(raw, 0.0), 1.0)
        ox, oy = rx - t * d[k, 0], ry - t * d[k, 1]
        dist = ox * ox + oy * oy
        if dist < best:
            best, best_k = dist, k
            best_t = raw if (k == 0 and raw < 0.0) or (k == last and raw > 1.0) else t
    k, t = best_k, best_t
    rx, ry = px - points[k, 0] - t * d[k, 0], py - points[k, 1] - t * d[k, 1]
    return s[k] + t * lengths[k], rx * normals[k, 0] + ry * normals[k, 1]
