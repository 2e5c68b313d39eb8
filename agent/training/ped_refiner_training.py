"""Training of the pedestrian refiner (``train.py detector refiner``) on a trained detector's own candidates.

Samples: every pedestrian box the detector reports (score >= ``candidate_score``) on the training splits,
plus ``--jitter`` randomly shifted and resized copies of each labelled pedestrian (so the refiner also learns
from boxes the detector happens to place well). A candidate overlapping a labelled pedestrian (IoU >= 0.1)
is a positive with that pedestrian's box as its target; one lying on an ignore region is dropped; the rest
are negatives. The checkpoint kept is the epoch with the best val pedestrian AP@0.5 within 40 m of detector
plus refiner; the score blend (``score_weight``) and the second NMS's IoU are then chosen on val as well,
and last how deep into the detector's pedestrian scores the refiner looks when the caller asks for every
detection (``candidate_score``: the AP evaluation's depth; at the driver's threshold of 0.3 the blend alone
decides, see ``RefinerConfig.lowest_candidate``). Training samples are always the candidates at
``TRAIN_CANDIDATE_SCORE``. ``--tune-only`` redoes these choices for an existing checkpoint without training.
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

from towndrive.agent.perception.checkpoints import load_checkpoint, save_checkpoint
from towndrive.agent.perception.detector import DecodedDetector, Detection, load_detector, postprocess
from towndrive.agent.perception.ped_refiner import (
    PEDESTRIAN,
    PedRefiner,
    Refine,
    RefinerConfig,
    crop_windows,
    load_refiner,
    refiner_inputs,
    to_window,
    windows,
)
from towndrive.agent.perception.tracking import iou_matrix
from towndrive.agent.training.detector_eval import Sample, class_ap, load_split, read_rgb
from towndrive.agent.training.devices import autocast, backward_step, grad_scaler, resolve_device, to_device

SCORE_WEIGHTS = (0.3, 0.4, 0.5, 0.6, 0.7)
NMS_IOUS = (0.5, 0.7, 1.0)  # 1.0: no second NMS
TRAIN_CANDIDATE_SCORE = 0.01  # the detector's pedestrian boxes the refiner is trained on
# Deeper candidates let the refiner lift pedestrians the detector scored very low (mostly at night); the
# search stops at 1e-4, where each val frame already gives the refiner dozens of crops.
CANDIDATE_SCORES = (0.01, 0.003, 0.001, 0.0003, 0.0001)


def detector_candidates(detector_path: str, samples: list[Sample], images: list[np.ndarray],
                        score: float, device: torch.device | None = None) -> list[list[Detection]]:
    """The detector's detections of every frame at a low threshold (torch, batches of 32)."""
    device = device or torch.device("cpu")
    model = DecodedDetector(load_detector(detector_path)).eval().to(device)
    out: list[list[Detection]] = []
    with torch.no_grad():
        for i in tqdm(range(0, len(samples), 32), desc="detect", unit="batch", leave=False):
            x = torch.from_numpy(np.stack(images[i:i + 32]).transpose(0, 3, 1, 2).copy()).float() / 255.0
            out.extend(postprocess(r, score) for r in model(to_device(x, device)).cpu().numpy())
    return out


def _on_ignore(cand: np.ndarray, ign: np.ndarray) -> np.ndarray:
    """Candidates with at least half their area on an ignore region (as the evaluation treats them)."""
    if not len(ign):
        return np.zeros(len(cand), bool)
    ix = np.clip(np.minimum(cand[:, None, 2], ign[None, :, 2]) - np.maximum(cand[:, None, 0], ign[None, :, 0]), 0, None)
    iy = np.clip(np.minimum(cand[:, None, 3], ign[None, :, 3]) - np.maximum(cand[:, None, 1], ign[None, :, 1]), 0, None)
    area = np.maximum((cand[:, 2] - cand[:, 0]) * (cand[:, 3] - cand[:, 1]), 1e-6)
    return (ix * iy / area[:, None] >= 0.5).any(1)


