"""The command PilotNet is given once a commanded turn is over (``agent.decision.turn_end``)."""

from __future__ import annotations

import math

import pytest

from towndrive.agent.decision.turn_end import FOLLOW, LEFT, RIGHT, TurnEnd, TurnEndRules
from towndrive.agent.perception.lanes import LaneResult


def lane(heading_deg: float, confidence: float = 0.6) -> LaneResult:
    return LaneResult(None, None, 0.0, math.inf, math.radians(heading_deg), 3.5, confidence, True)


def test_pilotnet_follows_the_road_once_a_turn_has_brought_the_car_onto_it() -> None:
    end = TurnEnd(TurnEndRules())
    end.reset()
    assert end.command(RIGHT, 0.0, lane(0.0), False, 0.1) == RIGHT  # first frame
    assert end.command(RIGHT, 0.0, lane(0.0), False, 0.1) == RIGHT  # approaching: not yet turning
    assert end.command(RIGHT, math.radians(60), lane(0.0), True, 0.1) == RIGHT  # the arc leads
    assert end.command(RIGHT, math.radians(70), lane(25.0), False, 0.1) == RIGHT  # the road turned into: still at an angle
    assert end.command(RIGHT, math.radians(70), lane(3.0, 0.2), False, 0.1) == RIGHT  # lined up but unsure
    assert end.command(RIGHT, math.radians(85), lane(3.0), False, 0.1) == FOLLOW  # lined up: the turn is over
    # It stays over while the car travels keep_m (the car drives straight: the odometry's turn goes back to 0) ...
    for _ in range(int(TurnEndRules().keep_m / 0.5) - 1):
        assert end.command(RIGHT, 0.0, None, False, 0.5) == FOLLOW
    assert end.command(RIGHT, 0.0, None, False, 0.5) == RIGHT
    # ... or until the route's command changes.
    end.reset()
    end.command(LEFT, 0.0, None, False, 0.0)
    assert end.command(LEFT, math.radians(-80), lane(-2.0), False, 0.1) == FOLLOW
    assert end.command(FOLLOW, 0.0, None, False, 0.1) == FOLLOW
    assert end.command(RIGHT, 0.0, lane(0.0), False, 0.1) == RIGHT


def test_engaged_again_inside_a_turn_the_car_need_not_turn_far_before_following_the_road() -> None:
    """After a take-over the safety driver leaves the car on the turn's own path, where the turn left to do may be
    small: a lined-up lane ends it at once; without the take-over the car would have to turn 20 degrees first."""
    end = TurnEnd(TurnEndRules())
    end.reset(engaged_again=True)
    end.command(RIGHT, 0.0, lane(0.0), False, 0.0)
    assert end.command(RIGHT, math.radians(2), lane(2.0), False, 0.1) == FOLLOW
    fresh = TurnEnd(TurnEndRules())
    fresh.reset()
    fresh.command(RIGHT, 0.0, lane(0.0), False, 0.0)
    assert fresh.command(RIGHT, math.radians(2), lane(2.0), False, 0.1) == RIGHT
    off = TurnEnd(TurnEndRules(enabled=False))
    off.reset(engaged_again=True)
    off.command(RIGHT, 0.0, None, False, 0.0)
    assert off.command(RIGHT, math.radians(85), lane(0.0), False, 0.1) == RIGHT


def test_engaged_again_inside_a_junction_the_car_is_mid_turn_until_the_turn_is_over() -> None:
    end = TurnEnd(TurnEndRules())
    end.reset(engaged_again=True, inside_junction=True)
    end.command(RIGHT, 0.0, None, False, 0.0)
    assert end.engaged_mid_turn
    assert end.command(RIGHT, math.radians(30), lane(3.0), False, 0.1) == FOLLOW  # lined up: over
    assert not end.engaged_mid_turn
    for engaged, inside, command in ((True, False, RIGHT), (False, True, RIGHT), (True, True, FOLLOW)):
        end.reset(engaged_again=engaged, inside_junction=inside)
        end.command(command, 0.0, None, False, 0.0)
        assert not end.engaged_mid_turn, (engaged, inside, command)


def test_once_a_turn_is_over_the_next_junction_s_stop_bar_counts_within_metres() -> None:
    """Past a stop line the junction's light and any bar are ignored for ``junction_ignore_m`` (a window sized for
    crossing the junction straight on); a turn that is over ends it within ``light_ignore_m``, so the bar of a
    junction a short block after a turn is tracked (without it, the car ran that junction's red)."""
    from towndrive.agent.decision.controller import ControllerConfig
    from towndrive.agent.decision.stop_line_track import StopLineTrack

    def bar_after(leave: bool) -> float | None:
        line = StopLineTrack(ControllerConfig())
        line.update(5.0, 3.0 + ControllerConfig().camera_to_front_m, None, None, 0.05)
        for _ in range(40):  # over the line, into the junction
            line.update(5.0, None, None, None, 0.05)
        assert line.in_junction
        end = TurnEnd(TurnEndRules())
        end.reset()
        end.command(RIGHT, 0.0, None, False, 0.0)
        assert end.command(RIGHT, math.radians(80), lane(1.0), False, 0.25) == FOLLOW and end.ended
        assert end.command(RIGHT, math.radians(80), lane(1.0), False, 0.25) == FOLLOW and not end.ended
        if leave:
            line.leave_junction(TurnEndRules().light_ignore_m)
        for _ in range(30):  # 7.5 m on along the road turned into, the next bar 20 m ahead of the camera
            line.update(5.0, None, None, None, 0.05)
        line.update(5.0, 20.0, None, None, 0.05)
        return line.stop_line

    assert bar_after(leave=False) is None
    assert bar_after(leave=True) == pytest.approx(20.0 - ControllerConfig().camera_to_front_m)


def test_the_next_junction_placed_after_a_turn_is_over_gets_its_own_command() -> None:
    """A block shorter than ``keep_m``: the car turned right, the next junction (placed as its stop bar is located)
    is a right turn too. PilotNet, and the junction's arc (which takes the same command), must get the route's
    right there, not "follow the road" left over from the turn before."""
    end = TurnEnd(TurnEndRules())
    end.reset()
    end.command(RIGHT, 0.0, None, False, 0.0)
    assert end.command(RIGHT, math.radians(85), lane(3.0), False, 0.1) == FOLLOW  # the first turn is over
    assert end.command(RIGHT, 0.0, None, False, 1.0) == FOLLOW  # on along the road turned into
    assert end.command(RIGHT, 0.0, lane(0.0), False, 1.0, junction_placed=True) == RIGHT  # the next bar, 13 m short
    assert end.command(RIGHT, 0.0, lane(0.0), False, 1.0, junction_placed=True) == RIGHT
    # A junction already placed as the turn ended is not the next one.
    end.reset()
    end.command(RIGHT, 0.0, None, False, 0.0, junction_placed=True)
    assert end.command(RIGHT, math.radians(85), lane(3.0), False, 0.1, junction_placed=True) == FOLLOW
    assert end.command(RIGHT, 0.0, None, False, 1.0, junction_placed=True) == FOLLOW
