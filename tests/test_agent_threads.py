"""The agent on two threads, and pipelined, decides exactly what it decides serially.

Why: a frame's independent stages run at the same time (``AgentConfig.stage_threads``) only because the actions
stay bit for bit those of the serial order; and the pipelined agent must be the serial one with one frame of
latency, nothing else. The frames are recorded once from the env (open loop), so every driver sees the same.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from towndrive.agent.agent_driver import DEFAULT_DETECTOR, AgentDriver
from towndrive.agent.decision.blind_spot import VEHICLES
from towndrive.agent.perception.pilotnet import DEFAULT_MODEL
from towndrive.envs.driver_context import DriverContext
from towndrive.sim.spec import CAMERA, MIRRORS

needs_models = pytest.mark.skipif(not (DEFAULT_MODEL.is_file() and DEFAULT_DETECTOR.is_file()),
                                  reason="the shipped PilotNet and detector models are not in data/models")
FRAMES = 24


@pytest.fixture(scope="module")
def recorded() -> tuple[list[dict[str, Any]], list[dict[str, np.ndarray]]]:
    """Observations of an autopilot drive with traffic, and both mirror frames of each step."""
    from towndrive.agent.autopilot import Autopilot
    from towndrive.envs.drive_env import DriveConfig, DriveEnv

    env = DriveEnv(DriveConfig(terminate_on_infraction=False, terminate_on_route_deviation=False))
    try:
        obs, _ = env.reset(seed=3)
        pilot = Autopilot()
        pilot.reset(env)
        observations, mirrors = [], []
        for k in range(FRAMES):
            # Ask for lane changes now and then, so that the mirror look holds one on some frames.
            observations.append({**obs, "command": 2 if 8 <= k < 16 else int(obs["command"])})
            mirrors.append({side: env.blind_spot_frame(side) for side in ("left", "right")})
            obs, *_ = env.step(pilot.act(obs))
    finally:
        env.close()
    return observations, mirrors


def drive(driver: AgentDriver, recorded: tuple[list[dict[str, Any]], list[dict[str, np.ndarray]]]
          ) -> tuple[list[np.ndarray], list[str], list[tuple[str, int]]]:
    observations, mirrors = recorded
    now = {"k": 0}
    looks: list[tuple[str, int]] = []

    def look(side: str) -> np.ndarray:
        looks.append((side, now["k"]))
        return mirrors[now["k"]][side]

    driver.reset(DriverContext(camera=CAMERA, dt_s=0.05, mirror_camera=MIRRORS.camera, mirror_frame=look))
    actions, reasons = [], []
    for k, obs in enumerate(observations):
        now["k"] = k
        actions.append(np.asarray(driver.act(obs)).copy())
        reasons.append(driver.reason)
    driver.adas_summary()
    return actions, reasons, looks


@needs_models
def test_two_threads_decide_bit_for_bit_what_one_thread_decides(recorded) -> None:
    serial = drive(AgentDriver(stage_threads=1), recorded)
    threaded = drive(AgentDriver(stage_threads=2), recorded)
    assert serial[2], "the mirror look must be exercised"
    assert [a.tobytes() for a in threaded[0]] == [a.tobytes() for a in serial[0]]
    assert threaded[1] == serial[1]
    assert threaded[2] == serial[2]


@needs_models
def test_switching_between_one_and_two_threads_changes_nothing(recorded) -> None:
    from towndrive.agent.agent_driver import StageThreadChoice

    serial = drive(AgentDriver(stage_threads=1), recorded)
    chooser = AgentDriver(stage_threads=0)
    chooser._threads = StageThreadChoice(period=8, trial=2)  # try, choose and try again within the short drive
    chooser._threads.frame = 0
    switching = drive(chooser, recorded)
    assert [a.tobytes() for a in switching[0]] == [a.tobytes() for a in serial[0]]
    assert switching[1] == serial[1]


def test_the_faster_thread_count_is_kept() -> None:
    from towndrive.agent.agent_driver import StageThreadChoice

    choice = StageThreadChoice(period=10, trial=2)
    choice.frame = 0
    tried = []
    for _ in range(10):
        n = choice.now()
        tried.append(n)
        choice.took(n, 0.010 if n == 1 else 0.020)  # one thread faster: the machine's cores are taken
    assert tried == [1, 1, 2, 2, 1, 1, 1, 1, 1, 1]
    for _ in range(10):
        n = choice.now()
        choice.took(n, 0.020 if n == 1 else 0.010)
    assert choice.chosen == 2  # the machine freed a core: two threads again


@needs_models
def test_the_pipelined_agent_is_the_serial_one_a_frame_late(recorded) -> None:
    serial = drive(AgentDriver(stage_threads=1), recorded)
    piped = drive(AgentDriver(pipeline=True), recorded)
    # Frame 0 is decided at once and given again on frame 1; from then on frame k gets frame k-1's action.
    expected = [serial[0][0]] + serial[0][:-1]
    assert [a.tobytes() for a in piped[0]] == [a.tobytes() for a in expected]
    assert piped[1] == [serial[1][0]] + serial[1][:-1]
    assert piped[2] == serial[2]  # the same mirror frames, rendered ahead on the caller's thread


@needs_models
def test_the_mirror_look_finds_the_vehicles_the_full_detector_finds(recorded) -> None:
    from towndrive.agent.agent_driver import DEFAULT_REFINER
    from towndrive.agent.perception.detector import OnnxDetector

    detector = OnnxDetector(DEFAULT_DETECTOR, 0.35, threads=1, refiner=DEFAULT_REFINER)
    found = 0
    for frames in recorded[1]:
        for rgb in frames.values():
            full = sorted((d.box, d.cls, d.score) for d in detector(rgb) if d.name in VEHICLES)
            only = sorted((d.box, d.cls, d.score) for d in detector.detect_only(rgb, VEHICLES))
            assert only == full
            found += len(only)
    assert found > 0


def test_stage_threads_is_checked() -> None:
    with pytest.raises(ValueError, match="stage_threads"):
        AgentDriver(net=object(), detect=lambda rgb: [], stage_threads=3)


def test_a_failing_stage_leaves_no_worker_stage_running() -> None:
    import threading
    import time

    running = threading.Event()

    def slow_detector(rgb: np.ndarray) -> list:
        running.set()
        time.sleep(0.05)
        running.clear()
        return []

    class FailingNet:
        def steer(self, rgb: np.ndarray, command: int) -> float:
            raise ValueError("no steering")

    driver = AgentDriver(net=FailingNet(), detect=slow_detector, stage_threads=2)
    driver.reset(DriverContext(camera=CAMERA, dt_s=0.05))
    obs = {"image": np.zeros((CAMERA.height, CAMERA.width, 3), np.uint8), "speed": np.zeros(1, np.float32),
           "command": 0}
    with pytest.raises(ValueError, match="no steering"):
        driver.act(obs)
    assert not running.is_set()  # the detector had finished before the error came out
