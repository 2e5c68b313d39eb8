"""Training of the YOLO-style detector: augmentation, target assignment, the YOLO loss, EMA, best checkpoint.

Target assignment follows YOLOv5: a ground-truth box is given to the cell holding its centre and to the
two neighbouring cells nearest to the centre (the ``2 sigmoid - 0.5`` offsets reach them), on each map whose
size range holds its longer side (``size_range``: stride 8 up to 64 px, stride 16 from 32 px; with a
stride-4 head, stride 4 up to 32 px and stride 8 from 16 to 64 px). Smaller boxes overwrite larger ones
in shared cells. Cells whose centre lies in an ignore region get no objectness loss. Loss: ``1 - GIoU`` for
boxes, BCE for objectness (weighted by each map's cell count relative to stride 16, as YOLOv5 weights P3 4x)
and BCE for classes, in YOLOv5's proportions.

Batches are built in the training process from one random stream (``--loader-workers 0``, as always), or by
DataLoader workers from a generator per batch (``loaders.py``). Started by ``torchrun``, each process trains on
its share of every epoch's frames with DistributedDataParallel (``devices.py``, as PilotNet does); rank 0
validates and writes the checkpoints.
"""

from __future__ import annotations

import argparse
import copy
import functools
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from tqdm import tqdm

from towndrive.agent.perception.checkpoints import load_checkpoint
from towndrive.agent.perception.checkpoints import save_checkpoint as save
from towndrive.agent.perception.classes import CLASSES, SIGN_CLASSES
from towndrive.agent.perception.detector import INPUT_HW, STRIDES, DecodedDetector, Detector, DetectorConfig, postprocess
from towndrive.agent.training.detector_eval import Sample, detection_report, load_split, read_rgb
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

LOSS_WEIGHTS = {"box": 0.05, "obj": 0.2, "cls": 0.04}
# Objectness weight per stride, proportional to the number of cells (YOLOv5's P3:P4 = 4:1), so every cell weighs
# the same whichever heads the model has.
OBJ_BALANCE = {4: 16.0, 8: 4.0, 16: 1.0}


def size_range(stride: int, strides: tuple[int, ...]) -> tuple[float, float]:
    """Longer box sides (px) assigned to a stride's map: 2x to 8x the stride; no lower bound on the finest map
    and no upper bound on the coarsest. With (8, 16): <= 64 and >= 32; with (4, 8, 16): <= 32, 16-64, >= 32."""
    lo = 0.0 if stride == min(strides) else 2.0 * stride
    hi = float("inf") if stride == max(strides) else 8.0 * stride
    return lo, hi


# --------------------------------------------------------------------------- augmentation
# Signs whose legend a mirror image would garble (a 30 reads as "0Ɛ", a 50 nearly as "02"): frames with one labelled
# are never flipped, so the detector learns each value the way the camera sees it.
LEGEND_CLASSES = np.array([CLASSES.index(n) for n in ("stop_sign", "speed_limit_30", "speed_limit_50")])


