"""Detector evaluation: AP per class (COCO-style, with "don't care" regions), traffic-light state and latency.

AP is the area under the 101-point interpolated precision-recall curve (COCO). A detection counts as a
true positive when it overlaps an unmatched ground-truth box of its class by at least the IoU threshold.
Detections that instead fall on an *ignore* region (objects the auto-labeller judged too small, occluded,
truncated or side-on, and objects outside a distance filter) count neither way, as in KITTI. mAP@0.5:0.95
averages AP over IoU thresholds 0.50, 0.55, ..., 0.95.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from towndrive.agent.perception.classes import CLASSES, LIGHT_CLASSES, SIGN_CLASSES, STATE_OF_CLASS
from towndrive.agent.perception.detector import NMS_GROUP, Detection, box_iou
from towndrive.agent.shipped import MODELS_DIR

IOU_THRESHOLDS = np.round(np.arange(0.5, 0.96, 0.05), 2)


@dataclass
class Sample:
    """One labelled frame: its image path and every object (labels and ignore regions) with distances."""

    image: str
    weather: str
    boxes: np.ndarray  # K x 4 (x0, y0, x1, y1)
    cls: np.ndarray  # K
    ignore: np.ndarray  # K bool
    distance_m: np.ndarray  # K


def load_split(root: str | Path, split: str) -> list[Sample]:
    """The split's frames from ``<split>_meta.jsonl`` (written next to the YOLO labels by the generator)."""
    root = Path(root)
    meta = root / f"{split}_meta.jsonl"
    if not meta.is_file():
        raise FileNotFoundError(f"{meta} not found; generate the dataset with `python train.py detector dataset`.")
    out = []
    for line in meta.read_text().splitlines():
        rec = json.loads(line)
        objs = rec["objects"]
        out.append(Sample(str(root / rec["image"]), rec["weather"],
                          np.array([o["box"] for o in objs], np.float32).reshape(-1, 4),
                          np.array([o["cls"] for o in objs], np.int64),
                          np.array([o["ignore"] for o in objs], bool),
                          np.array([o["distance_m"] for o in objs], np.float32)))
    return out


def read_rgb(path: str) -> np.ndarray:
    img = cv2.imread(path, cv2.IMREAD_COLOR)
    if img is None:
        raise FileNotFoundError(f"Image {path} is missing or unreadable; regenerate the dataset.")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


# --------------------------------------------------------------------------- AP
def _match_image(det_boxes: np.ndarray, gt: np.ndarray, ign: np.ndarray, thr: float) -> np.ndarray:
    """Per detection (sorted by score): 1 true positive, 0 false positive, -1 ignored."""
    out = np.zeros(len(det_boxes), np.int8)
    used = np.zeros(len(gt), bool)
    iou = box_iou(det_boxes, gt) if len(gt) else np.zeros((len(det_boxes), 0))
    if len(ign):
        inter_iou = box_iou(det_boxes, ign)
        lt = np.maximum(det_boxes[:, None, :2], ign[None, :, :2])
        rb = np.minimum(det_boxes[:, None, 2:], ign[None, :, 2:])
        inter = np.prod(np.clip(rb - lt, 0, None), axis=2)
        ioa = inter / np.maximum(np.prod(det_boxes[:, 2:] - det_boxes[:, :2], axis=1), 1e-9)[:, None]
        on_ignore = (ioa >= 0.5).any(1) | (inter_iou >= thr).any(1)
    else:
        on_ignore = np.zeros(len(det_boxes), bool)
    for i in range(len(det_boxes)):
        if len(gt):
            cand = np.where(used, -1.0, iou[i])
            j = int(np.argmax(cand))
            if cand[j] >= thr:
                used[j] = True
                out[i] = 1
                continue
        out[i] = -1 if on_ignore[i] else 0
    return out


