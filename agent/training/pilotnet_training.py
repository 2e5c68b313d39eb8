"""Train PilotNet (behavioural cloning) on recorded episodes, export it to ONNX, and optionally run DAgger.

  python train.py pilotnet --data data/episodes/autopilot --out out/pilotnet --epochs 12 --seed 0
  python train.py pilotnet --data ... --resume                 # continue from out/pilotnet/last.pt
  python train.py pilotnet --data ... --dagger 2               # then DAgger rounds (see agent.training.pilotnet_dagger)
  python train.py pilotnet --data ... --loader-workers 2      # batches built by 2 DataLoader worker processes
  torchrun --standalone --nproc_per_node 2 train.py pilotnet --data ...   # DistributedDataParallel, one process per GPU

A run folder holds ``last.pt`` (every epoch, for resuming), ``best.pt`` (lowest validation loss),
``log.csv`` and ``loss.png``. At the end the best checkpoint is written to ``--model`` (default
``data/models/pilotnet.pt``) with its ONNX twin, checked against torch within 1e-4.
Training is deterministic for a seed: sampling drawn from the seed, and torch's generator seeded per epoch;
augmentation in one stream in the training process (``--loader-workers 0``, the default), or with loader workers
from a generator per batch, so the weights are the same for any number of them (``loaders.py``).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import functools
import json
import math
import shutil
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from towndrive.agent.perception.checkpoints import load_checkpoint
from towndrive.agent.perception.pilotnet import (
    DEFAULT_CROP,
    INPUT_HEIGHT,
    INPUT_WIDTH,
    Crop,
    build,
    load_model,  # noqa: F401 (re-exported)
    parameter_count,
    to_tensor,
)
from towndrive.agent.training.devices import (
    Distributed,
    autocast,
    backward_step,
    data_parallel,
    grad_scaler,
    process_group,
    start_training,
    to_device,
)
from towndrive.agent.training.loaders import SeededBatches, batch_loader, check_loader_workers, seed_of
from towndrive.agent.training.outputs import replace_shipped
from towndrive.agent.training.pilotnet_args import add_arguments as pilotnet_arguments
from towndrive.agent.training.pilotnet_data import Augment, Augmenter, FrameSet, balance_weights, load_frames, split_by_episode
from towndrive.data.episodes import EpisodeError
from towndrive.sim.render import CameraConfig

add_arguments = pilotnet_arguments  # the flags live in a light module (help answers at once)


# --------------------------------------------------------------------------- checkpoints
def save_checkpoint(path: Path, model: torch.nn.Module, extra: dict[str, Any]) -> None:
    from towndrive.agent.perception.checkpoints import save_checkpoint as save

    model = getattr(model, "module", model)  # DistributedDataParallel: the model inside
    content = {"state_dict": model.state_dict(), **extra}
    if any(p.device.type != "cpu" for p in model.parameters()):
        content = _to_cpu(content)  # a GPU run's checkpoint loads on any machine
    save(path, content)


def _to_cpu(value: Any) -> Any:
    if isinstance(value, torch.Tensor):
        return value.detach().cpu()
    if isinstance(value, dict):
        return {k: _to_cpu(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_to_cpu(v) for v in value]
    return value


def export(model: torch.nn.Module, meta: dict[str, Any], pt_path: Path) -> float:
    """Write ``pt_path`` (weights + metadata) and its ``.onnx``; return ONNX Runtime's largest difference."""
    from towndrive.agent.deploy.onnx_export import export_onnx

    pt_path.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(pt_path, model, meta)
    gen = torch.Generator().manual_seed(0)
    image = torch.rand(4, 3, INPUT_HEIGHT, INPUT_WIDTH, generator=gen) * 255.0
    onnx_meta = {"pilotnet_meta": json.dumps({"conditional": bool(meta.get("conditional", False)),
                                              "crop": dict(meta.get("crop", {}))})}
    if getattr(model, "conditional", False):
        command = torch.tensor([0, 1, 2, 3], dtype=torch.int64)
        return export_onnx(model, [image, command], pt_path.with_suffix(".onnx"), ["image", "command"], ["steer"],
                           metadata=onnx_meta)
    return export_onnx(model, [image], pt_path.with_suffix(".onnx"), ["image"], ["steer"], metadata=onnx_meta)