def augment(img: np.ndarray, boxes: np.ndarray, rng: np.random.Generator,
            scale_prob: float = 1.0, flip: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flip (unless ``flip`` is False), scale, translate and HSV-jitter one frame and its boxes (all objects, labels
    and ignores).

    Returns the image, the boxes clipped to it, and which boxes survive (at least 40% of their area stays
    in the frame and they stay 2 px wide and tall; the others become ignore regions). The hue jitter is kept
    to a few degrees: a light's state *is* its hue. Only a ``scale_prob`` share of frames is rescaled (0.75x
    to 1.3x, sub-pixel translation, bilinear resampling); the others are shifted by whole pixels, so they stay
    as sharp as the camera's frames and their pixel-exact boxes stay pixel-exact (a 3 px wide pedestrian
    needs its box within about a pixel for IoU 0.5).
    """
    h, w = img.shape[:2]
    boxes = boxes.copy()
    if rng.random() < 0.5 and flip:  # drawn either way, so the random stream does not depend on ``flip``
        img = img[:, ::-1]
        boxes[:, [0, 2]] = w - boxes[:, [2, 0]]
    scale = float(rng.uniform(0.75, 1.3))  # drawn every time, so scale_prob 1 keeps the old random stream
    tx, ty = float(rng.uniform(-0.1, 0.1) * w), float(rng.uniform(-0.1, 0.1) * h)
    if scale_prob < 1.0 and rng.random() >= scale_prob:
        scale, tx, ty = 1.0, float(round(tx)), float(round(ty))
    m = np.array([[scale, 0, (1 - scale) * w / 2 + tx], [0, scale, (1 - scale) * h / 2 + ty]], np.float32)
    img = cv2.warpAffine(np.ascontiguousarray(img), m, (w, h), flags=cv2.INTER_LINEAR, borderValue=(114, 114, 114))
    area0 = np.prod(boxes[:, 2:] - boxes[:, :2], axis=1) * scale * scale
    boxes = boxes * scale + np.array([m[0, 2], m[1, 2], m[0, 2], m[1, 2]], np.float32)
    boxes[:, [0, 2]] = boxes[:, [0, 2]].clip(0, w)
    boxes[:, [1, 3]] = boxes[:, [1, 3]].clip(0, h)
    wh = boxes[:, 2:] - boxes[:, :2]
    ok = (np.prod(wh, axis=1) >= 0.4 * area0) & (wh.min(axis=1) >= 2) if len(boxes) else np.zeros(0, bool)
    # HSV jitter (YOLOv5's gains: hue 0.015, saturation 0.7, value 0.4), on a lookup table.
    gains = rng.uniform(-1, 1, 3) * np.array([0.015, 0.6, 0.4]) + 1
    hue, sat, val = cv2.split(cv2.cvtColor(img, cv2.COLOR_RGB2HSV))
    x = np.arange(256, dtype=np.float32)
    lut_h = ((x * gains[0]) % 180).astype(np.uint8)
    lut_s = np.clip(x * gains[1], 0, 255).astype(np.uint8)
    lut_v = np.clip(x * gains[2], 0, 255).astype(np.uint8)
    hsv = cv2.merge((cv2.LUT(hue, lut_h), cv2.LUT(sat, lut_s), cv2.LUT(val, lut_v)))
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB), boxes, ok


# --------------------------------------------------------------------------- targets and loss
def build_targets(boxes: np.ndarray, cls: np.ndarray, ignore: np.ndarray,
                  strides: tuple[int, ...] = STRIDES) -> list[dict[str, np.ndarray]]:
    """Per stride: positive cells with their box and class, and the objectness weight of every cell."""
    h, w = INPUT_HW
    out = []
    for s in strides:
        gh, gw = h // s, w // s
        weight = np.ones((gh, gw), np.float32)
        owner = -np.ones((gh, gw), np.int64)
        for b in boxes[ignore]:  # cells centred in an ignore region: no objectness loss
            c0, c1 = int(np.floor(b[0] / s - 0.5)) + 1, int(np.ceil(b[2] / s - 0.5))
            r0, r1 = int(np.floor(b[1] / s - 0.5)) + 1, int(np.ceil(b[3] / s - 0.5))
            cx, cy = int((b[0] + b[2]) / 2 / s), int((b[1] + b[3]) / 2 / s)
            weight[max(0, r0):max(0, r1), max(0, c0):max(0, c1)] = 0.0
            weight[min(cy, gh - 1), min(cx, gw - 1)] = 0.0
        keep = np.flatnonzero(~ignore)
        sides = np.max(boxes[keep, 2:] - boxes[keep, :2], axis=1) if len(keep) else np.zeros(0)
        lo, hi = size_range(s, strides)
        take = keep[(sides >= lo) & (sides <= hi)]
        areas = np.prod(boxes[take, 2:] - boxes[take, :2], axis=1)
        for k in take[np.argsort(-areas)]:  # large first, so small ones overwrite shared cells
            b = boxes[k]
            gx, gy = (b[0] + b[2]) / 2 / s, (b[1] + b[3]) / 2 / s
            ci, cj = min(int(gx), gw - 1), min(int(gy), gh - 1)
            cells = [(ci, cj), (ci - 1 if gx - ci < 0.5 else ci + 1, cj), (ci, cj - 1 if gy - cj < 0.5 else cj + 1)]
            for i, j in cells:
                if 0 <= i < gw and 0 <= j < gh:
                    owner[j, i] = k
        pos = np.flatnonzero(owner.ravel() >= 0)
        own = owner.ravel()[pos]
        weight.ravel()[pos] = 1.0
        out.append({"pos": pos, "box": boxes[own].astype(np.float32), "cls": cls[own], "weight": weight.ravel()})
    return out


def iou_and_giou(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """IoU and generalised IoU of paired boxes (x0, y0, x1, y1)."""
    lt, rb = torch.max(a[:, :2], b[:, :2]), torch.min(a[:, 2:], b[:, 2:])
    inter = (rb - lt).clamp(min=0).prod(1)
    area_a, area_b = (a[:, 2:] - a[:, :2]).prod(1), (b[:, 2:] - b[:, :2]).prod(1)
    union = area_a + area_b - inter
    iou = inter / union.clamp(min=1e-9)
    hull = (torch.max(a[:, 2:], b[:, 2:]) - torch.min(a[:, :2], b[:, :2])).clamp(min=0).prod(1)
    return iou, iou - (hull - union) / hull.clamp(min=1e-9)


def giou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Generalised IoU of paired boxes (x0, y0, x1, y1)."""
    return iou_and_giou(a, b)[1]


