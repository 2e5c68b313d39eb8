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

import math

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

    def _at(self, longitudinal: float) -> tuple[int, float]:
        k = int(np.searchsorted(self._s, longitudinal, side="right")) - 1
        k = min(max(k, 0), len(self._len) - 1)
        return k, (longitudinal - self._s[k]) / self._len[k]

    def heading_at(self, longitudinal: float) -> float:
        k, t = self._at(longitudinal)
        t = min(max(t, 0.0), 1.0)
        return float(self.headings[k] + t * (self.headings[k + 1] - self.headings[k]))

    def position(self, longitudinal: float, lateral: float) -> np.ndarray:
        k, t = self._at(longitudinal)
        h = self.heading_at(longitudinal)
        return self.points[k] + t * self._d[k] + lateral * np.array([-math.sin(h), math.cos(h)])

    def width_at(self, longitudinal: float) -> float:
        return self.width

    def local_coordinates(self, position: np.ndarray) -> tuple[float, float]:
        rel = np.asarray(position, float)[:2] - self.points[:-1]
        raw = np.einsum("ij,ij->i", rel, self._d) / (self._len ** 2)
        t = np.clip(raw, 0.0, 1.0)
        off = rel - t[:, None] * self._d
        k = int(np.argmin(np.einsum("ij,ij->i", off, off)))
        tk = float(raw[k]) if (k == 0 and raw[k] < 0) or (k == len(self._len) - 1 and raw[k] > 1) else float(t[k])
        s = float(self._s[k] + tk * self._len[k])
        lat = float((rel[k] - tk * self._d[k]) @ self._n[k])
        return s, lat

    def to_config(self) -> dict:
        return {"class_path": "towndrive.sim.polyline_lane.PolylineLane",
                "config": {"points": self.points.tolist(), "headings": self.headings.tolist(), "width": self.width}}
