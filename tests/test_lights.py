"""Traffic-light phases."""

from __future__ import annotations

import numpy as np

from towndrive.sim.lights import LightTiming, TrafficLights, light_phases
from towndrive.sim.objects import LightState
from towndrive.sim.town import OPPOSITE


def test_opposite_approaches_agree_and_conflicting_ones_are_red(town):
    lights = TrafficLights(town, LightTiming(), np.random.default_rng(0))
    by_node = {}
    for ap in town.approaches:
        by_node.setdefault(ap.node, {})[ap.arm] = ap.index
    for t in np.arange(0.0, 80.0, 0.25):
        lights.update(float(t))
        for arms in by_node.values():
            for arm, idx in arms.items():
                if OPPOSITE[arm] in arms:
                    assert lights.state(idx) == lights.state(arms[OPPOSITE[arm]])
                if lights.state(idx) != LightState.RED:
                    for other, j in arms.items():
                        if other not in (arm, OPPOSITE[arm]):
                            assert lights.state(j) == LightState.RED


def test_phase_durations_follow_the_timing(town):
    timing = LightTiming(green_s=10.0, yellow_s=2.0, all_red_s=1.0)
    lights = TrafficLights(town, timing, np.random.default_rng(1))
    dt = 0.05
    states = []
    for k in range(int(2 * timing.cycle_s / dt)):
        lights.update(k * dt)
        states.append(lights.state(0))
    runs = []
    current, length = states[0], 0
    for s in states[1:]:
        if s == current:
            length += 1
        else:
            runs.append((current, length + 1))
            current, length = s, 0
    full = runs[1:]  # the first run may be cut by the seeded offset
    assert {s for s, _ in full} == {LightState.GREEN, LightState.YELLOW, LightState.RED}
    for state, n in full:
        # red lasts the other axis's green and yellow plus two all-red gaps
        expected = {LightState.GREEN: 10.0, LightState.YELLOW: 2.0, LightState.RED: timing.cycle_s - 12.0}[state]
        assert abs(n * dt - expected) <= dt + 1e-9


def test_compiled_phases_match_the_numpy_formula():
    """``light_phases`` gives the phases and states of the NumPy expression it replaced, bit for bit."""
    rng = np.random.default_rng(7)
    timing = LightTiming()
    offset = np.concatenate([rng.uniform(0.0, timing.cycle_s, 60), [0.0, timing.half_cycle_s, timing.cycle_s]])
    shift = np.where(rng.random(len(offset)) < 0.5, 0.0, timing.half_cycle_s)
    times = np.concatenate([np.round(np.arange(0.0, 400.0, 0.05), 9), rng.uniform(0.0, 1e5, 2000),
                            np.arange(0.0, 200.0) * timing.half_cycle_s])
    phase, states = np.empty(len(offset)), np.empty(len(offset), np.int64)
    for time_s in times.tolist():
        light_phases(time_s, offset, shift, timing.cycle_s, timing.green_s, timing.green_s + timing.yellow_s,
                     phase, states)
        want = (time_s + offset - shift) % timing.cycle_s
        plain = np.full(len(want), int(LightState.RED))
        plain[want < timing.green_s + timing.yellow_s] = int(LightState.YELLOW)
        plain[want < timing.green_s] = int(LightState.GREEN)
        assert phase.tobytes() == want.tobytes()
        assert states.tolist() == plain.tolist()
