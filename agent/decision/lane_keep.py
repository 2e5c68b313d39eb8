"""Lane keeping on PilotNet's steering: it may change lanes, but not point far off its lane nor cross a road edge.

Why: PilotNet changes lanes as the autopilot it learned from does (into the kerb lane before a right turn), but now
and then it swings the car 20 degrees off the lane at cruise speed, straightens too late, and then steers on
towards the kerb: the car leaves the road a block before the junction. Two bounds, as a lane keeping assist has:

- a heading more than ``max_heading_rad`` off the lane the camera sees (a lane change needs a few degrees);
- a line the car must not cross, the road's solid white edge on its right or the yellow centre line on its left,
  that the car's side would come within ``margin_m`` of within ``crossing_s`` at its heading (or already has).

Either steers the car back along its lane with the junction hold's law (``JunctionRules``: heading and offset
gains), unless PilotNet already steers back harder. Only where the lane lines are what the car drives along: seen
with some confidence and some way ahead, and not while the junction's own steering leads (its hold or its turn arc)
nor at the junction where a commanded turn is due (its bar near, or a turn placed), where the approach lane's lines
point away from where the car is going.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from towndrive.agent.decision.junction import JunctionRules
from towndrive.agent.decision.signs import lanes_to_kerb
from towndrive.agent.perception.lanes import LaneResult
from towndrive.sim.spec import VEHICLE


@dataclass(frozen=True)
class LaneKeepRules:
    enabled: bool = True
    max_heading_rad: float = 0.2  # about 11 degrees: more than a lane change needs
    crossing_s: float = 1.0  # the car's side would reach a solid edge or the centre line this soon ...
    margin_m: float = 0.2  # ... or come this near it (the painted line's middle, level with the camera)
    heading_gain: float = JunctionRules.hold_heading_gain  # steer per radian of heading off the lane
    offset_gain: float = JunctionRules.hold_offset_gain  # steer per metre off the lane's centre
    min_confidence: float = 0.25  # a lane fit at least this sure (one line seen well gives 0.5)
    min_reach_m: float = 8.0  # ... whose lines reach at least this far ahead
    turn_bar_m: float = 15.0  # a commanded turn's bar nearer than this: the lanes no longer lead


def kept_steer(rules: LaneKeepRules, steer: float, lanes: LaneResult | None, speed_mps: float,
               turn_due: bool) -> tuple[float, str] | None:
    """The steer back along the lane and why, when PilotNet's ``steer`` would break a bound (module docstring);
    None when no bound applies or PilotNet already steers back at least as hard. ``turn_due``: a commanded turn
    is being made here."""
    if not rules.enabled or lanes is None or not lanes.detected or turn_due:
        return None
    heading, offset = lanes.heading_rad, lanes.centre_offset_m
    if lanes.confidence < rules.min_confidence or not (math.isfinite(heading) and math.isfinite(offset)):
        return None
    if lanes.reach_m(0.0) < rules.min_reach_m:
        return None
    why = ""
    if abs(heading) > rules.max_heading_rad:
        why = f"PilotNet points {math.degrees(abs(heading)):.0f} deg off the lane"
    else:
        # heading > 0: the lane runs right of the car's axis, the car drifts left across it at v sin(heading)
        drift = -speed_mps * math.sin(heading)  # the car's speed to the right across the lane
        half = VEHICLE.width_m / 2
        right, left = lanes.right, lanes.left
        if right is not None and lanes_to_kerb(lanes) == 0 and \
                float(right.x_at(0.0)) - half - drift * rules.crossing_s < rules.margin_m:
            why = "the road's edge is near"
        elif left is not None and left.color == "yellow" and \
                -float(left.x_at(0.0)) - half + drift * rules.crossing_s < rules.margin_m:
            why = "the centre line is near"
    if not why:
        return None
    back = max(-1.0, min(1.0, rules.heading_gain * heading - rules.offset_gain * offset))
    if (back >= 0 and steer >= back) or (back <= 0 and steer <= back):
        return None
    return back, why
