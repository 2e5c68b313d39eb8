"""Dead reckoning from the car's own speed and steering, and the approach lane measured before a junction.

Why: inside a junction there are no lines to steer or judge lights by. The car integrates its heading and
position with highway-env's bicycle model (the car of ``sim.spec``), keeps the heading it had while it last
drove along its lane (lights are judged in that frame once a commanded turn begins), and keeps the approach
lane's heading and its own offset from that lane's centre, measured from a confident lane fit well before the
stop line and dead-reckoned since.
"""

from __future__ import annotations

import math

import numpy as np

from towndrive.agent.decision.stop_line_track import StopLineTrack
from towndrive.agent.decision.turn_end import TurnEndRules
from towndrive.sim.spec import VEHICLE


def in_approach_frame(x_m: float, z_m: float, turned_rad: float) -> tuple[float, float]:
    """A point the camera sees at ``x_m`` right and ``z_m`` ahead, in the approach lane's frame (across it and along
    it), the car having turned ``turned_rad`` (``Odometry.turned``, positive right) since it drove along that lane."""
    c, s = math.cos(turned_rad), math.sin(turned_rad)
    return x_m * c + z_m * s, z_m * c - x_m * s


class Odometry:
    """The car's pose in its own episode frame (x ahead at yaw 0, y right; yaw positive to the right)."""

    def __init__(self, straight_steer: float = 0.08, road_min_confidence: float = 0.25, road_clear_m: float = 8.0,
                 along_min_mps: float = 1.0, new_road_min_confidence: float = TurnEndRules.min_confidence,
                 new_road_aligned_deg: float = TurnEndRules.aligned_deg) -> None:
        self.straight_steer = straight_steer  # below this |steer| the car drives along its lane ...
        self.along_min_mps = along_min_mps  # ... if it drives at all: a turn commanded, a car creeping to a stop
        #                                     or standing keeps its approach heading whatever its wheels do
        self.road_min_confidence = road_min_confidence  # a lane fit this sure measures the approach lane
        self.road_clear_m = road_clear_m  # ... only while the stop line is farther than this
        # inside a junction, the road a turn brought the car onto is measured from a lane this sure, lined up with
        # the car this near (the turn is over, as ``TurnEnd`` judges it; other lines there are the junction's)
        self.new_road_min_confidence = new_road_min_confidence
        self.new_road_aligned_rad = math.radians(new_road_aligned_deg)
        self.reset()

    def reset(self) -> None:
        self.turn = 0.0  # the heading change of the last frame (rad)
        self.yaw = 0.0  # dead-reckoned heading (rad)
        self.road_yaw: float | None = None  # the approach lane's heading in the same frame, from the lane fit
        self.road_offset = 0.0  # metres right of the approach lane's centre (measured, then dead-reckoned)
        self.approach_yaw = 0.0  # the heading the car had while it last drove along its lane
        self.pos = np.zeros(2)  # dead-reckoned position of the car's centre

    @property
    def turned(self) -> float:
        """The heading change since the car last drove along its lane (rad)."""
        return self.yaw - self.approach_yaw

    def advance(self, speed: float, steer: float, command: int, dt: float) -> None:
        """Integrate the heading from the speed and the steering just sent. While the car follows its lane, the
        approach heading follows it; once it steers into a commanded turn, the approach heading stays. A car that
        turned a little before the stop line and stops there is not following its lane when its wheels come straight
        as it stops: it still faces its light from that angle."""
        beta = math.atan(0.5 * math.tan(steer * VEHICLE.max_steer_rad))
        self.pos += speed * dt * np.array([math.cos(self.yaw + beta), math.sin(self.yaw + beta)])
        self.turn = speed * math.sin(beta) / (VEHICLE.length_m / 2) * dt
        self.yaw += self.turn
        if self.road_yaw is not None:
            self.road_offset += speed * math.sin(self.yaw + beta - self.road_yaw) * dt
        if command not in (1, 2) or (abs(steer) < self.straight_steer and speed >= self.along_min_mps):
            self.approach_yaw = self.yaw

    def leave_road(self) -> None:
        """A commanded turn is over: the road measured is behind the car, the one turned into not yet measured."""
        self.road_yaw = None
        self.road_offset = 0.0

    def measure_road(self, centre: np.ndarray | None, confidence: float, line: StopLineTrack, z0: float) -> None:
        """Keep the approach lane's heading and our offset from its centre (``centre``: the lane-centre polynomial
        in the camera's ground frame, evaluated at ``z0``, the car's centre), from a confident lane fit taken well
        before the stop line and outside a junction, or, for a road not yet measured (``leave_road``), from the
        first sure fit lined up with the car, inside the junction too."""
        in_junction = line.ignore_light_m > 0  # the approach lane is kept there; a road not yet measured is not
        if (centre is None or confidence < self.road_min_confidence
                or (line.stop_line is not None and line.stop_line < self.road_clear_m)
                or (in_junction and (self.road_yaw is not None or confidence < self.new_road_min_confidence))):
            return
        across = math.atan(float(np.polyval(np.polyder(centre), z0)))  # the lane's direction, right of ours
        if in_junction and abs(across) > self.new_road_aligned_rad:
            return  # the road turned into is measured once lined up with the car
        heading = self.yaw + across
        self.road_yaw = heading if self.road_yaw is None else self.road_yaw + 0.2 * (heading - self.road_yaw)
        self.road_offset = -float(np.polyval(centre, z0))
