"""A short property-based fuzz of what comes into the env from outside: reset options and actions.

Whatever hypothesis draws, the env either takes it or refuses it with one ``ValueError`` sentence that names
the offending input, and never hangs, crashes or returns a non-finite observation. A few seconds in all: the env
has no camera and the towns come from a small set (a new town costs about a second to generate)."""

from __future__ import annotations

import math

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from towndrive.envs.drive_env import DriveConfig, DriveEnv  # noqa: E402

ANY_NUMBER = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-(2**70), 2**70), st.booleans(),
                       st.text(max_size=3), st.none())
OPTIONS = st.fixed_dictionaries({}, optional={
    "traffic_density": st.one_of(ANY_NUMBER, st.floats(0.0, 2.0)),
    "town_seed": st.one_of(ANY_NUMBER, st.sampled_from([0, 1])),
    "weather": st.one_of(st.sampled_from(["noon", "night", "fog", ""]), ANY_NUMBER),
    "start": st.one_of(ANY_NUMBER, st.tuples(st.text(max_size=5), st.text(max_size=5), st.integers(-1, 3)),
                       st.just(("0-0Eo", "1-0Wi", 0))),
    "goal": st.one_of(ANY_NUMBER, st.tuples(st.text(max_size=5), st.text(max_size=5))),
    "typo_option": ANY_NUMBER,
})


@pytest.fixture(scope="module")
def env():
    e = DriveEnv(DriveConfig(render_camera=False, max_time_s=5.0))
    yield e
    e.close()


def _check_obs(obs: dict) -> None:
    assert np.all(np.isfinite(obs["speed"])) and 0 <= obs["command"] <= 3


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(options=OPTIONS, seed=st.one_of(st.none(), st.integers(0, 2**32 - 1), st.integers(-5, -1), st.floats(0, 10)))
def test_reset_options_are_taken_or_refused_by_name(env: DriveEnv, options: dict, seed) -> None:
    try:
        obs, info = env.reset(seed=seed, options=options)
    except ValueError as exc:
        message = str(exc)
        assert "\n" not in message and message.endswith(".")
        named = [k for k in options if k in message] + (["seed"] if "seed" in message else [])
        assert named, message  # the sentence names what was wrong
        return
    _check_obs(obs)
    assert math.isfinite(info["route"]["total_m"])


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(actions=st.lists(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=0, max_size=3),
                        min_size=1, max_size=12))
def test_actions_are_taken_or_refused(env: DriveEnv, actions: list[list[float]]) -> None:
    env.reset(seed=0, options={"town_seed": 0})
    for action in actions:
        try:
            obs, reward, terminated, truncated, _ = env.step(np.array(action, np.float32))
        except ValueError as exc:
            assert "Action must be two finite numbers" in str(exc)
            continue
        _check_obs(obs)
        assert math.isfinite(reward)
        if terminated or truncated:
            break
