"""PilotNet speed: training throughput and inference latency, torch versus ONNX Runtime.

Training: frames per second through the whole training step (balanced sampling, augmentation, forward,
backward, Adam) on 1 and 2 threads, batch 64, on frames from the simulator, in fp32 and with bf16
autocast. Inference: one frame at a time as the driver runs it (preprocess, then the network), p50 and
p95, with torch and with ONNX Runtime on the shipped model, 1 thread each (the other core is the
simulator's). The ratio torch / ONNX Runtime is measured in the same run.

Run: ``python bench/bench_pilotnet.py [--model data/models/pilotnet.pt]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.timing import measure  # noqa: E402
from towndrive.agent.perception.pilotnet import DEFAULT_MODEL, PilotNetModel, build, preprocess, to_tensor  # noqa: E402  # noqa: E402
from towndrive.agent.training.pilotnet_data import Augmenter, FrameSet, balance_weights  # noqa: E402
from towndrive.agent.training.pilotnet_training import _batches  # noqa: E402
from towndrive.envs.drive_env import DriveConfig, DriveEnv  # noqa: E402
from towndrive.sim.render import CameraConfig  # noqa: E402


def sim_frames(n: int) -> list[np.ndarray]:
    """Camera frames from a short autopilot drive (real pictures, not noise)."""
    from towndrive.agent.autopilot import Autopilot

    env = DriveEnv(DriveConfig())
    obs, _ = env.reset(seed=4)
    driver = Autopilot()
    driver.reset(env)
    frames = []
    for _ in range(n):
        obs, _, terminated, truncated, _ = env.step(driver.act(obs))
        if terminated or truncated:  # the episode is over: reset() would come next, so stop here
            break
        frames.append(obs["image"])
    env.close()
    return frames


def training_throughput(frames: list[np.ndarray], threads: int, batches: int, bf16: bool) -> float:
    torch.set_num_threads(threads)
    images = np.stack([preprocess(f) for f in frames])
    n = len(images)
    rng = np.random.default_rng(0)
    data = FrameSet(images, rng.uniform(-0.5, 0.5, n).astype(np.float32), np.full(n, 8.0, np.float32),
                    rng.integers(0, 4, n), np.zeros(n, np.int64), [])
    model = build(conditional=True).train()
    opt = torch.optim.Adam(model.parameters(), 1e-3)
    batch = 64
    it = _batches(rng, data, balance_weights(data.steer), batch * (batches + 2), batch, Augmenter(CameraConfig()))
    for k, (x, cmd, y) in enumerate(it):
        if k == 2:
            t0 = time.perf_counter()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            pred = model(x, cmd)
        loss = torch.nn.functional.mse_loss(pred[:, 0].float(), y)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return batch * batches / (time.perf_counter() - t0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    ap.add_argument("--batches", type=int, default=20)
    args = ap.parse_args()
    frames = sim_frames(200)
    print("Training throughput (conditional PilotNet, batch 64, augmentation on):")
    for threads in (1, 2):
        fp32 = training_throughput(frames, threads, args.batches, bf16=False)
        bf16 = training_throughput(frames, threads, args.batches, bf16=True)
        print(f"  {threads} thread(s): fp32 {fp32:6.0f} frames/s, bf16 autocast {bf16:6.0f} frames/s ({bf16 / fp32:.2f}x)")
    print("Inference, one frame at a time, 1 thread:")
    frame = frames[100]
    pre = measure(lambda: preprocess(frame), repeats=300)
    print(f"  preprocess (crop, resize, YUV)  {pre}")
    results = {}
    for backend in ("torch", "onnx"):
        net = PilotNetModel(args.model, backend=backend, threads=1)
        x = to_tensor(preprocess(frame))
        if backend == "torch":
            cmd = torch.tensor([0])
            with torch.no_grad():
                results[backend] = measure(lambda net=net, x=x, cmd=cmd: net.model(x, cmd) if net.conditional
                                           else net.model(x), repeats=300)
        else:
            feeds = {"image": x.numpy()}
            if net.conditional:
                feeds["command"] = np.array([0], np.int64)
            results[backend] = measure(lambda net=net, feeds=feeds: net.session.run(["steer"], feeds), repeats=300)
        full = measure(lambda net=net: net.steer(frame, 0), repeats=300)
        print(f"  {backend:>5} network {results[backend]};  preprocess + network {full}")
    print(f"  torch / ONNX Runtime (network p50): {results['torch'].p50_ms / results['onnx'].p50_ms:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
