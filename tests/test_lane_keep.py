"""Lane keeping on PilotNet's steering (agent.decision.lane_keep): the two bounds, and where they do not apply."""

from __future__ import annotations

import math

import numpy as np

from towndrive.agent.decision.lane_keep import LaneKeepRules, kept_steer
from towndrive.agent.perception.lanes import LaneLine, LaneResult

RULES = LaneKeepRules()


def lanes(heading_rad: float, right_x_m: float = 1.75, right_style: str = "solid", left_x_m: float = -1.75,
          left_color: str = "yellow", reach_m: float = 20.0) -> LaneResult:
    """Straight lane lines in the camera's ground frame, ``x = c + z tan(-heading)`` (a positive heading: the
    lane runs right of the car's axis, so its lines ahead lie farther right)."""
    slope = math.tan(heading_rad)

    def line(x0: float, color: str, style: str) -> LaneLine:
        return LaneLine(np.array([0.0, slope, x0]), (3.0, reach_m), 0.9, 500, color, style)

    centre = 0.5 * (left_x_m + right_x_m)
    return LaneResult(line(left_x_m, left_color, "solid"), line(right_x_m, "white", right_style), -centre, math.inf,
                      heading_rad, right_x_m - left_x_m, 0.9, True, centre_offset_m=-centre)


def test_a_heading_far_off_the_lane_is_steered_back_along_it() -> None:
    # 20 degrees right of the lane (the lane runs to the car's left): PilotNet steering on to the right
    kept = kept_steer(RULES, 0.3, lanes(-math.radians(20)), 6.0, turn_due=False)
    assert kept is not None and kept[0] < -0.3 and "off the lane" in kept[1]
    # a lane change's few degrees are left alone
    assert kept_steer(RULES, 0.3, lanes(-math.radians(6), right_style="dashed"), 6.0, turn_due=False) is None


def test_a_solid_edge_is_not_crossed_but_a_dashed_line_may_be() -> None:
    """Heading 6 degrees right at 6 m/s, the car's side 0.4 m from the line: it reaches it within the second."""
    near = lanes(-math.radians(6), right_x_m=0.95 + 0.4, left_x_m=0.95 + 0.4 - 3.5)
    kept = kept_steer(RULES, 0.1, near, 6.0, turn_due=False)
    assert kept is not None and kept[0] < 0 and "edge" in kept[1]
    dashed = lanes(-math.radians(6), right_x_m=1.35, right_style="dashed", left_x_m=1.35 - 3.5)
    assert kept_steer(RULES, 0.1, dashed, 6.0, turn_due=False) is None  # another lane of ours: a lane change
    # heading away from the edge, or standing: nothing to keep
    assert kept_steer(RULES, 0.0, lanes(math.radians(3), right_x_m=1.35, left_x_m=-2.15), 6.0, turn_due=False) is None
    # the centre line on the left alike
    left = lanes(math.radians(6), right_x_m=3.5 - 1.35, left_x_m=-1.35)
    kept = kept_steer(RULES, -0.1, left, 6.0, turn_due=False)
    assert kept is not None and kept[0] > 0 and "centre line" in kept[1]


def test_the_bounds_give_way_to_a_turn_and_to_a_harder_steer_back() -> None:
    far_off = lanes(-math.radians(20))
    assert kept_steer(RULES, 0.3, far_off, 6.0, turn_due=True) is None  # the junction's turn is being made
    assert kept_steer(RULES, -1.0, far_off, 6.0, turn_due=False) is None  # PilotNet already steers back harder
    assert kept_steer(RULES, 0.3, lanes(-math.radians(20), reach_m=5.0), 6.0, turn_due=False) is None  # lines short