def average_precision(tp: np.ndarray, scores: np.ndarray, n_gt: int) -> float:
    """COCO 101-point interpolated AP from per-detection TP flags (ignored ones removed) and scores."""
    if n_gt == 0:
        return float("nan")
    order = np.argsort(-scores, kind="stable")
    tp = tp[order].astype(np.float64)
    ctp, cfp = np.cumsum(tp), np.cumsum(1 - tp)
    recall = ctp / n_gt
    precision = ctp / np.maximum(ctp + cfp, 1e-9)
    precision = np.maximum.accumulate(precision[::-1])[::-1] if len(precision) else precision
    ap = 0.0
    for r in np.linspace(0, 1, 101):
        k = np.searchsorted(recall, r, side="left")
        ap += precision[k] if k < len(precision) else 0.0
    return ap / 101


def class_ap(samples: list[Sample], detections: list[list[Detection]], cls: int,
             thresholds: np.ndarray = IOU_THRESHOLDS, max_distance_m: float | None = None) -> dict:
    """AP of one class at each IoU threshold; ``max_distance_m`` turns farther ground truth into ignore regions."""
    group = NMS_GROUP[CLASSES[cls]]
    group_cls = [k for k, name in enumerate(CLASSES) if NMS_GROUP[name] == group]
    per_thr_tp: list[list[np.ndarray]] = [[] for _ in thresholds]
    scores: list[np.ndarray] = []
    n_gt = 0
    for s, dets in zip(samples, detections, strict=True):
        mine = [d for d in dets if d.cls == cls]
        mine.sort(key=lambda d: -d.score)
        db = np.array([d.box for d in mine], np.float32).reshape(-1, 4)
        near = np.ones(len(s.cls), bool) if max_distance_m is None else s.distance_m <= max_distance_m
        is_gt = (s.cls == cls) & ~s.ignore & near
        is_ign = np.isin(s.cls, group_cls) & (s.ignore | ~near)
        n_gt += int(is_gt.sum())
        scores.append(np.array([d.score for d in mine], np.float64))
        for t, thr in enumerate(thresholds):
            per_thr_tp[t].append(_match_image(db, s.boxes[is_gt], s.boxes[is_ign], float(thr)))
    sc = np.concatenate(scores) if scores else np.zeros(0)
    aps = []
    for t in range(len(thresholds)):
        flags = np.concatenate(per_thr_tp[t]) if per_thr_tp[t] else np.zeros(0, np.int8)
        keep = flags >= 0
        aps.append(average_precision(flags[keep], sc[keep], n_gt))
    return {"ap50": aps[0], "ap50_95": float(np.mean(aps)), "gt": n_gt}


OLD_CLASSES = CLASSES[:6]  # the classes of before the road signs (issue 31): compared across models of both kinds


def detection_report(samples: list[Sample], detections: list[list[Detection]], num_classes: int = len(CLASSES)) -> dict:
    """AP@0.5 and AP@0.5:0.95 per class (all distances), cars/pedestrians within 40 m, and the means: over every
    class with ground truth (``map50``), over the six classes of before the signs (``map50_old``) and over the
    signs (``map50_signs``). A model of fewer classes (``num_classes``) is scored on its own classes only."""
    per = {CLASSES[c]: class_ap(samples, detections, c) for c in range(num_classes)}
    within = {CLASSES[c]: class_ap(samples, detections, c, max_distance_m=40.0) for c in (0, 2)}

    def mean(names: tuple[str, ...] | None, key: str) -> float:
        vals = [v[key] for k, v in per.items() if v["gt"] > 0 and (names is None or k in names)]
        return float(np.mean(vals)) if vals else float("nan")

    return {"per_class": per, "within_40m": within, "map50": mean(None, "ap50"), "map50_95": mean(None, "ap50_95"),
            "map50_old": mean(OLD_CLASSES, "ap50"), "map50_signs": mean(SIGN_CLASSES, "ap50")}


