"""The stop bar ahead, tracked: one distance that the controller stops at and the junction guidance places turns by.

Why a track: the camera stops seeing a stop bar about 3 m ahead of it, before the car has stopped, so the last
measured distance is counted down by the car's own travel (speed x dt), exact enough for the last metres. A bar
cannot move away: a reading more than ``line_jump_m`` farther than the tracked one (the zebra beyond it, caught
for a frame) is believed only after ``line_jump_frames`` frames in a row that agree. With no bar seen, the
distance falls back on the light's distance minus where the road design puts lights (across the junction).
Once the bumper is past the bar, the junction's light is ignored for ``junction_ignore_m`` metres. A junction
entered by a line only inferred from the light (the bar hidden under a queue's cars, a light taken for ours that
stands nearer than the design puts it) is left again when a bar is read ahead in the first metres: the inferred
line was wrong, and the real bar, which a turn is placed by, would otherwise be ignored.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from towndrive.agent.decision.priors import junction_widening_m
from towndrive.sim.spec import ROAD, RoadDesign

if TYPE_CHECKING:
    from towndrive.agent.decision.controller import ControllerConfig

LIGHT_STATES = ("red", "yellow", "green")
NEXT_IN_CYCLE = {"green": "yellow", "yellow": "red", "red": "green"}  # what a light's state changes to


def camera_to_bar_m(line: StopLineTrack) -> float:
    """The camera to the tracked bar's near edge (the track keeps the bumper's distance, which the controller stops
    by; perception and the road design measure from the camera). Only with a bar tracked."""
    assert line.stop_line is not None
    return line.stop_line + line.config.camera_to_front_m


class Unconfirmed:
    """A stop-line reading that disagrees with the tracked one: believed once it has been seen again, frame after
    frame, where odometry puts it (within a metre)."""

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        self.value: float | None = None
        self.count = 0

    def travel(self, metres: float) -> None:
        if self.value is not None:
            self.value -= metres

    def see(self, reading: float) -> int:
        """One more disagreeing reading; returns how many frames in a row have agreed with it."""
        agrees = self.value is not None and abs(reading - self.value) < 1.0
        self.count = self.count + 1 if agrees else 1
        self.value = reading
        return self.count


class StopLineTrack:
    """Bumper to the stop bar ahead (odometry between readings), and the travel left inside a junction."""

    def __init__(self, config: ControllerConfig, road: RoadDesign = ROAD) -> None:
        self.config = config
        self.road = road
        self.reset()

    @property
    def junction_ignore_m(self) -> float:
        """Travel past a stop line during which lights are ignored: the configured distance is for the classic
        design's junctions; a design whose stop bars stand farther from the centre adds the difference on both
        sides (its junctions are that much wider)."""
        return self.config.junction_ignore_m + junction_widening_m(self.road.stop_line_setback_m)

    def reset(self) -> None:
        self.stop_line: float | None = None  # bumper to the stop line, metres
        self.stop_line_measured = False  # True once a bar was seen (not only inferred from the light)
        self._farther = Unconfirmed()  # a bar reading farther than the tracked line
        self._line_unseen_s = 0.0  # since the tracked bar was last measured
        self._reads = 0  # paint readings of the tracked bar
        self._hidden = False  # a vehicle in our path stood nearer than the bar since its last reading
        self._odd_light = Unconfirmed()  # a stop line inferred from a light, far from the tracked one
        self.ignore_light_m = 0.0  # travel left during which lights are ignored (inside a junction)
        self._inferred_entry = False  # the junction was entered by a line inferred from the light, never read
        self._bar_after_entry = Unconfirmed()  # a bar read ahead since then

    def leave_junction(self, within_m: float) -> None:
        """The car has left the junction (a turn is over): its light is ignored for at most ``within_m`` more."""
        self.ignore_light_m = min(self.ignore_light_m, within_m)

    @property
    def bar_confirmed(self) -> bool:
        """Whether the tracked bar is one to place a turn by without a near reading: read more than once, or read
        once and then hidden behind a vehicle in our path. A bar read once and then out of sight with nothing in
        front of it may be a glimpse (a kerb or a zebra's edge at night), which ``line_unseen_forget_s`` would
        forget: placed meanwhile, it put a turn's arc where there was none."""
        return self.stop_line_measured and self.stop_line is not None and (self._reads >= 2 or self._hidden)

    @property
    def in_junction(self) -> bool:
        """Whether the bumper crossed a stop line within the last ``junction_ignore_m`` metres."""
        return self.ignore_light_m > 0

    def update(self, speed_mps: float, stop_line_m: float | None, light: str | None, light_distance_m: float | None,
               dt: float, hidden: bool = False) -> bool:
        """One frame: the car travelled ``speed_mps x dt``; ``stop_line_m`` is the camera-to-bar reading (None when no bar
        is seen), ``light`` and ``light_distance_m`` our light; ``hidden``: a vehicle in our path stands nearer than
        the tracked bar (its paint may be out of sight behind it). Returns whether the bumper just entered a
        junction."""
        cfg = self.config
        travelled = speed_mps * dt
        if self.ignore_light_m > 0:
            self.ignore_light_m = max(0.0, self.ignore_light_m - travelled)
        if self.stop_line is not None:
            self.stop_line -= travelled
        self._farther.travel(travelled)
        self._odd_light.travel(travelled)
        self._bar_after_entry.travel(travelled)
        measured = None if stop_line_m is None else stop_line_m - cfg.camera_to_front_m
        if self._inferred_entry and self.junction_ignore_m - self.ignore_light_m > cfg.line_inferred_revert_m:
            self._inferred_entry = False  # far enough in: what is read now is inside the junction
        if (self._inferred_entry and measured is not None and measured >= cfg.line_jump_m
                and self._bar_after_entry.see(measured) >= cfg.line_jump_frames):
            self.ignore_light_m, self._inferred_entry = 0.0, False  # the real bar is ahead: not in the junction
            self._bar_after_entry.clear()
        if (measured is not None and self.stop_line_measured and self.stop_line is not None
                and measured > self.stop_line + cfg.line_jump_m):
            # A bar cannot move away: a farther "bar" is the zebra beyond it (close in always; farther out
            # it is believed only when it is seen again where odometry puts it, frame after frame).
            seen = self._farther.see(measured)
            if self.stop_line < 5.0 or seen < cfg.line_jump_frames:
                measured = None
        else:
            self._farther.clear()
        if measured is not None and self.ignore_light_m <= 0:
            self._reads = self._reads + 1 if self.stop_line_measured else 1
            self._hidden = False
            self.stop_line = measured
            self.stop_line_measured = True
            self._line_unseen_s = 0.0
        elif self.stop_line_measured and self.stop_line is not None:
            if hidden:  # a bar behind a car waiting at it is out of sight, not a glimpse that was never there
                self._hidden = True
            else:
                self._line_unseen_s += dt
            if self.stop_line > cfg.line_unseen_far_m and self._line_unseen_s > cfg.line_unseen_forget_s:
                # A glimpse (a kerb seen across the lane, a patch of headlight) dead-reckoned to the bumper
                # would put the car "in the junction" and make it ignore the real light ahead.
                self.stop_line, self.stop_line_measured = None, False
        elif (not self.stop_line_measured and light_distance_m is not None and self.ignore_light_m <= 0
              and light in LIGHT_STATES):
            # (before a bar is measured, our light can only be the design's main mount: agent.decision.our_light)
            inferred = light_distance_m - self.road.light_beyond_stop_line_m - cfg.camera_to_front_m \
                - cfg.light_fallback_margin_m
            # A reading far from the tracked one, or one that puts the car past a line it never saw, is believed
            # only when seen again where odometry puts it: a light misread for one frame would otherwise put the
            # car "in the junction" short of the real line, ignoring its light (docs/agent_rules.md).
            if ((self.stop_line is None and inferred >= -1.0)
                    or (self.stop_line is not None and abs(inferred - self.stop_line) <= cfg.line_jump_m)
                    or self._odd_light.see(inferred) >= cfg.line_jump_frames):
                self.stop_line = inferred
                self._odd_light.clear()
        if self.stop_line is not None and self.stop_line < -1.0:  # the bumper is past the line: in the junction
            self._inferred_entry = not self.stop_line_measured
            self._bar_after_entry.clear()
            self.stop_line, self.stop_line_measured = None, False
            self.ignore_light_m = self.junction_ignore_m
            return True
        return False
