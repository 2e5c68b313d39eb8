"""Steering through a junction, where there are no lines to follow.

Going straight, the car holds the approach lane's heading and its place across it (``Odometry``). Turning, it
pursues the road design's turn arc (a quarter circle from the stop bar's far edge into the same lane of the road
turned into) from the rear axle, as the autopilot follows lanes. The arc is placed by the stop bar tracked by the
controller (``StopLineTrack``) and the approach lane measured before it. Road-design numbers are ``sim.spec``'s
priors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from towndrive.agent.decision.odometry import Odometry
from towndrive.agent.decision.stop_line_track import StopLineTrack
from towndrive.agent.perception.stop_line import StopLine
from towndrive.sim.spec import ROAD, VEHICLE, RoadDesign


@lru_cache(maxsize=16)
def turn_path(command: int, setback_m: float, lane_offset_m: float, bar_depth_m: float = ROAD.stop_bar_depth_m,
              step_m: float = 0.2) -> tuple[np.ndarray, float]:
    """A junction turn in the approach frame (x along the approach lane from its stop bar's near edge, y to the
    right): 30 m of approach, the design's quarter circle from the bar's far edge (``bar_depth_m`` on) into the same lane of
    the road turned into, then 30 m of that road; and the path length at which the arc ends. The lane's centre
    is ``lane_offset_m`` right of the road's centre line, so a right turn's radius is ``setback - offset`` and a
    left turn's ``setback + offset`` (``sim/town.py``, junction connectors)."""
    right = command == 2
    radius = setback_m - lane_offset_m if right else setback_m + lane_offset_m
    side = 1.0 if right else -1.0
    x0 = bar_depth_m
    before = np.arange(x0 - 30.0, x0, step_m)
    approach = np.stack([before, np.zeros(len(before))], axis=1)
    theta = np.arange(0.0, math.pi / 2, step_m / radius)
    arc = np.stack([x0 + radius * np.sin(theta), side * (radius - radius * np.cos(theta))], axis=1)
    end = np.array([x0 + radius, side * radius])
    along = np.arange(0.0, 30.0, step_m)
    exit_ = np.stack([np.full(len(along), end[0]), end[1] + side * along], axis=1)
    path = np.concatenate([approach, arc, exit_])
    path.setflags(write=False)
    return path, (len(approach) + len(arc)) * step_m


@dataclass(frozen=True)
class JunctionRules:
    junction_hold_m: float = 20.0  # going straight, this far past the stop line the car holds the approach lane
    hold_heading_gain: float = 1.5  # steer per radian of heading error (about a 1 s time constant at 5 m/s)
    hold_offset_gain: float = 0.3  # steer per metre of dead-reckoned offset from the approach lane's centre
    hold_max_steer: float = 0.3
    turn_guidance: bool = True  # commanded turns inside a junction follow the turn arc
    turn_lookahead_m: float = 3.5  # pure pursuit of the arc from the rear axle: lookahead = this + s x speed
    turn_lookahead_s: float = 0.4
    turn_bar_seen_m: float = 12.0  # a turn is placed only by a stop bar seen this near