def predict(samples: list[Sample], detect: Callable[[np.ndarray], list[Detection]], progress: bool = True,
            images: np.ndarray | None = None) -> list[list[Detection]]:
    """Run a detector over a split (images from disk unless given as an N x H x W x 3 array)."""
    out = []
    for k, s in enumerate(tqdm(samples, desc="detect", unit="frame", disable=not progress, leave=False)):
        out.append(detect(images[k] if images is not None else read_rgb(s.image)))
    return out


# --------------------------------------------------------------------------- traffic-light state
DISTANCE_BINS_M = (0.0, 10.0, 20.0, 30.0, 40.0, 60.0)


def light_state_report(samples: list[Sample], detections: list[list[Detection]],
                       images: list[np.ndarray] | None = None) -> dict:
    """Per-state precision and recall of the detector's light classes and of the HSV baseline, and accuracy
    against distance.

    For every labelled light, the detection it matches (IoU >= 0.3 with any light-class detection) gives the
    detector's state; the HSV baseline classifies the same matched box's pixels (``hsv`` on detector boxes)
    and, as an upper bound for it, the ground-truth box (``hsv_gt_box``). A light with no matching detection
    counts as missed (state "none") for the detector and for HSV on detector boxes.
    """
    from towndrive.agent.perception.light_state import hsv_state

    states = ("red", "yellow", "green")
    light_ids = [CLASSES.index(n) for n in LIGHT_CLASSES]
    rows = []  # (true state, detector state, hsv-on-det state, hsv-on-gt state, distance)
    false_lights = {"detector": dict.fromkeys(states, 0), "hsv": dict.fromkeys(states, 0)}
    for k, (s, dets) in enumerate(zip(samples, detections, strict=True)):
        img = images[k] if images is not None else read_rgb(s.image)
        ld = [d for d in dets if d.cls in light_ids]
        db = np.array([d.box for d in ld], np.float32).reshape(-1, 4)
        is_gt = np.isin(s.cls, light_ids) & ~s.ignore
        gt_boxes = s.boxes[is_gt]
        gt_states = [STATE_OF_CLASS[CLASSES[c]] for c in s.cls[is_gt]]
        iou = box_iou(gt_boxes, db) if len(db) and len(gt_boxes) else np.zeros((len(gt_boxes), len(db)))
        used = set()
        for g in range(len(gt_boxes)):
            j = int(np.argmax(iou[g])) if len(db) else -1
            if j >= 0 and iou[g, j] >= 0.3 and j not in used:
                used.add(j)
                det_state = STATE_OF_CLASS[CLASSES[ld[j].cls]]
                hsv_det = hsv_state(img, ld[j].box)
            else:
                det_state, hsv_det = "none", "none"
            rows.append((gt_states[g], det_state, hsv_det, hsv_state(img, tuple(gt_boxes[g])), float(s.distance_m[is_gt][g])))
        # Detections on nothing labelled (and not on an ignored light) are false lights.
        ign = s.boxes[np.isin(s.cls, light_ids) & s.ignore]
        for j, d in enumerate(ld):
            if j in used:
                continue
            if len(ign) and box_iou(np.array([d.box], np.float32), ign).max() >= 0.3:
                continue
            false_lights["detector"][STATE_OF_CLASS[CLASSES[d.cls]]] += 1
            hs = hsv_state(img, d.box)
            if hs in false_lights["hsv"]:
                false_lights["hsv"][hs] += 1
    report: dict = {"lights": len(rows)}
    for method, col in (("detector", 1), ("hsv_on_detector_boxes", 2), ("hsv_on_gt_boxes", 3)):
        per = {}
        for st in states:
            tp = sum(1 for r in rows if r[0] == st and r[col] == st)
            n_true = sum(1 for r in rows if r[0] == st)
            n_pred = sum(1 for r in rows if r[col] == st)
            if method != "hsv_on_gt_boxes":
                n_pred += false_lights["detector" if method == "detector" else "hsv"][st]
            per[st] = {"precision": tp / n_pred if n_pred else float("nan"),
                       "recall": tp / n_true if n_true else float("nan"), "n": n_true}
        acc_bins = []
        for lo, hi in zip(DISTANCE_BINS_M[:-1], DISTANCE_BINS_M[1:], strict=True):
            sel = [r for r in rows if lo <= r[4] < hi]
            acc_bins.append({"range_m": [lo, hi], "n": len(sel),
                             "accuracy": sum(r[0] == r[col] for r in sel) / len(sel) if sel else float("nan")})
        red30 = [r for r in rows if r[0] == "red" and r[4] <= 30.0]
        per_all = sum(r[0] == r[col] for r in rows) / len(rows) if rows else float("nan")
        report[method] = {"per_state": per, "accuracy": per_all, "accuracy_vs_distance": acc_bins,
                          "red_recall_within_30m": (sum(r[col] == "red" for r in red30) / len(red30)
                                                    if red30 else float("nan")),
                          "red_within_30m": len(red30)}
    return report


