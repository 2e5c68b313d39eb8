"""A turn lane that is a straight lead-in, a circular arc and a straight lead-out.

Why: a junction turn is a quarter circle only when its start and end lie at the same distance from
the corner where the two lane lines meet, and then its radius grows with the stop lines' setback: a
junction whose stop lines stand well back would have right turns that sweep over the kerb corner.
Real turns follow the kerb: straight on past the stop line, round the corner on a radius set by the
kerb, straight out. A fillet (an arc of a chosen radius tangent to both lane lines, joined to them by
straight pieces) is that path; it connects any start pose to any end pose whose lines cross ahead,
also where a two-lane street meets a one-lane one. It keeps highway-env's four-method lane contract,
so vehicles drive it unchanged.
"""

from __future__ import annotations

import math

import numpy as np
from highway_env.road.lane import AbstractLane, CircularLane, LineType, StraightLane

from towndrive.sim.geometry import wrap_to_pi

_NONE = (LineType.NONE, LineType.NONE)


class FilletLane(AbstractLane):
    """From ``start`` heading ``heading_in`` to ``end`` heading ``heading_out``, turning less than 180 degrees,
    on an arc of ``radius_m`` (None, or more than fits: the largest arc that fits)."""

    def __init__(self, start: np.ndarray, heading_in: float, end: np.ndarray, heading_out: float, width: float,
                 radius_m: float | None = None) -> None:
        super().__init__()
        self.width = width
        self.design_radius_m = radius_m  # as asked (None: the largest that fits)
        self.line_types = list(_NONE)
        self.forbidden = False
        self.speed_limit = 20.0
        self.priority = 0
        d0 = np.array([math.cos(heading_in), math.sin(heading_in)])
        d1 = np.array([math.cos(heading_out), math.sin(heading_out)])
        turn = wrap_to_pi(heading_out - heading_in)
        if not 1e-6 < abs(turn) < math.pi - 1e-6:
            raise ValueError("a fillet lane turns by more than 0 and less than 180 degrees")
        # Where the two lane lines cross: start + a * d0 = end - b * d1.
        a, b = np.linalg.solve(np.column_stack([d0, d1]), np.asarray(end, float) - np.asarray(start, float))
        if a <= 0 or b <= 0:
            raise ValueError("a fillet lane needs its end ahead of its start, on a line crossing its own ahead")
        half_tan = math.tan(abs(turn) / 2)
        tangent = min(a, b)  # the arc touches both lines at this distance from where they cross
        if radius_m is not None:
            tangent = min(tangent, radius_m * half_tan)
        radius = tangent / half_tan
        corner = np.asarray(start, float) + a * d0
        arc_start, arc_end = corner - tangent * d0, corner + tangent * d1
        normal = np.array([-d0[1], d0[0]]) * (1.0 if turn > 0 else -1.0)  # towards the arc's centre
        centre = arc_start + radius * normal
        phase0 = math.atan2(arc_start[1] - centre[1], arc_start[0] - centre[0])
        self.pieces: list[AbstractLane] = []
        if a - tangent > 1e-6:
            self.pieces.append(StraightLane(np.asarray(start, float), arc_start, width=width, line_types=_NONE))
        self.pieces.append(CircularLane(centre, radius, phase0, phase0 + turn, clockwise=turn > 0, width=width,
                                        line_types=_NONE))
        if b - tangent > 1e-6:
            self.pieces.append(StraightLane(arc_end, np.asarray(end, float), width=width, line_types=_NONE))
        self.offsets = np.cumsum([0.0] + [p.length for p in self.pieces])
        self.length = float(self.offsets[-1])
        self.start = np.asarray(start, float)
        self.end = np.asarray(end, float)

    def tightest_turn(self) -> tuple[float, float]:
        """The arc's radius and where it starts along the lane."""
        k = next(k for k, p in enumerate(self.pieces) if isinstance(p, CircularLane))
        return float(self.pieces[k].radius), float(self.offsets[k])

    def _piece(self, longitudinal: float) -> tuple[AbstractLane, float]:
        k = int(np.searchsorted(self.offsets, longitudinal, side="right")) - 1
        k = min(max(k, 0), len(self.pieces) - 1)
        return self.pieces[k], float(longitudinal - self.offsets[k])

    def position(self, longitudinal: float, lateral: float) -> np.ndarray:
        piece, s = self._piece(longitudinal)
        return piece.position(s, lateral)

    def heading_at(self, longitudinal: float) -> float:
        piece, s = self._piece(longitudinal)
        return piece.heading_at(s)

    def width_at(self, longitudinal: float) -> float:
        return self.width

    def local_coordinates(self, position: np.ndarray) -> tuple[float, float]:
        """The piece whose span holds the point's projection with the smallest lateral offset; before the
        first or past the last piece, that end piece's coordinates (which extend its line)."""
        best: tuple[float, float, float] | None = None
        for k, piece in enumerate(self.pieces):
            s, lat = piece.local_coordinates(position)
            inside = -1e-9 <= s <= piece.length + 1e-9
            first, last = k == 0, k == len(self.pieces) - 1
            if inside or (first and s < 0) or (last and s > piece.length):
                cost = abs(lat) if inside else abs(lat) + (-s if s < 0 else s - piece.length)
                if best is None or cost < best[0]:
                    best = (cost, float(self.offsets[k] + s), float(lat))
        if best is None:  # inside no span (outside a convex corner): the nearest end of a piece
            ends = [(float(np.linalg.norm(position - p.position(s, 0.0))), k, s)
                    for k, p in enumerate(self.pieces) for s in (0.0, p.length)]
            _, k, s = min(ends)
            s_local, lat = self.pieces[k].local_coordinates(position)
            return float(self.offsets[k] + s), float(lat)
        return best[1], best[2]

    def to_config(self) -> dict:
        return {"class_path": "towndrive.sim.fillet_lane.FilletLane",
                "config": {"start": self.start.tolist(), "heading_in": self.heading_at(0.0),
                           "end": self.end.tolist(), "heading_out": self.heading_at(self.length), "width": self.width}}