class JunctionGuidance:
    """The straight hold and the turn arc (module docstring); ``placed`` once a stop bar ahead is located."""

    def __init__(self, rules: JunctionRules, line: StopLineTrack, odometry: Odometry, camera_to_centre_m: float,
                 road: RoadDesign = ROAD) -> None:
        self.rules = rules
        self.road = road  # lane width, stop-bar setback and depth: where the turn arc runs
        self.line = line
        self.odo = odometry
        self.camera_to_centre_m = camera_to_centre_m  # the camera's mount ahead of the car's centre
        self.reset()

    def reset(self) -> None:
        # the stop bar ahead (x, y, road yaw) and the command of the turn once it has begun (0: not yet)
        self.junction: tuple[float, float, float, int] | None = None

    @property
    def placed(self) -> bool:
        return self.junction is not None

    def hold(self, command: int) -> float | None:
        """Going straight through a junction, the steer that keeps the approach lane's heading and our place
        across it; None when this does not apply."""
        line, cfg, odo = self.line, self.rules, self.odo
        inside = line.ignore_light_m > line.config.junction_ignore_m - cfg.junction_hold_m
        if command != 3 or not inside or odo.road_yaw is None:
            return None
        steer = -(cfg.hold_heading_gain * (odo.yaw - odo.road_yaw) + cfg.hold_offset_gain * odo.road_offset)
        return float(np.clip(steer, -cfg.hold_max_steer, cfg.hold_max_steer))

    def note(self, stop: StopLine | None) -> None:
        """Where the stop bar ahead lies in the odometry frame (the approach lane's centre at the bar's near edge),
        from the tracked bar and the approach lane measured before it. Only a bar seen within ``turn_bar_seen_m``
        of the camera places a turn (farther readings are a metre or so off)."""
        line, odo = self.line, self.odo
        if line.ignore_light_m > 0 or not line.stop_line_measured or line.stop_line is None or odo.road_yaw is None:
            return
        if self.junction is None and (stop is None or stop.distance_m > self.rules.turn_bar_seen_m):
            return
        ahead = line.stop_line + line.config.camera_to_front_m + self.camera_to_centre_m  # car centre to the bar
        u = np.array([math.cos(odo.road_yaw), math.sin(odo.road_yaw)])
        right = np.array([-u[1], u[0]])
        bar = odo.pos - odo.road_offset * right + ahead * u
        self.junction = (float(bar[0]), float(bar[1]), odo.road_yaw, 0)

    def turn_steer(self, command: int, speed: float) -> float | None:
        """Turning at a junction, the steer that pursues the turn arc from our lane to the same lane of the road we
        turn into; None when this does not apply."""
        cfg, odo = self.rules, self.odo
        if self.junction is None or not cfg.turn_guidance:
            return None
        bx, by, road_yaw, started = self.junction
        if started:  # a turn under way is finished, whatever the route says next (leaving the junction, the
            command = started  # command already announces the next one)
        elif command not in (1, 2):
            if self.line.ignore_light_m > 0:  # through this junction another way: its bar is behind us
                self.junction = None
            return None
        # Left turns from the inner lane (0), right turns from the outer one (1). Taken from the other lane, this
        # arc still ends in a lane of the road turned into: the arc is placed from our own lane, and a right
        # turn's radius from the outer lane (or a left turn's from the inner) is the tighter one.
        k = 0 if command == 1 else 1
        u = np.array([math.cos(road_yaw), math.sin(road_yaw)])
        heading = odo.yaw - road_yaw
        half = VEHICLE.length_m / 2
        rel = odo.pos - np.array([bx, by])
        # the rear axle, along the approach and right of it: in highway-env's bicycle model it moves along the
        # car's heading on a curve of curvature tan(delta) / length
        here = np.array([float(rel @ u) - half * math.cos(heading), float(rel[0] * -u[1] + rel[1] * u[0])
                         - half * math.sin(heading)])
        path, arc_end = turn_path(command, self.road.stop_line_setback_m, (k + 0.5) * self.road.lane_width_m,
                                   self.road.stop_bar_depth_m)
        lookahead = cfg.turn_lookahead_m + cfg.turn_lookahead_s * speed
        if here[0] < self.road.stop_bar_depth_m - lookahead:  # not yet: the lookahead point is still before the arc
            return None
        step = float(np.hypot(*(path[1] - path[0])))
        nearest = int(np.argmin(np.sum((path - here) ** 2, axis=1)))
        if nearest * step > arc_end + 6.0:  # out of the turn, lined up on the road turned into: the lines lead again
            self.junction = None
            return None
        if not started:
            self.junction = (bx, by, road_yaw, command)
        target = path[min(len(path) - 1, nearest + int(round(lookahead / step)))]
        alpha = math.atan2(target[1] - here[1], target[0] - here[0]) - heading
        alpha = math.atan2(math.sin(alpha), math.cos(alpha))
        # Pure pursuit: the arc from the rear axle through the target has curvature 2 sin(alpha) / lookahead.
        delta = math.atan(2.0 * VEHICLE.length_m * math.sin(alpha) / lookahead)
        return float(np.clip(delta / VEHICLE.max_steer_rad, -1.0, 1.0))