# --------------------------------------------------------------------------- command
def resolve_refiner(choice: str, model: str) -> str | None:
    """``auto``: the shipped pedestrian refiner in the model's format, if it is there; ``none``: no refiner."""
    if choice == "none":
        return None
    if choice == "auto":
        models = MODELS_DIR
        path = models / ("ped_refiner.onnx" if model.endswith(".onnx") else "ped_refiner.pt")
        return str(path) if path.is_file() else None
    return choice


def resolve_signs(choice: str, model: str) -> str | None:
    """``auto``: the shipped sign reader in the model's format, if it is there and the model has sign classes;
    ``none``: no reader (the detector's own sign classes)."""
    if choice == "none":
        return None
    if choice == "auto":
        path = MODELS_DIR / ("sign_reader.onnx" if model.endswith(".onnx") else "sign_reader.pt")
        return str(path) if path.is_file() else None
    return choice


def model_classes(detector) -> int:
    """How many classes a ``TorchDetector`` or ``OnnxDetector`` reports (its output has 4 + 1 + that many columns)."""
    if hasattr(detector, "session"):
        width = detector.session.get_outputs()[0].shape[-1]
        if isinstance(width, int):
            return width - 5
        return int(detector.raw(np.zeros((160, 320, 3), np.uint8)).shape[-1]) - 5
    return int(detector.model.net.config.num_classes)


def evaluate_command(args: argparse.Namespace) -> int:
    """``train.py detector evaluate``: print and save the full report for a .pt or .onnx model, per split; with
    several splits (``--split test,test_downtown``) also a table of AP@0.5 per class and split."""
    from towndrive.agent.perception.detector import OnnxDetector, TorchDetector

    model = str(args.model)
    # Low score threshold for AP (the whole precision-recall curve); the light-state report uses the
    # operating threshold the driving stack uses.
    make = OnnxDetector if model.endswith(".onnx") else TorchDetector
    refiner = resolve_refiner(getattr(args, "refiner", "none"), model)
    signs = resolve_signs(getattr(args, "signs", "none"), model)
    det_ap = make(model, score_threshold=0.01, refiner=refiner)
    nc = model_classes(det_ap)
    if signs and nc > len(CLASSES) - len(SIGN_CLASSES):
        det_ap = make(model, score_threshold=0.01, refiner=refiner, signs=signs)
    else:
        signs = None  # a model of before the signs has no sign boxes to read
    splits = [x.strip() for x in str(args.split).split(",") if x.strip()]
    reports = {}
    for split in splits:
        samples = [x for part in split.split("+") for x in load_split(args.data, part)]  # a+b: pooled
        images = [read_rgb(s.image) for s in tqdm(samples, desc="load", unit="frame", leave=False)]
        dets = predict(samples, det_ap, images=images)
        report = {"model": model, "refiner": refiner, "signs": signs, "split": split, "frames": len(samples),
                  "classes": list(CLASSES[:nc]), "detection": detection_report(samples, dets, nc)}
        op = 0.3
        dets_op = [[d for d in ds if d.score >= op] for ds in dets]
        report["light_state"] = light_state_report(samples, dets_op, images)
        report["light_state"]["score_threshold"] = op
        print_report(report)
        reports[split] = report
    if len(splits) > 1:
        print_table(reports)
    Path(args.report).parent.mkdir(parents=True, exist_ok=True)
    Path(args.report).write_text(json.dumps(reports[splits[0]] if len(splits) == 1 else reports, indent=1))
    print(f"Report written to {args.report}")
    return 0


