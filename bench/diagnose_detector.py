"""Why a detector misses cars and pedestrians within 40 m: AP against the IoU threshold, recall by box height,
in groups or alone, and how far the matched boxes are off.

    OMP_NUM_THREADS=1 python bench/diagnose_detector.py --model data/models/detector.pt --split val

AP much higher at IoU 0.3 than at 0.5 means boxes in roughly the right place but too loose (localisation);
low recall even at IoU 0.3 for small heights means objects not found; low recall only for objects overlapping
another of their class means confusion in groups.

Then, per class, AP@0.5 within 40 m by box-height bin (the other bins' objects made ignore regions), by
weather, and with the smallest bin (< 8 px) made ignore regions: diagnostics only, not figures to report
against a target (the labelling rules say what counts). An ``.onnx`` model runs through ONNX Runtime, a
``.pt`` checkpoint through torch; both with the shipped pedestrian refiner unless ``--refiner none``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv: list[str] | None = None) -> int:
    import numpy as np
    import torch

    from towndrive.agent.perception.classes import CLASSES
    from towndrive.agent.perception.detector import DecodedDetector, box_iou, load_detector, postprocess
    from towndrive.agent.training.detector_eval import class_ap, load_split
    from towndrive.agent.training.detector_train_loop import load_images

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default="data/models/detector.pt")
    parser.add_argument("--data", default="data/datasets/detector")
    parser.add_argument("--split", default="val")
    parser.add_argument("--refiner", default="auto", help="pedestrian refiner: auto (the shipped one, in the "
                        "model's format), a path, or none (the one-stage detector alone)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    samples = load_split(args.data, args.split)
    images = load_images(samples, args.split)
    dets = []
    from towndrive.agent.training.detector_eval import resolve_refiner

    refiner = resolve_refiner(args.refiner, args.model)
    if args.model.endswith(".onnx") or refiner:
        from towndrive.agent.perception.detector import OnnxDetector, TorchDetector

        make = OnnxDetector if args.model.endswith(".onnx") else TorchDetector
        model = make(args.model, score_threshold=0.01, refiner=refiner)
        dets = [model(img) for img in images]
    else:
        dec = DecodedDetector(load_detector(args.model)).eval()
        with torch.no_grad():
            for i in range(0, len(samples), 32):
                x = torch.from_numpy(np.ascontiguousarray(images[i:i + 32].transpose(0, 3, 1, 2))).float().div_(255.0)
                dets += [postprocess(row, 0.01) for row in dec(x).numpy()]
    print(f"{args.model} + {refiner or 'no refiner'} on {args.split} ({len(samples)} frames), objects within 40 m")
    for c in (CLASSES.index("car"), CLASSES.index("pedestrian")):
        aps = {t: class_ap(samples, dets, c, np.array([t]), 40.0)["ap50"] for t in (0.1, 0.3, 0.5, 0.7)}
        rows = []  # height, width, grouped, best IoU (score >= 0.3), width ratio, x offset
        for s, d in zip(samples, dets, strict=True):
            gt = (s.cls == c) & ~s.ignore & (s.distance_m <= 40.0)
            gb = s.boxes[gt]
            db = np.array([x.box for x in d if x.cls == c and x.score >= 0.3], np.float32).reshape(-1, 4)
            same = box_iou(gb, s.boxes[s.cls == c]) if len(gb) else np.zeros((0, 0))
            iou = box_iou(gb, db) if len(gb) and len(db) else np.zeros((len(gb), 0))
            for k in range(len(gb)):
                j = int(iou[k].argmax()) if iou.shape[1] else -1
                best = float(iou[k, j]) if j >= 0 else 0.0
                w = gb[k, 2] - gb[k, 0]
                ratio = (db[j, 2] - db[j, 0]) / w if j >= 0 else np.nan
                dx = abs((db[j, 0] + db[j, 2] - gb[k, 0] - gb[k, 2]) / 2) if j >= 0 else np.nan
                rows.append((gb[k, 3] - gb[k, 1], w, (same[k] > 0.05).sum() > 1, best, ratio, dx))
        r = np.array(rows, np.float64).reshape(-1, 6)
        print(f"\n{CLASSES[c]}: {len(r)} labelled; AP " + "  ".join(f"@{t} {a:.3f}" for t, a in aps.items()))
        print("  height px    n   recall IoU.5  IoU.3   median width px  width ratio  |dx| px   (score >= 0.3)")
        for lo, hi in ((0, 8), (8, 12), (12, 16), (16, 24), (24, 32), (32, 48), (48, 1000)):
            m = (r[:, 0] >= lo) & (r[:, 0] < hi)
            if m.any():
                hit = m & (r[:, 3] >= 0.3)
                print(f"  {lo:>3}-{hi:<5} {m.sum():5d}   {np.mean(r[m, 3] >= 0.5):.3f}  {np.mean(r[m, 3] >= 0.3):.3f}"
                      f"   {np.median(r[m, 1]):8.1f}   {np.nanmedian(r[hit, 4]) if hit.any() else np.nan:10.2f}"
                      f"  {np.nanmedian(r[hit, 5]) if hit.any() else np.nan:8.2f}")
        for flag, name in ((0, "alone"), (1, "in groups")):
            m = r[:, 2] == flag
            if m.any():
                print(f"  {name:<10} {m.sum():5d}   {np.mean(r[m, 3] >= 0.5):.3f}  {np.mean(r[m, 3] >= 0.3):.3f}")
        slices_within_40m(samples, dets, c)
    return 0


HEIGHT_BINS = ((0, 8), (8, 12), (12, 20), (20, 10_000))


def _only(samples: list, cls: int, keep) -> list:
    """Copies of the samples in which labelled objects of ``cls`` failing ``keep(sample) -> bool mask`` are
    ignore regions (neither true nor false positives)."""
    from dataclasses import replace

    out = []
    for s in samples:
        drop = (s.cls == cls) & ~s.ignore & ~keep(s)
        out.append(replace(s, ignore=s.ignore | drop))
    return out


def slices_within_40m(samples: list, dets: list, cls: int) -> None:
    """AP@0.5 within 40 m and recall at IoU 0.5 (any score; score >= 0.3) by height bin and by weather."""
    import numpy as np

    from towndrive.agent.perception.detector import box_iou
    from towndrive.agent.training.detector_eval import class_ap

    def row(name: str, sub: list, sub_dets: list) -> None:
        a = class_ap(sub, sub_dets, cls, np.array([0.5]), 40.0)
        rec = []
        for min_score in (0.01, 0.3):
            hit = n = 0
            for s, d in zip(sub, sub_dets, strict=True):
                gt = s.boxes[(s.cls == cls) & ~s.ignore & (s.distance_m <= 40.0)]
                db = np.array([x.box for x in d if x.cls == cls and x.score >= min_score], np.float32).reshape(-1, 4)
                n += len(gt)
                if len(gt) and len(db):
                    hit += int((box_iou(gt, db).max(1) >= 0.5).sum())
            rec.append(hit / n if n else float("nan"))
        print(f"  {name:<22}{a['gt']:6d}   {a['ap50']:.3f}   {rec[0]:.3f}    {rec[1]:.3f}")

    print("  within 40 m, IoU 0.5      n     AP    recall  recall(score>=0.3)")
    row("all", samples, dets)
    for lo, hi in HEIGHT_BINS:
        def in_bin(s, lo=lo, hi=hi):
            h = s.boxes[:, 3] - s.boxes[:, 1]
            return (h >= lo) & (h < hi)
        row(f"height {lo}-{hi if hi < 10_000 else ''} px", _only(samples, cls, in_bin), dets)
    for weather in sorted({s.weather for s in samples}):
        frames = [k for k, s in enumerate(samples) if s.weather == weather]
        row(f"weather {weather}", [samples[k] for k in frames], [dets[k] for k in frames])
    row("< 8 px ignored", _only(samples, cls, lambda s: (s.boxes[:, 3] - s.boxes[:, 1]) >= 8), dets)


if __name__ == "__main__":
    raise SystemExit(main())