def build_samples(samples: list[Sample], images: list[np.ndarray], dets: list[list[Detection]],
                  config: RefinerConfig, jitter: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Crops, candidate and target boxes (window units) and labels (1 pedestrian, 0 not) of every candidate."""
    crops, cands, targets, labels = [], [], [], []
    for s, rgb, ds in zip(samples, images, dets, strict=True):
        is_gt = (s.cls == PEDESTRIAN) & ~s.ignore
        gt = s.boxes[is_gt].astype(np.float32)
        cand = np.array([d.box for d in ds if d.cls == PEDESTRIAN], np.float32).reshape(-1, 4)
        for _ in range(jitter if len(gt) else 0):
            wh = np.tile(np.stack([gt[:, 2] - gt[:, 0], gt[:, 3] - gt[:, 1]], 1), 2)
            j = gt + rng.normal(0.0, 0.15, gt.shape).astype(np.float32) * wh
            j[:, 2] = np.maximum(j[:, 2], j[:, 0] + 1.0)
            j[:, 3] = np.maximum(j[:, 3], j[:, 1] + 2.0)
            cand = np.concatenate([cand, j])
        if not len(cand):
            continue
        iou = iou_matrix(cand, gt) if len(gt) else np.zeros((len(cand), 1), np.float32)
        best = iou.argmax(1)
        label = np.where(iou.max(1) >= 0.1, 1, 0)
        label[(label == 0) & _on_ignore(cand, s.boxes[(s.cls == PEDESTRIAN) & s.ignore].astype(np.float32))] = -1
        keep = label >= 0
        if not keep.any():
            continue
        cand, best, label = cand[keep], best[keep], label[keep]
        win = windows(cand, config)
        target = gt[best] if len(gt) else cand
        crops.append(crop_windows(rgb, win))
        cands.append(to_window(cand, win))
        targets.append(to_window(target, win))
        labels.append(label)
    return {"crops": np.concatenate(crops), "cand": np.concatenate(cands).astype(np.float32),
            "target": np.concatenate(targets).astype(np.float32), "label": np.concatenate(labels).astype(np.float32)}


def _flip(crops: np.ndarray, cand: np.ndarray, target: np.ndarray, flip: np.ndarray) -> tuple[np.ndarray, ...]:
    crops = np.where(flip[:, None, None, None], crops[:, :, ::-1], crops)
    cand, target = cand.copy(), target.copy()
    for b in (cand, target):
        x0 = b[flip, 0].copy()
        b[flip, 0] = 1.0 - b[flip, 2]
        b[flip, 2] = 1.0 - x0
    return np.ascontiguousarray(crops), cand, target


def refiner_loss(out: torch.Tensor, cand: np.ndarray, target: np.ndarray, label: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """BCE of the pedestrian logit, and for positives L1 of the edges in units of the candidate's own size."""
    lab = torch.from_numpy(label).to(out.device)
    cls = nn.functional.binary_cross_entropy_with_logits(out[:, 4], lab)
    pos = lab > 0
    size = np.stack([cand[:, 2] - cand[:, 0], cand[:, 3] - cand[:, 1]] * 2, 1)
    err = ((out[:, :4] - torch.from_numpy(target - cand).to(out.device)).abs()
           / torch.from_numpy(size).to(out.device).clamp(min=0.02))
    box = err[pos].mean() if bool(pos.any()) else out.sum() * 0.0
    return cls, box


def val_ped_ap(samples: list[Sample], images: list[np.ndarray], dets: list[list[Detection]], model: PedRefiner,
               config: RefinerConfig) -> dict[str, float]:
    """Pedestrian AP within 40 m of detector + refiner on val."""
    model.eval()
    device = next(model.parameters()).device

    def run(x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return model(to_device(torch.from_numpy(x), device)).float().cpu().numpy()

    refine = Refine(run, config)
    refined = [refine(rgb, ds, 0.0) for rgb, ds in zip(images, dets, strict=True)]
    ap = class_ap(samples, refined, PEDESTRIAN, max_distance_m=40.0)
    return {"ap50": float(ap["ap50"]), "ap50_95": float(ap["ap50_95"])}


def train_refiner(args: argparse.Namespace) -> int:
    try:  # before any work: a missing GPU is one sentence
        device = resolve_device(getattr(args, "device", "cpu"))
    except ValueError as exc:
        print(f"towndrive train detector refiner: {exc}", file=sys.stderr)
        return 2
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(args.seed)
    channels = tuple(int(c) for c in str(args.channels).split(","))
    if len(channels) != 3:
        raise ValueError(f"--channels takes three widths, such as 24,48,96; got {args.channels!r}.")
    config = RefinerConfig(channels=channels, hidden=args.hidden, candidate_score=TRAIN_CANDIDATE_SCORE)
    t0 = time.perf_counter()
    if args.tune_only:
        return tune_checkpoint(args)
    train_samples = [s for split in args.train_splits.split(",") for s in load_split(args.data, split)]
    val_samples = [x for split in str(getattr(args, "val_splits", "val")).split(",") for x in load_split(args.data, split)]
    if not train_samples or not val_samples:
        raise ValueError(f"No training or val frames under {args.data}; run `python train.py detector dataset` first.")
    data: dict[str, list[np.ndarray]] = {}
    for k in range(0, len(train_samples), 2000):  # in chunks: the frames are decoded once and then let go
        chunk = train_samples[k:k + 2000]
        images = [read_rgb(s.image) for s in chunk]
        part = build_samples(chunk, images, detector_candidates(args.detector, chunk, images, config.candidate_score,
                                                                device),
                             config, args.jitter, rng)
        for key, v in part.items():
            data.setdefault(key, []).append(v)
    tr = {key: np.concatenate(v) for key, v in data.items()}
    val_images = [read_rgb(s.image) for s in val_samples]
    val_dets = detector_candidates(args.detector, val_samples, val_images, config.candidate_score, device)
    n = len(tr["label"])
    print(f"{n} candidates ({int(tr['label'].sum())} pedestrians) from {len(train_samples)} frames, "
          f"{time.perf_counter() - t0:.0f} s", flush=True)
    model = PedRefiner(config).to(device)
    scaler = grad_scaler(device)
    opt = torch.optim.AdamW(model.parameters(), args.lr, weight_decay=1e-4)
    steps = n // args.batch
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, args.lr, total_steps=args.epochs * steps)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    log = out.with_suffix(".log.jsonl").open("w")
    best = -1.0
    for epoch in range(args.epochs):
        model.train()
        perm = rng.permutation(n)
        sums = np.zeros(2)
        t_ep = time.perf_counter()
        for i in tqdm(range(steps), desc=f"refiner epoch {epoch}", unit="batch", leave=False):
            idx = np.sort(perm[i * args.batch:(i + 1) * args.batch])
            crops, cand, target = _flip(tr["crops"][idx], tr["cand"][idx], tr["target"][idx],
                                        rng.random(len(idx)) < 0.5)
            inputs = torch.from_numpy(refiner_inputs(crops, cand))
            with autocast(device):  # on CUDA: pinned non-blocking copy, autocast forward; no-ops on the CPU
                pred = model(to_device(inputs, device))
            cls, box = refiner_loss(pred.float(), cand, target, tr["label"][idx])  # the loss in fp32
            opt.zero_grad()
            backward_step(cls + box, opt, scaler)
            sched.step()
            sums += (cls.item(), box.item())
        val = val_ped_ap(val_samples, val_images, val_dets, model, config)
        row = {"epoch": epoch, "cls_loss": sums[0] / steps, "box_loss": sums[1] / steps, "val_ped40_ap50": val["ap50"],
               "val_ped40_ap50_95": val["ap50_95"], "seconds": round(time.perf_counter() - t_ep, 1)}
        print(json.dumps(row), flush=True)
        log.write(json.dumps(row) + "\n")
        log.flush()
        if val["ap50"] > best:
            best = val["ap50"]
            state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
            save_checkpoint(out, {"kind": "ped_refiner", "config": asdict(config), "state_dict": state,
                                  "epoch": epoch, "detector": str(args.detector), "seed": args.seed})
    log.close()
    ckpt = load_checkpoint(out, "pedestrian refiner")
    model = model.cpu()  # choosing the score blend and the NMS runs on the CPU, as deployed
    model.load_state_dict(ckpt["state_dict"])
    ckpt["config"], ap = tune(model, config, val_samples, val_images, val_dets, args.detector, out.with_suffix(".log.jsonl"))
    save_checkpoint(out, ckpt)
    print(f"Wrote {out} (epoch {ckpt['epoch']}, val pedestrian AP@0.5 within 40 m {ap:.3f}), "
          f"{(time.perf_counter() - t0) / 60:.1f} min")
    return 0


def tune(model: PedRefiner, config: RefinerConfig, val_samples: list[Sample], val_images: list[np.ndarray],
         val_dets: list[list[Detection]], detector: str, log_path: Path) -> tuple[dict, float]:
    """Choose the score blend and the second NMS's IoU on val (candidates at ``TRAIN_CANDIDATE_SCORE``), then the
    candidate depth with those; append the grids to the log; return the config (as a dict) and its val AP."""
    config = replace(config, candidate_score=TRAIN_CANDIDATE_SCORE)
    grid = {(w, iou): val_ped_ap(val_samples, val_images, val_dets, model,
                                 replace(config, score_weight=w, nms_iou=iou))["ap50"]
            for w in SCORE_WEIGHTS for iou in NMS_IOUS}
    weight, nms_iou = max(grid, key=lambda k: grid[k])
    config = replace(config, score_weight=weight, nms_iou=nms_iou)
    deep = detector_candidates(detector, val_samples, val_images, min(CANDIDATE_SCORES))
    depth = {c: val_ped_ap(val_samples, val_images, deep, model, replace(config, candidate_score=c))["ap50"]
             for c in tqdm(CANDIDATE_SCORES, desc="candidate depth", leave=False)}
    candidate = max(depth, key=lambda c: (depth[c], c))  # ties: the shallower, cheaper one
    config = replace(config, candidate_score=candidate)
    row = {"val_ap50_by_score_weight_and_nms_iou": {f"{w} {iou}": round(v, 4) for (w, iou), v in grid.items()},
           "val_ap50_by_candidate_score": {str(c): round(v, 4) for c, v in depth.items()},
           "chosen": {"score_weight": weight, "nms_iou": nms_iou, "candidate_score": candidate}}
    print(json.dumps(row))
    with log_path.open("a") as log:
        log.write(json.dumps(row) + "\n")
    return asdict(config), depth[candidate]


def tune_checkpoint(args: argparse.Namespace) -> int:
    """``--tune-only``: the choices of ``tune`` for the trained refiner at ``--out``, written back into it."""
    out = Path(args.out)
    model = load_refiner(out)
    val_samples = [x for split in str(getattr(args, "val_splits", "val")).split(",") for x in load_split(args.data, split)]
    val_images = [read_rgb(s.image) for s in val_samples]
    val_dets = detector_candidates(args.detector, val_samples, val_images, TRAIN_CANDIDATE_SCORE)
    ckpt = load_checkpoint(out, "pedestrian refiner")
    ckpt["config"], ap = tune(model, model.config, val_samples, val_images, val_dets, args.detector,
                              out.with_suffix(".log.jsonl"))
    save_checkpoint(out, ckpt)
    print(f"Tuned {out}: {ckpt['config']} (val pedestrian AP@0.5 within 40 m {ap:.3f})")
    return 0
