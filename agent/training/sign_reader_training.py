"""Training of the sign reader (``train.py detector signs``) on a trained detector's own sign boxes.

Samples: every sign box the detector reports (any of the four sign classes, score >= ``TRAIN_CANDIDATE_SCORE``) on
the training splits, plus ``--jitter`` randomly shifted and resized copies of each labelled sign. A box at IoU >= 0.5
with a labelled sign is that sign; one at IoU 0.2-0.5, or with half its area on an ignored sign (too small, seen
from the side, a limit too far to read), is left out; the rest are "no sign" (the detector's false signs, also on
the classic towns, which have none). The checkpoint kept is the epoch with the best val mAP@0.5 over the four sign
classes of detector plus reader; the score blend (``score_weight``) is then chosen on val as well.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from towndrive.agent.perception.checkpoints import save_checkpoint
from towndrive.agent.perception.classes import SIGN_CLASSES
from towndrive.agent.perception.detector import Detection
from towndrive.agent.perception.sign_reader import (
    NO_SIGN,
    SIGN_IDS,
    Read,
    SignReader,
    SignReaderConfig,
    crop_windows,
    windows,
)
from towndrive.agent.perception.tracking import iou_matrix
from towndrive.agent.training.detector_eval import Sample, class_ap, load_split, read_rgb
from towndrive.agent.training.devices import resolve_device
from towndrive.agent.training.ped_refiner_training import _on_ignore, detector_candidates

SCORE_WEIGHTS = (0.3, 0.5, 0.7, 0.85)
TRAIN_CANDIDATE_SCORE = 0.01


def build_samples(samples: list[Sample], images: list[np.ndarray], dets: list[list[Detection]],
                  config: SignReaderConfig, jitter: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Crops (uint8 N x 32 x 32 x 3) and labels (0-3 the signs in ``SIGN_CLASSES`` order, 4 no sign)."""
    crops, labels = [], []
    for s, rgb, ds in zip(samples, images, dets, strict=True):
        is_sign = np.isin(s.cls, SIGN_IDS)
        gt = s.boxes[is_sign & ~s.ignore].astype(np.float32)
        gt_cls = np.array([SIGN_IDS.index(int(c)) for c in s.cls[is_sign & ~s.ignore]], np.int64)
        cand = np.array([d.box for d in ds if d.cls in SIGN_IDS], np.float32).reshape(-1, 4)
        for _ in range(jitter if len(gt) else 0):
            wh = np.tile(np.stack([gt[:, 2] - gt[:, 0], gt[:, 3] - gt[:, 1]], 1), 2)
            j = gt + rng.normal(0.0, 0.08, gt.shape).astype(np.float32) * wh
            j[:, 2] = np.maximum(j[:, 2], j[:, 0] + 2.0)
            j[:, 3] = np.maximum(j[:, 3], j[:, 1] + 2.0)
            cand = np.concatenate([cand, j])
        if not len(cand):
            continue
        iou = iou_matrix(cand, gt) if len(gt) else np.zeros((len(cand), 1), np.float32)
        best = iou.max(1)
        label = np.where(best >= 0.5, gt_cls[iou.argmax(1)] if len(gt) else NO_SIGN, NO_SIGN)
        drop = (best >= 0.2) & (best < 0.5)
        drop |= (label == NO_SIGN) & _on_ignore(cand, s.boxes[is_sign & s.ignore].astype(np.float32))
        if (~drop).any():
            crops.append(crop_windows(rgb, windows(cand[~drop], config)))
            labels.append(label[~drop])
    if not crops:
        return {"crops": np.zeros((0, 32, 32, 3), np.uint8), "label": np.zeros(0, np.int64)}
    return {"crops": np.concatenate(crops), "label": np.concatenate(labels).astype(np.int64)}


