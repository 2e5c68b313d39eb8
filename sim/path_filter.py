"""A cheap, conservative test of which agents could lie on a path of lanes, before the exact one.

``sim.traffic.path_gap`` asks highway-env's ``lane.local_coordinates`` for every nearby agent and
every lane of the path (a few microseconds of Python each), yet most nearby agents are nowhere near
the path. This module rules those out in one compiled loop over flat lane parameters. It only ever
drops an agent that the exact test would reject anyway: the bounds it checks are the exact test's
bounds widened by the agent's reach (bumpers, a walking pedestrian's look-ahead) and a margin far
larger than any rounding difference. So which agents reach the exact test changes, never the answer.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable

import numba as nb
import numpy as np
from highway_env.road.lane import AbstractLane, CircularLane, StraightLane

KIND_STRAIGHT, KIND_CIRCULAR, KIND_OTHER = 0.0, 1.0, 2.0
ROW_SIZE = 7  # kind, x, y (start or centre), ux, uy (direction), length, radius
MARGIN_M = 0.5  # widening of every bound: rounding is at most a few nanometres here
BUMPER_SWING_M = 0.3  # a vehicle's bumpers count in a path search when they swing this far out of its centre's line

_ROWS: weakref.WeakKeyDictionary[AbstractLane, np.ndarray] = weakref.WeakKeyDictionary()


def lane_row(lane: AbstractLane) -> np.ndarray:
    """A lane's flat parameters (built once per lane: lanes never change after the town is made)."""
    row = _ROWS.get(lane)
    if row is None:
        if type(lane) is StraightLane:
            row = np.array([KIND_STRAIGHT, lane.start[0], lane.start[1], lane.direction[0], lane.direction[1],
                            lane.length, 0.0])
        elif type(lane) is CircularLane:
            row = np.array([KIND_CIRCULAR, lane.center[0], lane.center[1], 0.0, 0.0, lane.length, lane.radius])
        else:  # no shortcut known: every agent goes on to the exact test
            row = np.array([KIND_OTHER, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
        _ROWS[lane] = row
    return row


_PATHS: dict[tuple[int, ...], tuple[tuple[weakref.ref, ...], np.ndarray]] = {}
PATHS_MAX = 4096  # a guard only: entries go with their lanes, and the towns in memory hold a few hundred paths


def path_rows(lanes: list[AbstractLane]) -> np.ndarray:
    """Flat parameters of the lanes of a path, one row each. NPCs ask for the same few paths step
    after step, so they are kept, for as long as all their lanes live: the entry holds each lane weakly
    and is dropped when one of them goes (before its id can be reused by another lane). Why weakly: the
    cache held the lanes themselves, so a run over many towns kept the lanes of every town it visited
    (about 50 KB a town, up to 4096 paths, bench/bench_memory_soak.py)."""
    key = tuple(map(id, lanes))
    hit = _PATHS.get(key)
    if hit is None:
        if len(_PATHS) >= PATHS_MAX:
            _PATHS.clear()
        forget = _forget_path(key)
        hit = (tuple(weakref.ref(lane, forget) for lane in lanes), np.stack([lane_row(lane) for lane in lanes]))
        _PATHS[key] = hit
    return hit[1]


def _forget_path(key: tuple[int, ...], paths: dict = _PATHS) -> Callable[[weakref.ref], None]:
    """The weak references' callback: drop the path when one of its lanes is collected (the cache is bound
    here, not looked up as a global, which may be gone when lanes die at interpreter exit)."""
    def forget(_: weakref.ref) -> None:
        paths.pop(key, None)
    return forget


@nb.njit(cache=True, nogil=True)
def _lateral_reach(k: int, headings: np.ndarray, speeds: np.ndarray, half_lengths: np.ndarray,
                   is_pedestrian: np.ndarray, on_crossing: np.ndarray, path_heading: float, tolerances: np.ndarray,
                   lookahead_s: float) -> tuple[float, float]:
    """(lateral tolerance, reach) of agent ``k`` in ``sim.traffic.path_gap``: the tolerance it is held to
    and how far its extra points (bumpers, a walking pedestrian's place ahead) lie from its centre.
    ``tolerances`` = vehicle, walking pedestrian, standing pedestrian. The choices repeat path_gap's
    comparisons on the same numbers, except the bumpers' swing, which is recomputed and so is given bumpers
    whenever it is within a micrometre of the threshold."""
    if is_pedestrian[k]:
        walking = speeds[k] > 0.1
        tol = tolerances[1] if walking or on_crossing[k] else tolerances[2]
        return tol, lookahead_s * speeds[k] if walking else 0.0
    swing = half_lengths[k] * abs(np.sin(headings[k] - path_heading))
    return tolerances[0], half_lengths[k] if swing > BUMPER_SWING_M - 1e-6 else 0.0


@nb.njit(cache=True, nogil=True)
def may_touch_path(positions: np.ndarray, headings: np.ndarray, speeds: np.ndarray, half_lengths: np.ndarray,
                   is_pedestrian: np.ndarray, on_crossing: np.ndarray, candidates: np.ndarray, rows: np.ndarray,
                   path_heading: float, tolerances: np.ndarray, lookahead_s: float) -> np.ndarray:
    """For each candidate agent, whether any point the exact test tries (centre, bumpers, a walking
    pedestrian's place ``lookahead_s`` ahead) could be within its lateral tolerance of a path lane,
    between the lane's ends widened by the agent's half length. False means the exact test would skip
    the agent."""
    out = np.zeros(len(candidates), dtype=np.bool_)
    for i in range(len(candidates)):
        k = candidates[i]
        tol, reach = _lateral_reach(k, headings, speeds, half_lengths, is_pedestrian, on_crossing, path_heading,
                                    tolerances, lookahead_s)
        lat_max = tol + reach + MARGIN_M
        s_pad = half_lengths[k] + reach + MARGIN_M
        px, py = positions[k, 0], positions[k, 1]
        for j in range(rows.shape[0]):
            if _row_may_hold(px, py, rows, j, lat_max, s_pad):
                out[i] = True
                break
    return out


@nb.njit(cache=True, nogil=True)
def _row_may_hold(px: float, py: float, rows: np.ndarray, j: int, lat_max: float, s_pad: float) -> bool:
    """Whether the point may lie within ``lat_max`` of lane row ``j``, between its ends widened by ``s_pad``
    (a lane kind without a cheap bound always may)."""
    kind = rows[j, 0]
    dx, dy = px - rows[j, 1], py - rows[j, 2]
    if kind == KIND_STRAIGHT:
        ux, uy = rows[j, 3], rows[j, 4]
        s = dx * ux + dy * uy
        lat = dy * ux - dx * uy
        return abs(lat) <= lat_max and -s_pad <= s <= rows[j, 5] + s_pad
    if kind == KIND_CIRCULAR:
        return abs(np.sqrt(dx * dx + dy * dy) - rows[j, 6]) <= lat_max
    return True


@nb.njit(cache=True, nogil=True)
def path_candidates(positions: np.ndarray, ids: np.ndarray, skip_id: int, ox: float, oy: float, radius2: float,
                    headings: np.ndarray, speeds: np.ndarray, half_lengths: np.ndarray, is_pedestrian: np.ndarray,
                    on_crossing: np.ndarray, rows: np.ndarray, path_heading: float, tolerances: np.ndarray,
                    lookahead_s: float) -> np.ndarray:
    """Indices (ascending) of the agents other than ``skip_id`` whose squared distance from the origin
    is below ``radius2`` (the same subtraction, squares and sum as NumPy's, so the same agents) and
    that ``may_touch_path``."""
    near = np.empty(len(ids), dtype=np.int64)
    n = 0
    for k in range(len(ids)):
        dx = positions[k, 0] - ox
        dy = positions[k, 1] - oy
        if dx * dx + dy * dy < radius2 and ids[k] != skip_id:
            near[n] = k
            n += 1
    near = near[:n]
    return near[may_touch_path(positions, headings, speeds, half_lengths, is_pedestrian, on_crossing, near, rows,
                               path_heading, tolerances, lookahead_s)]


@nb.njit(cache=True, nogil=True)
def lanes_may_hold(px: float, py: float, rows: np.ndarray, lateral_m: float, s_pad: float) -> np.ndarray:
    """For each lane row, whether the point could be within ``lateral_m`` of it, between its ends
    widened by ``s_pad`` (bounds widened by ``MARGIN_M``). False means the exact test would reject it."""
    out = np.zeros(rows.shape[0], dtype=np.bool_)
    for j in range(rows.shape[0]):
        out[j] = _row_may_hold(px, py, rows, j, lateral_m + MARGIN_M, s_pad + MARGIN_M)
    return out


@nb.njit(cache=True, nogil=True)
def clearly_nearest_lane(px: float, py: float, rows: np.ndarray) -> int:
    """The lane row whose centre line the point is nearest to, by |lateral| as ``lane.local_coordinates``
    gives it (straight: distance across the line; circular: distance from the arc's radius), if every other
    lane is farther by more than twice ``MARGIN_M``; else -1 (too close to call, or a lane kind without a cheap
    formula). The formulas here differ from highway-env's by rounding only, far below the margin, so a row
    returned here is the one the exact comparison picks."""
    best, best_lat, second = -1, np.inf, np.inf
    for j in range(rows.shape[0]):
        dx, dy = px - rows[j, 1], py - rows[j, 2]
        if rows[j, 0] == KIND_STRAIGHT:
            lat = abs(dy * rows[j, 3] - dx * rows[j, 4])
        elif rows[j, 0] == KIND_CIRCULAR:
            lat = abs(np.sqrt(dx * dx + dy * dy) - rows[j, 6])
        else:
            return -1
        if lat < best_lat:
            best, best_lat, second = j, lat, best_lat
        elif lat < second:
            second = lat
    return best if best_lat + 2 * MARGIN_M < second else -1


@nb.njit(cache=True, nogil=True)
def points_within(points: np.ndarray, cx: float, cy: float, radius2: float) -> np.ndarray:
    """For each point, whether its squared distance from (cx, cy) is below ``radius2``: the NumPy expression
    ``d = points - (cx, cy); d[:, 0] ** 2 + d[:, 1] ** 2 < radius2`` element by element (the same subtraction,
    squares and sum), in one compiled call instead of half a dozen NumPy calls on a few dozen numbers."""
    out = np.empty(points.shape[0], dtype=np.bool_)
    for i in range(points.shape[0]):
        dx, dy = points[i, 0] - cx, points[i, 1] - cy
        out[i] = dx * dx + dy * dy < radius2
    return out


@nb.njit(cache=True, nogil=True)
def zone_holds(points: np.ndarray, cx: float, cy: float, ux: float, uy: float, vx: float, vy: float, half_u: float,
               half_v: float) -> int:
    """Whether any point lies in the rectangle centred on (cx, cy) with half sizes ``half_u`` along the unit
    vector (ux, uy) and ``half_v`` along (vx, vy): 1 surely (a point inside by ``MARGIN_M``), 0 surely not
    (every point outside by ``MARGIN_M``), -1 when it is too close to call and the exact test must decide."""
    unsure = False
    for i in range(points.shape[0]):
        dx, dy = points[i, 0] - cx, points[i, 1] - cy
        a, b = abs(dx * ux + dy * uy), abs(dx * vx + dy * vy)
        if a <= half_u - MARGIN_M and b <= half_v - MARGIN_M:
            return 1
        if a <= half_u + MARGIN_M and b <= half_v + MARGIN_M:
            unsure = True
    return -1 if unsure else 0
