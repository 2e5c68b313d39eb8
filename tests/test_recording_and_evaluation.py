"""Drivers, recording episodes (atomic, interrupt-safe), the scenario suite and closed-loop metrics."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from towndrive.agent.autopilot import Autopilot
from towndrive.agent.drivers import make_driver
from towndrive.data.episodes import EpisodeError, list_episodes, read_episode
from towndrive.envs.drive_env import DriveConfig, DriveEnv
from towndrive.envs.evaluation import run_episode
from towndrive.envs.metrics import EpisodeTrace, aggregate, episode_metrics
from towndrive.envs.scenarios import SCENARIOS, run_scenario
from towndrive.sim.render import CameraConfig

ROOT = Path(__file__).resolve().parents[1]
SMALL = CameraConfig(width=200, height=66)
BLIND = replace(DriveConfig(render_camera=False), terminate_on_infraction=False, terminate_on_route_deviation=False)


def test_unknown_driver_is_one_clear_error():
    with pytest.raises(ValueError, match="Unknown driver 'robot'; choose one of"):
        make_driver("robot")
    assert make_driver("autopilot").privileged


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_autopilot_passes_scenario(name):
    result = run_scenario(name, Autopilot(), DriveConfig(render_camera=False))
    assert result.passed, result.detail


def test_autopilot_drives_seeded_routes_with_traffic_cleanly():
    env = DriveEnv(BLIND)
    scores = []
    for seed in (100, 104, 107):
        m = episode_metrics(run_episode(env, Autopilot(), seed))
        scores.append(m["driving_score"])
        assert m["infractions"] == {} and m["interventions"] == 0, m
    assert min(scores) >= 98.0


def test_the_safety_driver_puts_the_car_back_and_tells_the_driver():
    class Swerver:
        """Steers hard right at speed: off its lane within seconds, again after every intervention."""

        name, privileged = "swerver", False

        def __init__(self) -> None:
            self.restarts = 0
            self.first_speeds: list[float] = []  # the speed each re-engagement first sees

        def reset(self, env) -> None:
            pass

        def act(self, observation) -> np.ndarray:
            if len(self.first_speeds) < self.restarts:
                self.first_speeds.append(float(observation["speed"][0]))
            return np.array([0.5, 0.6], np.float32)

        def on_intervention(self) -> None:
            self.restarts += 1

    driver = Swerver()
    trace = run_episode(DriveEnv(replace(BLIND, max_time_s=12.0)), driver, 100)
    assert len(trace.interventions) >= 1
    assert driver.restarts == len(trace.interventions)
    assert driver.first_speeds and max(driver.first_speeds) == 0.0  # where the car stands now, not the last step


def test_noise_injection_perturbs_but_labels_stay_clean():
    env = DriveEnv(BLIND)
    obs, _ = env.reset(seed=3)
    driver = Autopilot(noise=True, noise_seed=1, noise_every_s=(1.0, 2.0))
    driver.reset(env)
    perturbed = 0
    for _ in range(200):
        action = driver.act(obs)
        perturbed += not np.allclose(action, driver.clean_action)
        obs, _, term, trunc, info = env.step(action)
        assert not term
    assert perturbed > 10
    assert abs(info["lane_offset_m"]) < 1.0  # it recovered


def test_metrics_follow_the_leaderboard_rules():
    trace = EpisodeTrace(seed=1, route_total_m=400.0, dt_s=0.05)
    info = {"ego": {"x": 0.0, "y": 0.0, "speed_mps": 5.0}, "lane_offset_m": 0.2, "infractions": [],
            "route": {"progress_m": 300.0, "completion": 0.75}, "distance_m": 500.0}
    for _ in range(1200):  # 60 s
        trace.add_step(info, np.zeros(2))
    trace.infractions = [{"kind": "collision_vehicle"}, {"kind": "red_light"}, {"kind": "wrong_way"}]
    trace.interventions = [10.0]
    m = episode_metrics(trace)
    assert m["route_completion"] == pytest.approx(75.0)
    assert m["infraction_penalty"] == pytest.approx(0.6 * 0.7 * 0.7)  # the take-over costs 0.7 too
    assert m["driving_score"] == pytest.approx(75.0 * 0.294)
    assert m["autonomy"] == pytest.approx((1 - 6.0 / 60.0) * 100)
    assert m["infractions_per_km"]["red_light"] == pytest.approx(2.0)
    assert aggregate([m, m])["driving_score"] == pytest.approx(m["driving_score"])


def _record(tmp: Path, episodes: int, seconds: float, extra: list[str] | None = None) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "drive.py", "--driver", "autopilot", "--record", str(tmp), "--episodes", str(episodes),
           "--seconds", str(seconds), "--width", "200", "--height", "66", *(extra or [])]
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)


def test_recording_round_trips_through_hdf5(tmp_path):
    done = _record(tmp_path, 2, 3.0, ["--depth", "--noise"])
    assert done.returncode == 0, done.stderr[-2000:]
    paths = list_episodes(tmp_path)
    assert [p.name for p in paths] == ["episode_00000.h5", "episode_00001.h5"]
    ep = read_episode(paths[1])
    assert ep.steps == 60 and ep.frames.shape == (60, 66, 200, 3) and ep.extras["depth"].shape == (60, 66, 200)
    assert ep.attrs["seed"] == 1 and ep.attrs["driver"] == "autopilot" and ep.attrs["camera"]["width"] == 200
    assert np.all(np.abs(ep.actions) <= 1.0) and ep.speed.max() > 1.0
    # The recorded frames are the simulator's: replaying the seed renders the same first frame.
    env = DriveEnv(DriveConfig(camera=SMALL))
    obs, _ = env.reset(seed=1)
    assert np.array_equal(obs["image"], ep.frames[0])
    env.close()
    assert not list(tmp_path.glob("*.partial"))


def test_interrupted_recording_keeps_every_finished_episode(tmp_path):
    cmd = [sys.executable, "drive.py", "--driver", "autopilot", "--record", str(tmp_path), "--episodes", "50",
           "--seconds", "1.5", "--width", "200", "--height", "66"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while time.time() < deadline and len(list(tmp_path.glob("episode_*.h5"))) < 2:
        time.sleep(0.2)
    time.sleep(0.3)  # let it get into the middle of the next episode
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err[-2000:]
    assert "kept" in err and "dropped the one in progress" in err
    kept = list_episodes(tmp_path)
    assert len(kept) >= 2
    for path in kept:
        assert read_episode(path).steps == 30  # every kept episode is whole
    assert not list(tmp_path.glob("*.partial"))


def test_corrupt_episode_is_reported_by_name(tmp_path):
    bad = tmp_path / "episode_00003.h5"
    bad.write_bytes(os.urandom(2048))
    with pytest.raises(EpisodeError, match="episode_00003.h5"):
        read_episode(bad)


def test_evaluate_writes_metrics_table_plots_and_video(tmp_path):
    cmd = [sys.executable, "drive.py", "--driver", "autopilot", "--evaluate", "--episodes", "2", "--seed", "5",
           "--seconds", "12", "--width", "200", "--height", "66", "--out", str(tmp_path)]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    for key in ("route_completion", "infraction_penalty", "driving_score", "autonomy", "infractions_per_km"):
        assert key in metrics["mean"] and key in metrics["episodes"][0]
    assert len(metrics["episodes"]) == 2 and metrics["mean"]["episodes"] == 2
    assert (tmp_path / "table.md").read_text().startswith("# Closed-loop evaluation: autopilot")
    assert (tmp_path / "video.mp4").stat().st_size > 10_000
    assert (tmp_path / "plots" / "trajectory_seed5.png").exists()
    assert (tmp_path / "plots" / "speed_steer_seed6.png").exists()


def test_scenario_cli_prints_a_table_and_rejects_unknown_names(tmp_path):
    done = subprocess.run([sys.executable, "drive.py", "--driver", "autopilot", "--scenario", "red_light", "--no-video",
                           "--out", str(tmp_path)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "| red_light | PASS |" in done.stdout and "1 passed, 0 failed" in done.stdout
    assert json.loads((tmp_path / "results.json").read_text())[0]["passed"] is True
    bad = subprocess.run([sys.executable, "drive.py", "--scenario", "moon_landing"], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert bad.returncode == 2 and "Unknown scenario 'moon_landing'" in bad.stderr