def yolo_loss(maps: list[torch.Tensor], targets: list[list[dict[str, np.ndarray]]],
              strides: tuple[int, ...] = STRIDES, obj_iou: float = 0.0,
              box_l1: float = 0.0) -> tuple[torch.Tensor, dict]:
    """The YOLO loss family over a batch; ``targets[image][level]`` from ``build_targets``.

    ``obj_iou`` is YOLOv5's ``gr``: a positive cell's objectness target is ``1 - obj_iou + obj_iou * IoU``
    of its predicted box (detached), so among the cells that see one object the best-placed box scores highest
    and survives NMS; 0 gives every positive the target 1.

    ``box_l1`` adds the mean absolute error of the four box edges, in cells of the map's stride, with that
    weight relative to the GIoU term: an unbiased pull on each edge. Under an uncertain centre, 1 - GIoU is
    smallest for a box wider than the object, which costs the narrowest objects (pedestrians 2-3 px wide)
    IoU 0.5.
    """
    bce = torch.nn.functional.binary_cross_entropy_with_logits
    nc = maps[0].shape[1] - 5  # the model's classes (the six without the road signs, or all of CLASSES)
    lbox, lcls, lobj, ll1 = (maps[0].new_zeros(()) for _ in range(4))
    n_pos = 0
    for level, (m, s) in enumerate(zip(maps, strides, strict=True)):
        n, ch, gh, gw = m.shape
        t = m.permute(0, 2, 3, 1).reshape(n, gh * gw, ch)
        weight = torch.from_numpy(np.stack([tg[level]["weight"] for tg in targets])).to(m.device)
        obj_target = torch.zeros(n, gh * gw, device=m.device)
        img_idx = np.concatenate([np.full(len(tg[level]["pos"]), i) for i, tg in enumerate(targets)])
        pos = np.concatenate([tg[level]["pos"] for tg in targets])
        if len(pos):
            ii = torch.from_numpy(img_idx.astype(np.int64)).to(m.device)
            pp = torch.from_numpy(pos.astype(np.int64)).to(m.device)
            tbox = torch.from_numpy(np.concatenate([tg[level]["box"] for tg in targets])).to(m.device)
            tcls = torch.from_numpy(np.concatenate([tg[level]["cls"] for tg in targets]).astype(np.int64)).to(m.device)
            p = t[ii, pp]
            grid = torch.stack([pp % gw, pp // gw], 1).float()
            xy = (torch.sigmoid(p[:, :2]) * 2 - 0.5 + grid) * s
            wh = torch.exp(p[:, 2:4].clamp(-6, 6)) * s
            pbox = torch.cat([xy - wh / 2, xy + wh / 2], 1)
            iou, g = iou_and_giou(pbox, tbox)
            lbox = lbox + (1 - g).sum()
            if box_l1:
                ll1 = ll1 + (pbox - tbox).abs().mean(1).sum() / s
            onehot = torch.nn.functional.one_hot(tcls, nc).float()
            lcls = lcls + bce(p[:, 5:], onehot, reduction="sum") / nc
            if obj_iou:
                obj_target[ii, pp] = 1.0 - obj_iou + obj_iou * iou.detach()
            else:
                obj_target[ii, pp] = 1.0
            n_pos += len(pos)
        lobj = lobj + OBJ_BALANCE[s] * (bce(t[..., 4], obj_target, reduction="none") * weight).mean()
    n_pos = max(n_pos, 1)
    parts = {"box": lbox / n_pos, "obj": lobj, "cls": lcls / n_pos}
    total = sum(LOSS_WEIGHTS[k] * v for k, v in parts.items())
    if box_l1:
        parts["l1"] = ll1 / n_pos
        total = total + box_l1 * LOSS_WEIGHTS["box"] * parts["l1"]
    total = total * len(targets)
    return total, {k: float(v.detach()) for k, v in parts.items()}


# --------------------------------------------------------------------------- data
def load_images(samples: list[Sample], desc: str) -> np.ndarray:
    paths = [s.image for s in samples]
    unique = list(dict.fromkeys(paths))  # a frame listed twice (--repeat-sign-frames) is read once
    images = np.stack([read_rgb(p) for p in tqdm(unique, desc=f"load {desc}", unit="frame", leave=False)])
    if len(unique) == len(paths):
        return images
    where = {p: k for k, p in enumerate(unique)}
    return images[[where[p] for p in paths]]


def make_batch(images: np.ndarray, samples: list[Sample], idx: np.ndarray, rng: np.random.Generator | None,
               strides: tuple[int, ...] = STRIDES, scale_prob: float = 1.0):
    """Images as a float tensor and per-image targets, augmented when ``rng`` is given."""
    xs, tgs = [], []
    for k in idx:
        s = samples[k]
        img, boxes, ignore = images[k], s.boxes, s.ignore.copy()
        if rng is not None:
            legend = bool(np.isin(s.cls[~s.ignore], LEGEND_CLASSES).any())
            img, boxes, ok = augment(img, boxes, rng, scale_prob, flip=not legend)
            ignore = ignore | ~ok
        xs.append(img.transpose(2, 0, 1))
        tgs.append(build_targets(boxes, s.cls, ignore, strides))
    x = torch.from_numpy(np.ascontiguousarray(np.stack(xs))).float().div_(255.0)
    return x, tgs


def _seeded_batch(rng: np.random.Generator, idx: np.ndarray, images: np.ndarray, samples: list[Sample],
                  strides: tuple[int, ...], scale_prob: float):
    """``make_batch`` in the argument order of ``loaders.SeededBatches``."""
    return make_batch(images, samples, idx, rng, strides, scale_prob)


class EMA:
    """Exponential moving average of weights (YOLOv5's ModelEMA): steadier evaluations and checkpoints."""

    def __init__(self, model: torch.nn.Module, decay: float = 0.999, tau: float = 1000.0) -> None:
        self.model = copy.deepcopy(model).eval()
        self.decay, self.tau, self.updates = decay, tau, 0
        for p in self.model.parameters():
            p.requires_grad_(False)

    def update(self, model: torch.nn.Module) -> None:
        self.updates += 1
        d = self.decay * (1 - math.exp(-self.updates / self.tau))
        with torch.no_grad():
            src = model.state_dict()
            for k, v in self.model.state_dict().items():
                if v.dtype.is_floating_point:
                    v.mul_(d).add_(src[k].detach(), alpha=1 - d)
                else:
                    v.copy_(src[k])


def evaluate_model(model: Detector, images: np.ndarray, samples: list[Sample]) -> dict:
    """Detection report of a model on preloaded images (batched torch inference, score threshold 0.01)."""
    dec = DecodedDetector(model).eval()
    device = next(model.parameters()).device
    dets = []
    with torch.no_grad():
        for i in range(0, len(samples), 32):
            x = torch.from_numpy(np.ascontiguousarray(images[i:i + 32].transpose(0, 3, 1, 2))).float().div_(255.0)
            for row in dec(to_device(x, device)).float().cpu().numpy():
                dets.append(postprocess(row, 0.01))
    return detection_report(samples, dets, model.config.num_classes)


def save_checkpoint(path: Path, model: Detector, meta: dict) -> None:
    state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    config = {"width": model.config.width, "num_classes": model.config.num_classes, "strides": list(model.config.strides)}
    if model.config.s4_blocks:  # only when used, so older readers still load the models without them
        config["s4_blocks"] = model.config.s4_blocks
    if model.config.s4_pixels:
        config["s4_pixels"] = True
    save(path, {"state_dict": state, "config": config, "classes": CLASSES[:model.config.num_classes], "input_hw": INPUT_HW,
                **meta})


def init_from(model: Detector, source: dict[str, torch.Tensor], name: str = "--init") -> str:
    """Warm start (``--init``): every tensor of ``source`` whose name and shape match ``model``'s. New layers keep
    their initialisation (the stride-4 refinement blocks start as the identity, so the model starts as the one it
    comes from). A head of more classes than the source's (the road signs appended to the six classes of before)
    takes the source's rows (box, objectness, the old classes' channels) exactly and keeps its own fresh rows for
    the new classes (RetinaNet's prior, so they start near 0.05 and do not flood the old classes' NMS groups).
    Returns a sentence saying what was taken."""
    own = model.state_dict()
    taken = {k: v for k, v in source.items() if k in own and own[k].shape == v.shape}
    grown = []
    for k, v in source.items():
        if k in taken or k not in own or not k.startswith("head"):
            continue
        mine = own[k]
        if v.ndim == mine.ndim and v.shape[0] < mine.shape[0] and v.shape[1:] == mine.shape[1:]:
            merged = mine.clone()
            merged[:v.shape[0]] = v
            taken[k] = merged
            grown.append(f"{k} {v.shape[0]}->{mine.shape[0]}")
    model.load_state_dict(taken, strict=False)
    new = sorted({k.split(".")[0] for k in own if k not in taken})
    msg = f"{name}: {len(taken)} of {len(own)} tensors taken; new: {new}"
    if grown:
        msg += (f"; grown heads (the source's rows copied, the new classes' rows fresh): {', '.join(grown)}")
    return msg


# --------------------------------------------------------------------------- training
def train(args: argparse.Namespace) -> int:
    """``train.py detector train``: AdamW, cosine schedule, EMA, best checkpoint by val mAP@0.5; under torchrun one
    DistributedDataParallel process per GPU (or gloo process on the CPU)."""
    try:  # before any work: a missing GPU is one sentence
        dist, device = start_training(getattr(args, "device", "cpu"))
        workers = check_loader_workers(getattr(args, "loader_workers", 0))
    except ValueError as exc:
        print(f"towndrive train detector train: {exc}", file=sys.stderr)
        return 2
    with process_group(dist, device):
        return _train(args, device, dist, workers)


def _train(args: argparse.Namespace, device: torch.device, dist: Distributed, workers: int) -> int:
    torch.manual_seed(args.seed)
    torch.set_num_threads(max(1, args.threads))
    rng = np.random.default_rng(args.seed)
    train_s = [x for name in str(getattr(args, "train_splits", "train")).split(",") for x in load_split(args.data, name)]
    repeat = int(getattr(args, "repeat_sign_frames", 1))
    if repeat > 1:  # frames with a labelled road sign (a rarer sight than cars or people) several times per epoch
        sign_ids = [CLASSES.index(n) for n in SIGN_CLASSES]
        with_signs = [x for x in train_s if np.isin(x.cls[~x.ignore], sign_ids).any()]
        print(f"{len(with_signs)} training frames with a labelled sign, {repeat} times each per epoch")
        train_s = train_s + with_signs * (repeat - 1)
    val_s = [x for name in str(getattr(args, "val_splits", "val")).split(",") for x in load_split(args.data, name)]
    train_x = load_images(train_s, "train")
    val_x = load_images(val_s, "val") if dist.is_main else None  # rank 0 alone validates
    strides = tuple(int(v) for v in str(getattr(args, "strides", "8,16")).split(","))
    model = Detector(DetectorConfig(width=getattr(args, "width", 32), strides=strides,
                                    num_classes=getattr(args, "classes", len(CLASSES)),
                                    s4_blocks=getattr(args, "s4_blocks", 0),
                                    s4_pixels=getattr(args, "s4_pixels", False)))
    obj_iou, scale_prob = getattr(args, "obj_iou", 0.0), getattr(args, "scale_prob", 1.0)
    box_l1 = getattr(args, "box_l1", 0.0)
    if getattr(args, "init", ""):
        if args.resume:
            raise ValueError("Pass --resume or --init, not both.")
        src = load_checkpoint(args.init, "detector (--init)")
        print(init_from(model, src["state_dict"], args.init))
    if args.resume:
        ckpt = load_checkpoint(args.resume, "detector (--resume)")
        cfg = ckpt.get("config", {})
        if (tuple(cfg.get("strides", STRIDES)) != strides or cfg.get("width", 32) != model.config.width
                or cfg.get("s4_blocks", 0) != model.config.s4_blocks
                or cfg.get("s4_pixels", False) != model.config.s4_pixels):
            raise ValueError(f"--resume {args.resume} has strides {tuple(cfg.get('strides', STRIDES))}, width "
                             f"{cfg.get('width', 32)}, s4_blocks {cfg.get('s4_blocks', 0)} and s4_pixels "
                             f"{cfg.get('s4_pixels', False)}; pass the same --strides, --width, --s4-blocks and "
                             "--s4-pixels (or --init to warm-start a different shape).")
        model.load_state_dict(ckpt["state_dict"])
    model.to(device)
    scaler = grad_scaler(device)
    ema = EMA(model)
    trained = data_parallel(model, device, dist)  # under torchrun: rank 0's weights everywhere, gradients averaged
    decay, no_decay = [], []
    for name, p in model.named_parameters():
        (no_decay if p.ndim <= 1 or name.endswith(".bias") else decay).append(p)
    opt = torch.optim.AdamW([{"params": decay, "weight_decay": 5e-4}, {"params": no_decay, "weight_decay": 0.0}],
                            lr=args.lr)
    steps_per_epoch = len(train_s) // (args.batch * dist.world_size)  # per process: each trains on its share
    in_process = workers == 0 and not dist.enabled  # the one random stream of before loader workers and torchrun
    total = steps_per_epoch * args.epochs
    warmup = min(300, total // 10)
    out = Path(args.out)
    log_path = out.with_suffix(".log.jsonl")
    log_path.parent.mkdir(parents=True, exist_ok=True)
    best, t0, step = -1.0, time.perf_counter(), 0
    history = []
    print(f"train {len(train_s)} frames, val {len(val_s)} frames, {steps_per_epoch} steps/epoch, "
          f"{sum(p.numel() for p in model.parameters())} parameters, {torch.get_num_threads()} thread(s), on {device}"
          + (f", {workers} loader worker{'s' if workers > 1 else ''}" if workers else "") + dist.label)
    stop = False
    for epoch in range(args.epochs):
        trained.train()
        if in_process:
            order = rng.permutation(len(train_s))
            batches: Any = (make_batch(train_x, train_s, order[b * args.batch:(b + 1) * args.batch], rng, strides,
                                       scale_prob) for b in range(steps_per_epoch))
        else:  # every rank the same permutation, each its own slice; batch b augmented from (seed, epoch, rank, b)
            order = np.random.default_rng((args.seed, epoch)).permutation(len(train_s))
            mine = order[dist.rank::dist.world_size][:steps_per_epoch * args.batch]
            make = functools.partial(_seeded_batch, images=train_x, samples=train_s, strides=strides,
                                     scale_prob=scale_prob)
            key = (args.seed, epoch, dist.rank)
            batches = batch_loader(SeededBatches(make, mine, args.batch, key), workers, device, seed_of(key))
        bar = tqdm(batches, total=steps_per_epoch, desc=f"epoch {epoch + 1}/{args.epochs}", unit="batch",
                   disable=not dist.is_main)
        run = {"box": 0.0, "obj": 0.0, "cls": 0.0}
        for b, (x, tgs) in enumerate(bar):
            lr = args.lr * (step / max(warmup, 1) if step < warmup
                            else 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * (step - warmup) / max(total - warmup, 1))))
            for g in opt.param_groups:
                g["lr"] = lr
            # On CUDA: a pinned non-blocking copy, an autocast forward, the loss in fp32, fp16 through a GradScaler;
            # on the CPU each of these is a no-op (float() of an fp32 map is the map itself).
            with autocast(device):
                maps = trained(to_device(x, device))
            loss, parts = yolo_loss([m.float() for m in maps], tgs, strides, obj_iou, box_l1)
            opt.zero_grad(set_to_none=True)
            backward_step(loss, opt, scaler, clip=(model.parameters(), 10.0))
            ema.update(model)
            step += 1
            for k in run:
                run[k] = 0.9 * run[k] + 0.1 * parts[k] if b else parts[k]
            bar.set_postfix(box=f"{run['box']:.3f}", obj=f"{run['obj']:.4f}", cls=f"{run['cls']:.3f}", lr=f"{lr:.1e}")
            if args.time_limit_min and dist.agree(time.perf_counter() - t0 > args.time_limit_min * 60):
                stop = True  # every rank at the same step (their next all-reduce would wait for the others)
                break
        bar.close()
        if not dist.is_main:
            dist.barrier()  # rank 0 validates and writes the epoch's checkpoints
            if stop:
                break
            continue
        assert val_x is not None
        rep = evaluate_model(ema.model, val_x, val_s)
        score = rep["map50"]
        entry = {"epoch": epoch + 1, "steps": step, "minutes": round((time.perf_counter() - t0) / 60, 2),
                 "val_map50": round(score, 4), "val_map50_95": round(rep["map50_95"], 4),
                 "val_ap50": {k: round(v["ap50"], 4) for k, v in rep["per_class"].items()},
                 "val_within_40m_ap50": {k: round(v["ap50"], 4) for k, v in rep["within_40m"].items()},
                 "loss": {k: round(v, 4) for k, v in run.items()}}
        history.append(entry)
        with open(log_path, "a") as f:
            f.write(json.dumps(entry) + "\n")
        msg = "  ".join(f"{k} {v:.3f}" for k, v in entry["val_ap50"].items())
        print(f"epoch {epoch + 1}: val mAP@0.5 {score:.3f}, mAP@0.5:0.95 {rep['map50_95']:.3f} | {msg}")
        meta = {"epoch": epoch + 1, "val_map50": score, "seed": args.seed, "command": "train.py detector train",
                "args": vars(args) | {"run": None}}
        if getattr(args, "save_epochs", False):
            save_checkpoint(out.with_suffix(f".e{epoch + 1}.pt"), ema.model, meta)
        if score > best:
            best = score
            save_checkpoint(out, ema.model, meta)
            print(f"  best so far: saved {out}")
        dist.barrier()
        if stop:
            print(f"Time limit of {args.time_limit_min} min reached after {step} steps.")
            break
    if not dist.is_main:
        return 0
    print(f"Training took {(time.perf_counter() - t0) / 60:.1f} min; best val mAP@0.5 {best:.3f} -> {out}")
    return 0
