"""Evaluation reports: events with clips, the take-over cost, time standing with nothing in the path,
and the CARLA Leaderboard 2.0 rules one can switch on."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from towndrive.agent.autopilot import Autopilot
from towndrive.envs.drive_env import DriveConfig, DriveEnv
from towndrive.envs.evaluation import evaluate, run_episode
from towndrive.envs.metrics import EpisodeTrace, EvaluationRules, episode_metrics
from towndrive.sim.world import WorldConfig

BLIND = DriveConfig(render_camera=False, world=replace(WorldConfig(), npc_count=6, pedestrian_count=6), max_time_s=30.0)


class Standstill:
    """A driver that never moves: what a false hold looks like to the evaluator."""

    name = "standstill"
    privileged = False
    reason = "holding for a person nobody is standing in"

    def reset(self, env) -> None:
        pass

    def act(self, observation) -> np.ndarray:
        return np.array([0.0, -1.0], np.float32)


def test_a_red_run_is_an_event_with_place_light_and_clip(tmp_path):
    metrics = evaluate(Autopilot(ignore_lights=True), BLIND, 2, 500, tmp_path, video=False, plots=False,
                       options=lambda k: {"town_seed": 100 + k})
    events = [ev for e in metrics["episodes"] for ev in e["events"] if ev["kind"] == "red_light"]
    assert events, "the driver that ignores lights ran no red light in 2 x 30 s"
    ev = events[0]
    assert ev["approach"] >= 0 and ev["other_kind"] == "traffic_light" and ev["speed_mps"] > 0
    clip = tmp_path / "clips" / ev["clip"]
    assert clip.is_file() and clip.stat().st_size > 1000
    table = (tmp_path / "table.md").read_text()
    assert "## Events" in table and ev["clip"] in table
    audit = json.loads((tmp_path / "metrics.json").read_text())["mean"]["audit"]
    assert audit["red_light"]["confirmed"] == len(events)
    assert all(c["unconfirmed"] == 0 and c["missed"] == 0 for c in audit.values())


def test_standing_with_nothing_in_the_path_is_counted_and_the_driver_reason_kept():
    env = DriveEnv(replace(BLIND, max_time_s=10.0, terminate_on_infraction=False))
    rules = EvaluationRules(hold_timeout_s=4.0)
    trace = run_episode(env, Standstill(), 3, options={"town_seed": 100}, rules=rules)
    m = episode_metrics(trace)
    assert m["standing_clear_s"] > 5.0 and m["longest_clear_hold_s"] >= 4.0
    timeouts = [ev for ev in m["events"] if ev["kind"] == "hold_timeout"]
    assert len(timeouts) == 2 and timeouts[0]["reason"] == Standstill.reason
    assert m["infraction_penalty"] == pytest.approx(0.7 ** 2)


def test_the_agent_blocked_rule_ends_the_route():
    env = DriveEnv(replace(BLIND, terminate_on_infraction=False))
    trace = run_episode(env, Standstill(), 3, options={"town_seed": 100}, rules=EvaluationRules(blocked_limit_s=5.0))
    assert trace.elapsed_s == pytest.approx(5.0, abs=0.1)
    assert [ev["kind"] for ev in trace.events] == ["agent_blocked"]
    default = run_episode(env, Standstill(), 3, options={"town_seed": 100})
    assert default.elapsed_s == pytest.approx(30.0, abs=0.1) and default.events == []


def test_the_minimum_speed_rule_uses_the_leaderboard_formula():
    env = DriveEnv(replace(BLIND, max_time_s=40.0, terminate_on_infraction=False))
    slow = Autopilot(target_speed_mps=3.0)
    trace = run_episode(env, slow, 7, options={"town_seed": 101}, rules=EvaluationRules(min_speed=True))
    events = [ev for ev in trace.events if ev["kind"] == "min_speed"]
    assert events, "a car at 3 m/s among 7-11 m/s traffic was never slower than it"
    for ev in events:
        ratio = float(ev["why"].split("%")[0].split()[-1]) / 100
        assert ev["penalty"] == pytest.approx(0.7 + 0.3 * ratio, abs=1e-3) and ratio < 1.0
    m = episode_metrics(trace)
    assert m["infraction_penalty"] == pytest.approx(float(np.prod([ev["penalty"] for ev in events])), rel=1e-5)


def test_a_takeover_costs_its_penalty_and_is_an_event():
    trace = EpisodeTrace(seed=1, route_total_m=100.0, dt_s=0.05, takeover_penalty=0.7)
    info = {"ego": {"x": 0.0, "y": 0.0, "speed_mps": 5.0}, "lane_offset_m": 0.0, "infractions": [],
            "route": {"progress_m": 100.0, "completion": 1.0}, "distance_m": 100.0}
    trace.add_step(info, np.zeros(2))
    trace.interventions = [1.0, 2.0]
    assert episode_metrics(trace)["driving_score"] == pytest.approx(100.0 * 0.49)
    with pytest.raises(ValueError, match="takeover_penalty"):
        EvaluationRules(takeover_penalty=1.5)


def test_drive_until_replays_an_episode_up_to_a_time(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    cmd = [sys.executable, "drive.py", "--driver", "autopilot", "--evaluate", "--seed", "500", "--town-seed", "100",
           "--traffic", "0.3", "--width", "160", "--height", "80", "--until", "2.5", "--out", str(tmp_path)]
    done = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["episodes"][0]["elapsed_s"] == pytest.approx(2.5, abs=0.06)
    assert (tmp_path / "until_2.50s.png").is_file()
    refused = subprocess.run([sys.executable, "drive.py", "--driver", "autopilot", "--until", "2"], cwd=root,
                             capture_output=True, text=True, timeout=120)
    assert refused.returncode == 2 and "--evaluate" in refused.stderr and "Traceback" not in refused.stderr
