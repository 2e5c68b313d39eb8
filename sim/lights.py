"""Traffic-light phases: opposite approaches in step, conflicting ones red.

Each junction runs a two-axis cycle (east-west, then north-south): green, yellow, all-red. A
junction's cycle starts at a seeded offset so that the town does not switch in unison.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.objects import LightState
from sim.town import Arm, Town


@dataclass(frozen=True)
class LightTiming:
    green_s: float = 14.0
    yellow_s: float = 3.0
    all_red_s: float = 1.5

    @property
    def half_cycle_s(self) -> float:
        return self.green_s + self.yellow_s + self.all_red_s

    @property
    def cycle_s(self) -> float:
        return 2 * self.half_cycle_s


class TrafficLights:
    """The state of every approach's light at the current time."""

    def __init__(self, town: Town, timing: LightTiming, rng: np.random.Generator) -> None:
        self.timing = timing
        junctions = sorted({ap.node for ap in town.approaches})
        offsets = {node: float(rng.uniform(0.0, timing.cycle_s)) for node in junctions}
        self._offset = np.array([offsets[ap.node] for ap in town.approaches])
        # East-west arms use the first half of the cycle, north-south the second.
        self._axis_shift = np.array([0.0 if ap.arm in (Arm.E, Arm.W) else timing.half_cycle_s for ap in town.approaches])
        self._forced: dict[int, tuple[LightState, float]] = {}
        self.time_s = 0.0
        self._states = np.zeros(len(town.approaches), dtype=np.int64)
        self._state_list: list[LightState] = []  # the same states as enum members, rebuilt only on a change
        self._phase = np.zeros(len(town.approaches))
        self.update(0.0)

    def update(self, time_s: float) -> None:
        self.time_s = time_s
        t = self.timing
        self._phase = (time_s + self._offset - self._axis_shift) % t.cycle_s
        states = np.full(len(self._phase), int(LightState.RED))
        states[self._phase < t.green_s + t.yellow_s] = int(LightState.YELLOW)
        states[self._phase < t.green_s] = int(LightState.GREEN)
        for index, (state, until) in self._forced.items():
            if time_s < until:
                states[index] = int(state)
        if not self._state_list or not np.array_equal(states, self._states):
            self._state_list = [LightState(int(s)) for s in states]
        self._states = states

    def state(self, approach: int) -> LightState:
        return self._state_list[approach]

    @property
    def states(self) -> list[LightState]:
        """Every approach's state (a fresh list; lights change every few seconds, so the members are kept)."""
        return list(self._state_list)

    def red_remaining_s(self, approach: int) -> float:
        """Seconds until this approach turns green again (0 when it is not red)."""
        if self._state_list[approach] != LightState.RED:
            return 0.0
        return float(self.timing.cycle_s - self._phase[approach])

    def force(self, approach: int, state: LightState, until_s: float) -> None:
        """Hold one light in a state until a time (scenarios: 'a red light that turns green')."""
        self._forced[approach] = (state, until_s)
        self.update(self.time_s)
