"""Two detectors on the same frames: AP@0.5 per class, the difference, and whether it is beyond noise.

    OMP_NUM_THREADS=1 python bench/compare_detectors.py --before OLD.onnx --after NEW.onnx --split test+test_classic

Noise: a paired bootstrap over frames (the same resampled frames for both models, ``--resamples`` times); the
interval printed is the 2.5-97.5 percentile of the difference. A difference whose interval holds 0 is within the
noise of the test set's size. Both models run through ONNX Runtime (``.onnx``) or torch (``.pt``) with the shipped
pedestrian refiner unless ``--refiner none``; ``--after-signs`` gives the second model a sign reader.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv: list[str] | None = None) -> int:
    import numpy as np

    from towndrive.agent.perception.classes import CLASSES
    from towndrive.agent.perception.detector import OnnxDetector, TorchDetector
    from towndrive.agent.training.detector_eval import class_ap, load_split, model_classes, read_rgb, resolve_refiner

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--before", required=True)
    parser.add_argument("--after", required=True)
    parser.add_argument("--after-signs", default="", help="sign reader for --after (a path; default none)")
    parser.add_argument("--data", default="data/datasets/detector")
    parser.add_argument("--split", default="test", help="a split, or several pooled with + (test+test_classic)")
    parser.add_argument("--refiner", default="auto", help="pedestrian refiner: auto (the shipped one), a path or none")
    parser.add_argument("--resamples", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    samples = [x for part in args.split.split("+") for x in load_split(args.data, part)]
    images = [read_rgb(s.image) for s in samples]
    dets, ncls = [], []
    for path, signs in ((args.before, None), (args.after, args.after_signs or None)):
        make = OnnxDetector if path.endswith(".onnx") else TorchDetector
        model = make(path, score_threshold=0.01, refiner=resolve_refiner(args.refiner, path), signs=signs)
        ncls.append(model_classes(model))
        dets.append([model(img) for img in images])
    rng = np.random.default_rng(args.seed)
    draws = [rng.integers(0, len(samples), len(samples)) for _ in range(args.resamples)]
    rows = [(CLASSES[c], c, None) for c in range(min(ncls))] + [("car within 40 m", 0, 40.0),
                                                                 ("pedestrian within 40 m", 2, 40.0)]
    print(f"{args.before} -> {args.after} on {args.split} ({len(samples)} frames), AP@0.5; paired bootstrap over "
          f"frames ({args.resamples} resamples): the difference's 95% interval")
    print("| class | labelled | before | after | difference | 95% interval | beyond noise? |")
    print("|---|---:|---:|---:|---:|---|---|")
    for name, c, dist in rows:
        full = [class_ap(samples, d, c, max_distance_m=dist) for d in dets]
        diffs = []
        for idx in draws:
            sub = [samples[k] for k in idx]
            a, b = (class_ap(sub, [d[k] for k in idx], c, thresholds=np.array([0.5]), max_distance_m=dist)["ap50"]
                    for d in dets)
            diffs.append(b - a)
        lo, hi = np.percentile(diffs, [2.5, 97.5])
        diff = full[1]["ap50"] - full[0]["ap50"]
        verdict = "no" if lo <= 0 <= hi else ("better" if lo > 0 else "worse")
        print(f"| {name} | {full[0]['gt']} | {full[0]['ap50']:.3f} | {full[1]['ap50']:.3f} | {diff:+.3f} | "
              f"{lo:+.3f} to {hi:+.3f} | {verdict} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
