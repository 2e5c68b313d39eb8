"""Traffic-light phases: opposite approaches in step, conflicting ones red.

Each junction runs a two-axis cycle (east-west, then north-south): green, yellow, all-red. A
junction's cycle starts at a seeded offset so that the town does not switch in unison.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from towndrive.sim.objects import LightState
from towndrive.sim.spec import LIGHT_ALL_RED_S, LIGHT_GREEN_S, LIGHT_YELLOW_S
from towndrive.sim.town import Arm, Town

_GREEN, _YELLOW, _RED = int(LightState.GREEN), int(LightState.YELLOW), int(LightState.RED)  # the kernel's constants


@dataclass(frozen=True)
class LightTiming:
    green_s: float = LIGHT_GREEN_S
    yellow_s: float = LIGHT_YELLOW_S
    all_red_s: float = LIGHT_ALL_RED_S

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
        self._phase = np.empty(len(self._offset))
        states = np.empty(len(self._offset), np.int64)
        light_phases(time_s, self._offset, self._axis_shift, t.cycle_s, t.green_s, t.green_s + t.yellow_s,
                     self._phase, states)
        for index, (state, until) in self._forced.items():
            if time_s < until:
                states[index] = int(state)
        # the arrays have one length and dtype, so equal bytes mean equal states
        if not self._state_list or states.tobytes() != self._states.tobytes():
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


@nb.njit(cache=True, nogil=True)
def light_phases(time_s: float, offset: np.ndarray, axis_shift: np.ndarray, cycle_s: float, green_s: float,
                 green_yellow_s: float, phase: np.ndarray, states: np.ndarray) -> None:
    """Each approach's place in its cycle, ``(time_s + offset - axis_shift) % cycle_s``, into ``phase``, and its
    state into ``states``: green before ``green_s``, yellow before ``green_yellow_s``, red after.

    One compiled loop instead of a dozen NumPy calls on a few dozen numbers (the calls cost more than the
    arithmetic). The same operations in the same order as the NumPy expression; the float remainder is
    Python's (fmod, then the divisor added when the signs differ), as NumPy's ``%`` computes it.
    """
    for k in range(offset.shape[0]):
        ph = (time_s + offset[k] - axis_shift[k]) % cycle_s
        phase[k] = ph
        if ph < green_s:
            states[k] = _GREEN
        elif ph < green_yellow_s:
            states[k] = _YELLOW
        else:
            states[k] = _RED
