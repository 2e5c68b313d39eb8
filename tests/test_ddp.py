"""PilotNet training with DistributedDataParallel: two gloo processes on the CPU, started by torchrun."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tiny_episodes(tmp_path_factory):
    """Two very short autopilot episodes, recorded by drive.py (as tests/test_pilotnet.py does)."""
    import drive

    folder = tmp_path_factory.mktemp("ddp_episodes")
    assert drive.main(["--driver", "autopilot", "--record", str(folder), "--episodes", "2", "--seconds", "3",
                       "--noise", "--traffic", "0", "--width", "160", "--height", "80"]) == 0
    return folder


@pytest.mark.skipif(not torch.distributed.is_available() or not torch.distributed.is_gloo_available(),
                    reason="torch without the gloo backend")
def test_two_gloo_processes_train_a_model_that_loads_and_drives(tiny_episodes, tmp_path):
    out = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
           "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--standalone",
           str(ROOT / "train.py"), "pilotnet", "--data", str(tiny_episodes), "--out", str(out),
           "--model", str(out / "m.pt"), "--epochs", "1", "--samples-per-epoch", "64", "--batch", "16",
           "--threads", "1", "--validation", "0.5", "--seed", "3", "--device", "cpu"]
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stderr.count("rank 0 of 2") == 1 and proc.stderr.count("rank 1 of 2") == 1, proc.stderr[-3000:]
    # rank 0 alone writes: one log row for the epoch, one model and its ONNX twin
    assert len((out / "log.csv").read_text().strip().splitlines()) == 2
    assert sorted(p.name for p in out.glob("m.*")) == ["m.log.csv", "m.onnx", "m.pt"]
    assert not list(out.glob("*.partial"))

    from towndrive.agent.perception.pilotnet import load_model

    model, meta = load_model(out / "m.pt")
    assert meta["epoch"] == 1 and not any(k.startswith("module.") for k in model.state_dict())

    from dataclasses import replace

    from towndrive.agent.pilotnet_driver import PilotNetDriver
    from towndrive.envs.drive_env import DriveConfig, DriveEnv
    from towndrive.envs.evaluation import run_episode
    from towndrive.sim.world import WorldConfig

    world = replace(WorldConfig(), npc_count=0, pedestrian_count=0)
    drive_env = DriveEnv(DriveConfig(world=world, max_time_s=0.5, terminate_on_infraction=False,
                                     terminate_on_route_deviation=False))
    try:
        trace = run_episode(drive_env, PilotNetDriver(out / "m.pt", backend="torch"), seed=1)
    finally:
        drive_env.close()
    assert len(trace.steer) >= 5 and all(abs(s) <= 1.0 for s in trace.steer)  # it drove a few steps


def test_device_flag_resolves_and_a_missing_gpu_is_one_clear_error():
    from towndrive.agent.training.devices import distributed_from_env, resolve_device

    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    missing = f"cuda:{torch.cuda.device_count() if torch.cuda.is_available() else 0}"
    with pytest.raises(ValueError, match=f"--device {missing}: torch sees"):
        resolve_device(missing)
    with pytest.raises(ValueError, match="expected auto, cpu, cuda or cuda:K"):
        resolve_device("tpu")
    assert not distributed_from_env().enabled or "WORLD_SIZE" in os.environ


def test_train_pilotnet_on_a_missing_gpu_exits_with_one_sentence(tmp_path, capsys):
    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    import train

    assert train.main(["pilotnet", "--data", str(tmp_path), "--out", str(tmp_path / "o"), "--device", "cuda"]) == 2
    assert "--device cuda: torch sees no CUDA device here" in capsys.readouterr().err
