"""PilotNet and detector training with DistributedDataParallel: two gloo processes on the CPU, started by torchrun."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "data" / "models"
needs_gloo = pytest.mark.skipif(not torch.distributed.is_available() or not torch.distributed.is_gloo_available(),
                                reason="torch without the gloo backend")


def torchrun(*train_args: str, processes: int = 2) -> subprocess.CompletedProcess:
    """``torchrun --standalone --nproc_per_node N train.py ARGS`` on the CPU, one thread per process."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
           "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", str(processes), "--standalone",
           str(ROOT / "train.py"), *train_args]
    return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=240)


@pytest.fixture(scope="module")
def tiny_episodes(tmp_path_factory):
    """Two very short autopilot episodes, recorded by drive.py (as tests/test_pilotnet.py does)."""
    import drive

    folder = tmp_path_factory.mktemp("ddp_episodes")
    assert drive.main(["--driver", "autopilot", "--record", str(folder), "--episodes", "2", "--seconds", "3",
                       "--noise", "--traffic", "0", "--width", "160", "--height", "80"]) == 0
    return folder


@needs_gloo
def test_two_gloo_processes_train_a_model_that_loads_and_drives(tiny_episodes, tmp_path):
    out = tmp_path / "run"
    proc = torchrun("pilotnet", "--data", str(tiny_episodes), "--out", str(out), "--model", str(out / "m.pt"),
                    "--epochs", "1", "--samples-per-epoch", "64", "--batch", "16", "--threads", "1", "--validation",
                    "0.5", "--seed", "3", "--device", "cpu")
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


@pytest.fixture(scope="module")
def tiny_detector_dataset(tmp_path_factory):
    """Eight auto-labelled training frames and four validation frames (YOLO layout), from the autolabeller."""
    from towndrive.agent.training.autolabel import SplitSpec, generate_split, write_dataset_yaml

    root = tmp_path_factory.mktemp("detector_dataset")
    generate_split(root, SplitSpec("train", (0,), ("noon",), 8, frames_per_episode=8), 0, progress=False)
    generate_split(root, SplitSpec("val", (100,), ("dusk",), 4, frames_per_episode=4), 0, progress=False)
    write_dataset_yaml(root)
    return root


@needs_gloo
@pytest.mark.skipif(not (MODELS / "detector.pt").is_file(), reason="no shipped detector to start from")
def test_two_gloo_processes_train_a_detector_that_detects_like_a_single_process_one(tiny_detector_dataset, tmp_path,
                                                                                    town):
    """One epoch from the shipped weights (--init, a small learning rate), in one process with batch 2 and in two
    torchrun processes with batch 1 each (with a loader worker each): both checkpoints load and find the same
    car."""
    import train

    common = ["--data", str(tiny_detector_dataset), "--epochs", "1", "--lr", "1e-4", "--seed", "0", "--threads", "1",
              "--device", "cpu", "--init", str(MODELS / "detector.pt")]
    single, ddp = tmp_path / "single.pt", tmp_path / "ddp.pt"
    assert train.main(["detector", "train", *common, "--batch", "2", "--out", str(single)]) == 0
    proc = torchrun("detector", "train", *common, "--batch", "1", "--loader-workers", "1", "--out", str(ddp))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.count("rank 0 of 2") == 1 and proc.stdout.count("rank 1 of 2") == 1, proc.stdout[-3000:]
    assert "4 steps/epoch" in proc.stdout  # 8 frames, 2 processes, batch 1: each trains on its half
    assert len(ddp.with_suffix(".log.jsonl").read_text().splitlines()) == 1  # rank 0 alone logs and saves

    from towndrive.agent.perception.checkpoints import load_checkpoint
    from towndrive.agent.perception.detections import box_iou
    from towndrive.agent.perception.detector import TorchDetector
    from towndrive.agent.training.autolabel import render_and_label
    from towndrive.sim.objects import SemanticClass
    from towndrive.sim.render import CameraConfig, SceneRenderer
    from towndrive.sim.world import World, WorldConfig

    ckpt = load_checkpoint(ddp, "detector")
    assert ckpt["epoch"] == 1 and not any(k.startswith("module.") for k in ckpt["state_dict"])
    shipped = load_checkpoint(MODELS / "detector.pt", "detector")["state_dict"]
    assert any(not torch.equal(v, shipped[k]) for k, v in ckpt["state_dict"].items())  # it did train

    world = World(town, WorldConfig(npc_count=0, pedestrian_count=0), seed=5, spawn_traffic=False)
    lane, s = world.ego_lane[0], world.ego_lane[1]
    world.spawn_npc(lane, s + 18.0, kind=SemanticClass.CAR, color=(0.2, 0.3, 0.8))
    renderer = SceneRenderer(town, seed=town.seed)
    try:
        frame, labels = render_and_label(renderer, world, CameraConfig(), "noon")
    finally:
        renderer.close()
    car = np.array([next(lab for lab in labels if lab.name == "car").box], np.float32)
    found = {}
    for name, path in (("single", single), ("ddp", ddp)):
        cars = [d for d in TorchDetector(path)(frame.rgb) if d.name == "car"]
        assert cars, f"the {name}-process detector missed a car 17 m ahead"
        best = max(cars, key=lambda d: box_iou(np.array([d.box]), car)[0, 0])
        assert box_iou(np.array([best.box]), car)[0, 0] >= 0.5, name
        found[name] = np.array([best.box])
    assert box_iou(found["single"], found["ddp"])[0, 0] >= 0.8