def _jitter_colour(crops: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Brightness and contrast per crop (the weathers and the night's glow), as floats in [0, 255]."""
    x = crops.astype(np.float32)
    gain = rng.uniform(0.7, 1.3, (len(x), 1, 1, 1)).astype(np.float32)
    mean = x.mean(axis=(1, 2, 3), keepdims=True)
    contrast = rng.uniform(0.8, 1.2, (len(x), 1, 1, 1)).astype(np.float32)
    return np.clip((x - mean) * contrast + mean * gain, 0, 255)


def sign_map(samples: list[Sample], images: list[np.ndarray], dets: list[list[Detection]], model: SignReader,
             config: SignReaderConfig) -> dict:
    """Val AP@0.5 per sign class of detector + reader, and their mean."""
    model.eval()

    def run(x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return model(torch.from_numpy(x)).numpy()

    read = Read(run, config)
    out = [read(rgb, ds, 0.0) for rgb, ds in zip(images, dets, strict=True)]
    per = {name: class_ap(samples, out, k) for name, k in zip(SIGN_CLASSES, SIGN_IDS, strict=True)}
    valid = [v["ap50"] for v in per.values() if v["gt"] > 0]
    return {"map50": float(np.mean(valid)) if valid else float("nan"),
            "ap50": {k: round(float(v["ap50"]), 4) for k, v in per.items()}}


def train_sign_reader(args: argparse.Namespace) -> int:
    try:
        device = resolve_device(getattr(args, "device", "cpu"))
    except ValueError as exc:
        print(f"towndrive train detector signs: {exc}", file=sys.stderr)
        return 2
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(args.seed)
    config = SignReaderConfig(candidate_score=TRAIN_CANDIDATE_SCORE)
    t0 = time.perf_counter()
    train_samples = [s for split in args.train_splits.split(",") for s in load_split(args.data, split)]
    val_samples = [s for split in args.val_splits.split(",") for s in load_split(args.data, split)]
    parts: list[dict[str, np.ndarray]] = []
    for k in range(0, len(train_samples), 2000):  # in chunks: the frames are decoded once and then let go
        chunk = train_samples[k:k + 2000]
        images = [read_rgb(s.image) for s in chunk]
        cands = detector_candidates(args.detector, chunk, images, config.candidate_score, device)
        parts.append(build_samples(chunk, images, cands, config, args.jitter, rng))
    data = {key: np.concatenate([p[key] for p in parts]) for key in ("crops", "label")}
    val_images = [read_rgb(s.image) for s in val_samples]
    val_dets = detector_candidates(args.detector, val_samples, val_images, config.candidate_score, device)
    counts = np.bincount(data["label"], minlength=NO_SIGN + 1)
    print(f"{len(data['label'])} training crops: " + ", ".join(
        f"{name} {n}" for name, n in zip((*SIGN_CLASSES, "no sign"), counts.tolist(), strict=True))
        + f" ({time.perf_counter() - t0:.0f} s)")
    model = SignReader(config)
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=5e-4)
    steps = max(1, len(data["label"]) // args.batch) * args.epochs
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=args.lr, total_steps=steps, pct_start=0.15)
    # Classes weighted by 1/sqrt(frequency): the yields are a tenth as many as the stops.
    weight = torch.from_numpy((counts.max() / np.maximum(counts, 1)) ** 0.5).float()
    loss_fn = nn.CrossEntropyLoss(weight=weight)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    log = out.with_suffix(".log.jsonl")
    best, best_state = -1.0, None
    for epoch in range(args.epochs):
        model.train()
        order = rng.permutation(len(data["label"]))
        total = 0.0
        bar = tqdm(range(len(order) // args.batch), desc=f"epoch {epoch + 1}/{args.epochs}", unit="batch", leave=False)
        for b in bar:
            idx = order[b * args.batch:(b + 1) * args.batch]
            x = _jitter_colour(data["crops"][idx], rng)
            x = torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2)) / 255.0 - 0.5).float()
            loss = loss_fn(model(x), torch.from_numpy(data["label"][idx]))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            total += float(loss.detach())
        rep = sign_map(val_samples, val_images, val_dets, model, config)
        entry = {"epoch": epoch + 1, "loss": round(total / max(1, len(order) // args.batch), 4),
                 "val_sign_map50": round(rep["map50"], 4), "val_ap50": rep["ap50"],
                 "minutes": round((time.perf_counter() - t0) / 60, 2)}
        with open(log, "a") as f:
            f.write(json.dumps(entry) + "\n")
        print(f"epoch {epoch + 1}: loss {entry['loss']:.3f}, val sign mAP@0.5 {rep['map50']:.3f} | "
              + "  ".join(f"{k} {v:.3f}" for k, v in rep["ap50"].items()))
        if rep["map50"] > best:
            best = rep["map50"]
            best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    assert best_state is not None
    model.load_state_dict(best_state)
    grid = {}
    for w in SCORE_WEIGHTS:  # the blend with the detector's score, on val
        grid[w] = sign_map(val_samples, val_images, val_dets, model, replace(config, score_weight=w))["map50"]
    weight_best = max(grid, key=lambda w: (grid[w], -abs(w - 0.5)))
    config = replace(config, score_weight=weight_best)
    print("score blend on val: " + "  ".join(f"{w}: {v:.3f}" for w, v in grid.items()) + f" -> {weight_best}")
    with open(log, "a") as f:
        f.write(json.dumps({"blend_grid": {str(k): round(v, 4) for k, v in grid.items()}, "score_weight": weight_best})
                + "\n")
    save_checkpoint(out, {"state_dict": model.state_dict(), "config": asdict(config), "classes": SIGN_CLASSES,
                          "detector": str(args.detector), "seed": args.seed, "val_sign_map50": grid[weight_best],
                          "command": "train.py detector signs", "args": vars(args) | {"run": None}})
    print(f"Saved {out} (val sign mAP@0.5 {grid[weight_best]:.3f}) in {(time.perf_counter() - t0) / 60:.1f} min")
    return 0