# --------------------------------------------------------------------------- training
def predict(model: torch.nn.Module, images: np.ndarray, command: np.ndarray, batch: int = 256) -> np.ndarray:
    out = []
    model = getattr(model, "module", model)
    device = next(model.parameters()).device
    with torch.no_grad():
        for i in range(0, len(images), batch):
            x = to_device(to_tensor(images[i:i + batch]), device)
            c = to_device(torch.from_numpy(command[i:i + batch]), device)
            y = model(x, c) if model.conditional else model(x)
            out.append(y[:, 0].float().cpu().numpy())
    return np.concatenate(out) if out else np.zeros(0, np.float32)


def _batches(rng: np.random.Generator, train: FrameSet, weights: np.ndarray, samples: int, batch: int,
             augmenter: Augmenter | None):
    """Balanced draws with replacement, augmented, in this process from one stream (``--loader-workers 0``);
    yields (images, commands, steer) tensors."""
    picks = rng.choice(len(train), size=samples, p=weights)
    for i in range(0, samples, batch):
        yield _batch(rng, picks[i:i + batch], train, augmenter)


def _batch(rng: np.random.Generator, idx: np.ndarray, train: FrameSet,
           augmenter: Augmenter | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One batch of the frames ``idx``, augmented with draws from ``rng``."""
    imgs = np.empty((len(idx), INPUT_HEIGHT, INPUT_WIDTH, 3), np.uint8)
    steer = np.empty(len(idx), np.float32)
    cmd = np.empty(len(idx), np.int64)
    for j, k in enumerate(idx):
        if augmenter is None:
            imgs[j], steer[j], cmd[j] = train.images[k], train.steer[k], train.command[k]
        else:
            imgs[j], steer[j], cmd[j] = augmenter(rng, train.images[k], float(train.steer[k]),
                                                  float(train.speed[k]), int(train.command[k]))
    return to_tensor(imgs), torch.from_numpy(cmd), torch.from_numpy(steer)


def epoch_batches(rng: np.random.Generator, train: FrameSet, weights: np.ndarray, samples: int, batch: int,
                  augmenter: Augmenter | None, workers: int, key: tuple[int, ...], device: torch.device):
    """The epoch's batches: drawn from ``rng`` here (``workers`` 0), or built by ``workers`` DataLoader processes,
    batch b augmented from a generator seeded by ``(*key, b)`` (the same batches for any number of workers)."""
    if workers == 0:
        return _batches(rng, train, weights, samples, batch, augmenter)
    picks = rng.choice(len(train), size=samples, p=weights)
    make = functools.partial(_batch, train=train, augmenter=augmenter)
    return batch_loader(SeededBatches(make, picks, batch, key), workers, device, seed=seed_of(key))


def fit(model: torch.nn.Module, train: FrameSet, val: FrameSet, args: argparse.Namespace, out: Path,
        first_epoch: int = 0, optimizer_state: dict | None = None, best_val: float = math.inf,
        epochs: int | None = None, meta: dict[str, Any] | None = None, dist: Distributed | None = None) -> float:
    """Train for ``epochs`` epochs from ``first_epoch``; checkpoint every epoch; return the best val loss.

    ``model`` may be wrapped in DistributedDataParallel (``dist`` enabled): each rank then draws its own share of
    the epoch's samples from a seed of its own, and only rank 0 validates, logs and writes checkpoints."""
    epochs = args.epochs if epochs is None else epochs
    dist = dist or Distributed()
    net = getattr(model, "module", model)
    device = next(net.parameters()).device
    scaler = grad_scaler(device) if _cuda_mixed(args, device) else None
    opt = torch.optim.Adam(model.parameters(), lr=args.lr)
    if optimizer_state:
        opt.load_state_dict(optimizer_state)
    total = first_epoch + epochs
    sched = torch.optim.lr_scheduler.LambdaLR(  # cosine over all epochs, resumed where it stopped
        opt, lambda e: 0.5 * (1 + math.cos(math.pi * min(e + first_epoch, total) / max(total, 1))))
    weights = balance_weights(train.steer)
    samples = args.samples_per_epoch or len(train)
    if dist.enabled:  # every rank the same number of batches, so that their all-reduces pair up
        samples = math.ceil(samples / dist.world_size)
    augmenter = None if args.no_augment else Augmenter(
        CameraConfig(), Augment(flip_p=0.0 if args.no_flip else 0.5))
    workers = check_loader_workers(getattr(args, "loader_workers", 0))
    log_path = out / "log.csv"
    new_log = not log_path.exists() or first_epoch == 0
    with log_path.open("w" if new_log else "a", newline="") if dist.is_main else contextlib.nullcontext() as fh:
        log = csv.writer(fh) if fh is not None else None
        if new_log and log is not None:
            log.writerow(["epoch", "train_loss", "val_loss", "val_mae", "lr", "frames_per_s", "seconds"])
        for epoch in range(first_epoch, first_epoch + epochs):
            if dist.enabled:  # a shard of its own per rank
                rng = np.random.default_rng((args.seed, epoch, dist.rank))
                torch.manual_seed(args.seed * 1000 + epoch + 7919 * dist.rank)
            else:
                rng = np.random.default_rng((args.seed, epoch))
                torch.manual_seed(args.seed * 1000 + epoch)
            model.train()
            t0, losses = time.perf_counter(), []
            batches = epoch_batches(rng, train, weights, samples, args.batch, augmenter, workers,
                                    (args.seed, epoch, dist.rank), device)
            bar = tqdm(batches, total=math.ceil(samples / args.batch),
                       desc=f"epoch {epoch + 1}/{total}", unit="batch", mininterval=2.0, file=sys.stderr,
                       disable=not dist.is_main)
            for x, cmd, y in bar:
                x, cmd, y = to_device(x, device), to_device(cmd, device), to_device(y, device)  # CUDA: pinned copies
                with _precision(args, device):
                    pred = model(x, cmd) if net.conditional else model(x)
                loss = torch.nn.functional.mse_loss(pred[:, 0].float(), y)
                opt.zero_grad()
                backward_step(loss, opt, scaler)
                losses.append(loss.item())
                bar.set_postfix(loss=f"{np.mean(losses[-50:]):.4f}")
            sched.step()
            seconds = time.perf_counter() - t0
            if not dist.is_main:
                dist.barrier()  # rank 0 validates and writes the epoch's checkpoints
                continue
            model.eval()
            val_pred = predict(model, val.images, val.command)
            val_loss = float(np.mean((val_pred - val.steer) ** 2)) if len(val) else float("nan")
            val_mae = float(np.mean(np.abs(val_pred - val.steer))) if len(val) else float("nan")
            frames = samples * dist.world_size
            row = [epoch + 1, np.mean(losses), val_loss, val_mae, opt.param_groups[0]["lr"], frames / seconds, seconds]
            log.writerow([f"{v:.6g}" if isinstance(v, float) else v for v in row])
            fh.flush()
            state = {**(meta or {}), "epoch": epoch + 1, "val_loss": val_loss, "val_mae": val_mae}
            if val_loss < best_val or not math.isfinite(best_val):
                best_val = val_loss
                save_checkpoint(out / "best.pt", model, state)
            save_checkpoint(out / "last.pt", model, {**state, "optimizer": opt.state_dict(), "best_val": best_val})
            print(f"epoch {epoch + 1}: train {np.mean(losses):.4f} val {val_loss:.4f} (MAE {val_mae:.3f}) "
                  f"{frames / seconds:.0f} frames/s", file=sys.stderr)
            dist.barrier()
    if dist.is_main:
        plot_log(log_path, out / "loss.png")
    return best_val


def _cuda_mixed(args: argparse.Namespace, device: torch.device) -> bool:
    """Mixed precision on CUDA unless --precision fp32."""
    return device.type == "cuda" and getattr(args, "precision", "auto") != "fp32"


def _precision(args: argparse.Namespace, device: torch.device) -> Any:
    """The forward pass's arithmetic: bf16 autocast on a CPU that has it (``use_bf16``); on CUDA autocast (bf16, or
    fp16 with a GradScaler) unless --precision fp32."""
    if device.type == "cpu":
        return torch.autocast("cpu", dtype=torch.bfloat16, enabled=use_bf16(args))
    return autocast(device) if _cuda_mixed(args, device) else contextlib.nullcontext()


def use_bf16(args: argparse.Namespace) -> bool:
    precision = getattr(args, "precision", "fp32")
    if precision == "auto":
        return bool(getattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False)())
    return precision == "bf16"