def ap_table(reports: dict[str, dict]) -> list[str]:
    """Lines of a Markdown table: AP@0.5 (and the labelled count) per class and split, then the means."""
    splits = list(reports)
    lines = ["| class | " + " | ".join(splits) + " |", "|---|" + "---:|" * len(splits)]
    for name in CLASSES:
        cells = []
        for sp in splits:
            v = reports[sp]["detection"]["per_class"].get(name)
            if v is None:
                cells.append("-")
            elif v["gt"] == 0:
                cells.append("(0)")
            else:
                cells.append(f"{v['ap50']:.3f} ({v['gt']})")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    for key, label in (("map50_old", "mAP, six old classes"), ("map50_signs", "mAP, signs"), ("map50", "mAP, all")):
        cells = [f"{reports[sp]['detection'][key]:.3f}" if reports[sp]["detection"][key] == reports[sp]["detection"][key]
                 else "-" for sp in splits]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    for name in ("car", "pedestrian"):
        cells = [f"{reports[sp]['detection']['within_40m'][name]['ap50']:.3f}" for sp in splits]
        lines.append(f"| {name} within 40 m | " + " | ".join(cells) + " |")
    return lines


def print_table(reports: dict[str, dict]) -> None:
    first = next(iter(reports.values()))
    print(f"\nAP@0.5 (labelled objects) of {first['model']}, per split:")
    print("\n".join(ap_table(reports)))


def print_report(report: dict) -> None:
    det = report["detection"]
    refiner = f" + {report['refiner']}" if report.get("refiner") else " (no pedestrian refiner)"
    signs = f" + {report['signs']}" if report.get("signs") else ""
    print(f"{report['model']}{refiner}{signs} on {report['split']} ({report['frames']} frames)")
    print(f"{'class':<14}{'GT':>6}{'AP@0.5':>9}{'AP@.5:.95':>11}")
    for name, v in det["per_class"].items():
        print(f"{name:<14}{v['gt']:>6}{v['ap50']:>9.3f}{v['ap50_95']:>11.3f}")
    print(f"{'mean':<14}{'':>6}{det['map50']:>9.3f}{det['map50_95']:>11.3f}")
    for name, v in det["within_40m"].items():
        print(f"{name + ' <=40 m':<14}{v['gt']:>6}{v['ap50']:>9.3f}{v['ap50_95']:>11.3f}")
    ls = report["light_state"]
    print(f"traffic-light state ({ls['lights']} labelled lights, score >= {ls['score_threshold']})")
    for method in ("detector", "hsv_on_detector_boxes", "hsv_on_gt_boxes"):
        m = ls[method]
        states = "  ".join(f"{st}: P {v['precision']:.3f} R {v['recall']:.3f} (n={v['n']})"
                           for st, v in m["per_state"].items())
        print(f"  {method:<22} acc {m['accuracy']:.3f}  red recall <=30 m {m['red_recall_within_30m']:.3f} "
              f"(n={m['red_within_30m']})  {states}")
        print("    accuracy vs distance: " + "  ".join(
            f"{b['range_m'][0]:.0f}-{b['range_m'][1]:.0f} m {b['accuracy']:.3f} (n={b['n']})"
            for b in m["accuracy_vs_distance"]))
