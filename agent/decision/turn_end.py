"""When a commanded turn has brought the car onto the road turned into, PilotNet is asked to follow that road.

Why: the route command names the junction's turn until the car leaves the junction, and PilotNet, conditioned on
it, keeps steering into the turn after the junction's arc hands over: where the road turned into is already
straight ahead it overturns, and the car cuts to the turn's inner side. The same happens when the car is engaged
again in the middle of a turn (after a safety driver's take-over), where the turn left to do is small. The lane
finder tells when the turn is over: a confident lane lined up with the car. From then the command PilotNet gets
is "follow the road" for ``keep_m`` of travel, until the route's command changes, or until the next junction's
stop bar is placed (downtown's blocks can be shorter than ``keep_m``, and the next turn may be the same way); the
controller still knows the car is turning (its speed caps are unchanged). The junction is then behind the car: its
light is ignored for at most ``light_ignore_m`` more (``StopLineTrack.leave_junction``), so that the next junction's
stop bar and light count from there, not from a window sized for crossing the junction straight on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from towndrive.agent.perception.lanes import LaneResult
from towndrive.sim.spec import COMMAND_CODES

FOLLOW, LEFT, RIGHT = (COMMAND_CODES[name] for name in ("follow", "left", "right"))  # the observation's codes


@dataclass(frozen=True)
class TurnEndRules:
    enabled: bool = True
    min_turned_deg: float = 20.0  # a turn counts as under way once the car has turned this far
    aligned_deg: float = 8.0  # a lane this near the car's heading is the road turned into
    min_confidence: float = 0.4  # ... when the lane finder is this sure of it
    keep_m: float = 15.0  # then PilotNet follows the road this far (or until the command changes)
    light_ignore_m: float = 5.0  # ... and the junction's light is ignored at most this much farther


class TurnEnd:
    """The command PilotNet is given (module docstring). ``reset(engaged_again)`` per episode or take-over."""

    def __init__(self, rules: TurnEndRules) -> None:
        self.rules = rules
        self.reset()

    def reset(self, engaged_again: bool = False, inside_junction: bool = False) -> None:
        """``engaged_again``: after a take-over; ``inside_junction``: one taken inside a junction (the safety driver
        leaves the car there, on the turn's path)."""
        self._done: int | None = None  # the turn judged over, while its command lasts
        self._left_m = 0.0  # travel left on the road turned into before the command is given back
        self._engaged_in_turn = engaged_again  # engaged again, perhaps inside a turn: no turning to wait for
        self._inside = inside_junction  # (counts only while engaged again: engaged_mid_turn)
        self._first = True
        self._placed = False  # whether a junction ahead was placed on the last frame
        self.ended = False  # the turn was judged over on this frame

    @property
    def engaged_mid_turn(self) -> bool:
        """Engaged again inside a junction with its turn not yet over: the car is turning, whatever the lane lines
        (absent there) and the junction guidance (which starts afresh, nothing placed) tell. A left or right
        command then is no lane change to come (``BlindSpot.plan``): held as one, PilotNet was told to follow a
        lane the car was not in, and it left the turn."""
        return self._engaged_in_turn and self._inside

    def command(self, command: int, turned_rad: float, lanes: LaneResult | None, arc_leads: bool,
                travelled_m: float, junction_placed: bool = False) -> int:
        """The command for PilotNet this frame: ``command`` (the route's), or FOLLOW once the turn is over.
        ``turned_rad``: the heading change since the car last drove along its lane; ``lanes``: the last lane fit;
        ``arc_leads``: the junction's arc is under way (``JunctionGuidance.arc_leads``); ``travelled_m``: since the
        last frame; ``junction_placed``: a junction's stop bar ahead is located (``JunctionGuidance.placed``): one
        placed after the turn was judged over is the next junction, and the route's command is its own."""
        r = self.rules
        self.ended = False
        next_junction = junction_placed and not self._placed
        self._placed = junction_placed
        if self._done is not None and next_junction:
            self._done, self._engaged_in_turn = None, False
        if self._first:
            self._first = False
            self._engaged_in_turn = self._engaged_in_turn and command in (LEFT, RIGHT)
            return command  # (the last lane fit is from before a take-over)
        if command not in (LEFT, RIGHT) or (self._done is not None and command != self._done):
            self._done, self._engaged_in_turn = None, False
            return command
        if self._done is not None:
            self._left_m -= travelled_m
            if self._left_m > 0:
                return FOLLOW
            self._done = None
            return command
        if not r.enabled or arc_leads or lanes is None:
            return command
        under_way = abs(turned_rad) >= math.radians(r.min_turned_deg) or self._engaged_in_turn
        aligned = (lanes.confidence >= r.min_confidence and math.isfinite(lanes.heading_rad)
                   and abs(lanes.heading_rad) <= math.radians(r.aligned_deg))
        if under_way and aligned:
            self._done, self._left_m, self._engaged_in_turn = command, r.keep_m, False
            self.ended = True
            return FOLLOW
        return command