def plot_log(log_path: Path, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with log_path.open() as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        return
    epochs = [int(r["epoch"]) for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(epochs, [float(r["train_loss"]) for r in rows], "o-", label="train (augmented, balanced)")
    ax.plot(epochs, [float(r["val_loss"]) for r in rows], "s-", label="validation (held-out episodes)")
    ax.set_xlabel("epoch")
    ax.set_ylabel("MSE of steer")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend()
    ax.set_title("PilotNet training")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    try:
        dist, device = start_training(getattr(args, "device", "cpu"))  # torchrun sets RANK, WORLD_SIZE, LOCAL_RANK
        check_loader_workers(getattr(args, "loader_workers", 0))
    except ValueError as exc:
        print(f"towndrive train pilotnet: {exc}", file=sys.stderr)
        return 2
    if dist.enabled and args.dagger:
        print("towndrive train pilotnet: DAgger rounds run in one process; train with torchrun, then run --dagger "
              "with --resume without torchrun.", file=sys.stderr)
        return 2
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    with process_group(dist, device):
        return _run(args, device, dist)


def _run(args: argparse.Namespace, device: torch.device, dist: Distributed) -> int:
    out: Path = args.out
    if args.model is None:
        args.model = out / "pilotnet.pt"
    out.mkdir(parents=True, exist_ok=True)
    try:
        frames = load_frames(args.data, side_cameras=not args.no_side_cameras,
                             workers=getattr(args, "loader_workers", 0))
    except EpisodeError as exc:
        print(f"towndrive train pilotnet: {exc}", file=sys.stderr)
        return 2
    train, val = split_by_episode(frames, args.validation, args.seed)
    print(f"{len(frames)} frames from {len(frames.episode_paths)} episodes: {len(train)} train, {len(val)} validation "
          f"(split by episode)", file=sys.stderr)
    conditional = not args.unconditional
    meta = {"conditional": conditional, "crop": asdict(DEFAULT_CROP), "input": [INPUT_HEIGHT, INPUT_WIDTH, "YUV"],
            "seed": args.seed, "data": [str(d) for d in args.data], "command": " ".join(["python", "train.py", *sys.argv[2:]])
            if sys.argv[0].endswith("train.py") else "", "train_frames": len(train), "val_frames": len(val)}
    model = build(conditional)
    first_epoch, opt_state, best = 0, None, math.inf
    if args.resume:
        last = out / "last.pt"
        if not last.is_file():
            print(f"towndrive train pilotnet: nothing to resume: {last} does not exist.", file=sys.stderr)
            return 2
        ckpt = load_checkpoint(last, "PilotNet training")
        model.load_state_dict(ckpt["state_dict"])
        first_epoch, opt_state, best = int(ckpt["epoch"]), ckpt.get("optimizer"), float(ckpt.get("best_val", math.inf))
        print(f"resuming after epoch {first_epoch} (best validation loss {best:.4f})", file=sys.stderr)
    print(f"{'conditional ' if conditional else ''}PilotNet, {parameter_count(model):,} parameters, on {device}"
          + dist.label, file=sys.stderr)
    remaining = max(0, args.epochs - first_epoch)
    if remaining:
        model = model.to(device)
        fit(data_parallel(model, device, dist), train, val, args, out, first_epoch, opt_state, best, remaining, meta,
            dist)
    if not dist.is_main:
        return 0  # rank 0 exports
    best_model, best_meta = load_model(out / "best.pt")
    if args.dagger:
        from towndrive.agent.training.pilotnet_dagger import dagger

        best_model, best_meta = dagger(best_model, best_meta, frames, args, out, fit)
    diff = export(best_model, best_meta, args.model)
    shutil.copy(out / "log.csv", args.model.with_suffix(".log.csv"))
    if args.replace_shipped:
        replace_shipped([args.model, args.model.with_suffix(".onnx"), args.model.with_suffix(".log.csv")],
                        ["pilotnet.pt", "pilotnet.onnx", "pilotnet.log.csv"])
    summary = {"model": str(args.model), "onnx": str(args.model.with_suffix(".onnx")), "onnx_max_abs_diff": diff,
               "val_loss": best_meta.get("val_loss"), "val_mae": best_meta.get("val_mae"), "epoch": best_meta.get("epoch")}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    return 0


__all__ = ["add_arguments", "run", "load_model", "export", "predict", "fit", "Crop"]
