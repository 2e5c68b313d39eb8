"""Detector: auto-labelled dataset, training, evaluation and ONNX export (``train.py detector ACTION``).

Actions, in the order a new user runs them:

  dataset   drive the autopilot through many towns and weathers and write YOLO-layout labelled frames
  train     train the YOLO-style detector (agent/perception/detector.py), keep the best checkpoint by val mAP@0.5
  refiner   train the pedestrian refiner (agent/perception/ped_refiner.py) on the trained detector's candidates
  signs     train the sign reader (agent/perception/sign_reader.py), which reads which sign a sign box holds
  evaluate  per-class AP@0.5 and AP@0.5:0.95 on the held-out towns, cars/pedestrians within 40 m,
            traffic-light state against the HSV baseline, accuracy against distance
  export    write the ONNX model, check it against torch, run it through ONNX Runtime
  sheet     draw the ONNX model's detections on held-out dusk and night frames (docs/detections_sheet.png)
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from towndrive.agent.perception.classes import CLASSES, SIGN_CLASSES
from towndrive.agent.training.devices import add_device_argument, add_loader_argument
from towndrive.agent.training.outputs import add_replace_shipped

DEFAULT_DATA = "data/datasets/detector"
DEFAULT_CKPT = "data/models/detector.pt"  # the shipped models (read by eval; written only with --replace-shipped)
DEFAULT_ONNX = "data/models/detector.onnx"
DEFAULT_REFINER = "data/models/ped_refiner.pt"
DEFAULT_REFINER_ONNX = "data/models/ped_refiner.onnx"
RUN_CKPT = "out/detector/detector.pt"  # what training writes by default
RUN_REFINER = "out/detector/ped_refiner.pt"
RUN_SIGNS = "out/detector/sign_reader.pt"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True,
                                metavar="{dataset,train,refiner,signs,evaluate,export,sheet}")
    p = sub.add_parser("dataset", help="generate the auto-labelled YOLO dataset")
    p.add_argument("--out", default=DEFAULT_DATA, help="dataset root (images/, labels/, dataset.yaml)")
    p.add_argument("--train-frames", type=int, default=6000, help="frames in the train split")
    p.add_argument("--val-frames", type=int, default=1200, help="frames in the validation split")
    p.add_argument("--test-frames", type=int, default=1200, help="frames in the test split")
    p.add_argument("--peds-frames", type=int, default=6000, help="frames of the extra train_peds split")
    p.add_argument("--peds-count", type=int, default=60,
                   help="pedestrians per town in train_peds and train_peds2 (default world: 24)")
    p.add_argument("--peds2-frames", type=int, default=6000, help="frames of the extra train_peds2 split")
    p.add_argument("--rigs-frames", type=int, default=8000,
                   help="frames of the train_rigs split (each from another car's camera, autolabel.RigRange)")
    p.add_argument("--agent-frames", type=int, default=3000,
                   help="frames of the train_agent split (the camera-only agent drives: its own closed loop's frames)")
    p.add_argument("--splits", default="train,val,test",
                   help="which splits to (re)generate, comma-separated. train, val, test: classic towns 0-29, "
                   "100-109, 200-209; train_peds, train_peds2: extra training towns 30-59 and 60-99 with more "
                   "pedestrians; train_rigs, val_rigs, test_rigs: towns 30-99 (more pedestrians), 100-109 and "
                   "200-209, each frame from a camera drawn from other cars' mounts and lenses; train_agent: towns 30-99 "
                   "driven by the camera-only agent, what its detector sees; train_STYLE, val_STYLE, "
                   "test_STYLE (STYLE: classic, downtown, suburb): towns of that "
                   "town style from sim/splits.py's train (0-3999), validation (4000-4999) and test (5000-5999) "
                   "seeds, the first 30, 10 and 10 of each, sampled more often near road signs")
    p.add_argument("--town-style", default="",
                   help="STYLE: read the plain names train, val and test in --splits as train_STYLE, val_STYLE and "
                   "test_STYLE (e.g. --town-style suburb --splits train,val)")
    p.add_argument("--seed", type=int, default=0, help="seed of the towns, routes and traffic the frames come from")

    p = sub.add_parser("train", help="train the detector on a generated dataset")
    p.add_argument("--data", default=DEFAULT_DATA, help="dataset root")
    p.add_argument("--train-splits", default="train", help="training splits, comma-separated (e.g. train,train_peds)")
    p.add_argument("--val-splits", default="val",
                   help="validation splits for the checkpoint choice, comma-separated (e.g. val_classic,val_downtown)")
    p.add_argument("--out", default=RUN_CKPT, help="best checkpoint (by val mAP@0.5)")
    p.add_argument("--epochs", type=int, default=30, help="training epochs")
    p.add_argument("--batch", type=int, default=32, help="images per batch")
    p.add_argument("--lr", type=float, default=2e-3, help="learning rate (AdamW, cosine schedule)")
    p.add_argument("--seed", type=int, default=0, help="seed of initialisation and sampling")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    p.add_argument("--time-limit-min", type=float, default=0.0, help="stop after this many minutes (0: no limit)")
    p.add_argument("--resume", default="", help="continue from this checkpoint's weights")
    p.add_argument("--strides", default="4,8,16", help="head strides: 4,8,16 (the shipped model) or 8,16 (no stride-4 head)")
    p.add_argument("--width", type=int, default=32, help="backbone channels at stride 4 (doubled at each stride)")
    p.add_argument("--s4-blocks", type=int, default=0, help="residual blocks on the stride-4 path before its head")
    p.add_argument("--classes", type=int, default=len(CLASSES), choices=(len(CLASSES) - len(SIGN_CLASSES), len(CLASSES)),
                   help="the first N classes of agent/perception/classes.py: all of them, or the six without the road "
                   "signs (the default detector's, for towns without signs)")
    p.add_argument("--s4-pixels", action="store_true",
                   help="add each 4x4 cell's raw pixels (space-to-depth, 1x1 conv) to the stride-4 path")
    p.add_argument("--init", default="", help="warm start: this checkpoint's weights where names and shapes match "
                   "(unlike --resume, the model may have more layers, e.g. --s4-blocks). A checkpoint of fewer classes "
                   "(the six of before the road signs) grows: its head rows (box, objectness, its classes) are copied "
                   "exactly and the new classes' rows start fresh")
    p.add_argument("--obj-iou", type=float, default=0.0,
                   help="objectness target of a positive: 1 - g + g * IoU of its box (YOLOv5's gr); 0: always 1")
    p.add_argument("--box-l1", type=float, default=0.0,
                   help="weight of an L1 loss on the box edges in cells of their stride, added to GIoU (0: off); "
                   "GIoU alone lets a 2-3 px wide pedestrian's box grow wide when its centre is uncertain")
    p.add_argument("--save-epochs", action="store_true",
                   help="also save every epoch's EMA weights next to --out (NAME.eN.pt), to choose by another val figure")
    p.add_argument("--repeat-sign-frames", type=int, default=1,
                   help="training frames with a labelled road sign count this many times per epoch (signs are rare)")
    p.add_argument("--scale-prob", type=float, default=1.0,
                   help="share of training frames rescaled (0.75-1.3x); the rest are shifted by whole pixels")
    add_loader_argument(p)
    add_device_argument(p, more="Several GPUs (or CPU processes): start with torchrun --nproc_per_node N train.py "
                                "detector train ... (DDP; --batch per process)")

    p = sub.add_parser("refiner", help="train the second-stage pedestrian refiner on the detector's candidates")
    p.add_argument("--data", default=DEFAULT_DATA, help="dataset root")
    p.add_argument("--detector", default=DEFAULT_CKPT, help="the trained detector whose candidates it refines")
    p.add_argument("--train-splits", default="train,train_peds,train_peds2", help="comma-separated splits to train on")
    p.add_argument("--val-splits", default="val",
                   help="comma-separated splits for the epoch choice and the tuning (e.g. val_classic,val_downtown)")
    p.add_argument("--out", default=RUN_REFINER, help="best checkpoint (by val pedestrian AP@0.5 within 40 m)")
    p.add_argument("--epochs", type=int, default=6, help="training epochs")
    p.add_argument("--batch", type=int, default=256, help="crops per batch")
    p.add_argument("--lr", type=float, default=2e-3, help="learning rate")
    p.add_argument("--jitter", type=int, default=2, help="jittered copies of each labelled pedestrian per frame")
    p.add_argument("--seed", type=int, default=0, help="seed of initialisation and sampling")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    p.add_argument("--channels", default="24,48,96", help="the refiner's conv widths at its three scales")
    p.add_argument("--hidden", type=int, default=256, help="units of its hidden linear layer")
    add_device_argument(p)
    p.add_argument("--tune-only", action="store_true", help="no training: choose the score blend, the second NMS "
                   "and the candidate depth on val for the refiner at --out again, and write them into it")

    p = sub.add_parser("signs", help="train the second-stage sign reader on the detector's sign boxes")
    p.add_argument("--data", default=DEFAULT_DATA, help="dataset root")
    p.add_argument("--detector", default=DEFAULT_CKPT, help="the trained detector whose sign boxes it reads")
    p.add_argument("--train-splits", default="train,train_downtown,train_suburb",
                   help="comma-separated splits to train on (the classic towns' give false signs to reject)")
    p.add_argument("--val-splits", default="val_classic,val_downtown,val_suburb",
                   help="comma-separated splits for the epoch and score-blend choice")
    p.add_argument("--out", default=RUN_SIGNS, help="checkpoint (best epoch by val sign mAP@0.5 of detector + reader)")
    p.add_argument("--epochs", type=int, default=12, help="training epochs")
    p.add_argument("--batch", type=int, default=128, help="crops per batch")
    p.add_argument("--lr", type=float, default=2e-3, help="learning rate (AdamW, one-cycle)")
    p.add_argument("--jitter", type=int, default=4, help="jittered copies of each labelled sign per frame")
    p.add_argument("--seed", type=int, default=0, help="seed of initialisation and sampling")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    add_device_argument(p)

    p = sub.add_parser("evaluate", help="AP per class, light state vs HSV baseline, on the held-out split")
    p.add_argument("--data", default=DEFAULT_DATA, help="dataset root")
    p.add_argument("--model", default=DEFAULT_CKPT, help=".pt checkpoint or .onnx model")
    p.add_argument("--refiner", default="auto", help="pedestrian refiner: auto (data/models/ped_refiner.pt or .onnx, "
                   "as the model), a path, or none (the one-stage detector alone)")
    p.add_argument("--signs", default="auto", help="sign reader: auto (data/models/sign_reader.pt or .onnx, as the "
                   "model, if there), a path, or none (the detector's own sign classes)")
    p.add_argument("--split", default="test", help="test: towns 200-209, never used for training or model choice; "
                   "several, comma-separated (test,test_classic,test_downtown,test_suburb), add a table per class and "
                   "split; a+b pools splits (test_downtown+test_suburb)")
    p.add_argument("--report", default="out/detector/eval.json", help="where the JSON report goes")

    p = sub.add_parser("export", help="export the checkpoint (and the refiner) to ONNX with a parity check")
    p.add_argument("--model", default=RUN_CKPT, help="the detector checkpoint to export")
    p.add_argument("--out", default=None, help="the ONNX file (default: beside the checkpoint)")
    p.add_argument("--refiner", default="auto",
                   help=f"refiner checkpoint to export too (auto: {RUN_REFINER} if it exists; 'none': skip)")
    p.add_argument("--refiner-out", default=None, help="the refiner's ONNX file (default: beside its checkpoint)")
    p.add_argument("--signs", default="auto",
                   help=f"sign reader checkpoint to export too (auto: {RUN_SIGNS} if it exists; 'none': skip)")
    p.add_argument("--signs-out", default=None, help="the sign reader's ONNX file (default: beside its checkpoint)")
    add_replace_shipped(p, "detector, refiner and sign reader (.pt and .onnx)")

    p = sub.add_parser("sheet", help="a sheet of detections on held-out dusk and night frames")
    p.add_argument("--data", default=DEFAULT_DATA, help="dataset root")
    p.add_argument("--model", default=DEFAULT_ONNX, help="ONNX detector to draw")
    p.add_argument("--split", default="test", help="split the frames come from")
    p.add_argument("--out", default="docs/detections_sheet.png", help="the sheet (PNG)")
    p.add_argument("--refiner", default="auto", help="pedestrian refiner: auto, an .onnx path or none")
    p.add_argument("--signs", default="auto", help="sign reader: auto, an .onnx path or none")
    p.add_argument("--frames", type=int, default=12, help="frames on the sheet")


def run(args: argparse.Namespace) -> int:
    actions = {"dataset": _dataset, "train": _train, "refiner": _refiner, "signs": _signs, "evaluate": _evaluate,
               "export": _export, "sheet": _sheet}
    return actions[args.action](args)


def dataset_specs(args: argparse.Namespace) -> list:
    """The ``SplitSpec``s that ``--splits`` (and ``--town-style``) name, in the order given; one sentence for
    an unknown name or style."""
    from towndrive.agent.training.autolabel import default_splits, styled_splits
    from towndrive.sim.town_style import STYLES

    specs = default_splits(args.train_frames, args.val_frames, args.test_frames, args.peds_frames, args.peds_count,
                           args.peds2_frames, args.rigs_frames, args.agent_frames)
    for style in STYLES:
        specs += styled_splits(style, args.train_frames, args.val_frames, args.test_frames)
    by_name = {spec.name: spec for spec in specs}
    style = getattr(args, "town_style", "")
    if style and style not in STYLES:
        raise ValueError(f"unknown town style {style!r}; the styles are {', '.join(STYLES)}.")
    names = [n.strip() for n in args.splits.split(",") if n.strip()]
    if style:
        names = [f"{n}_{style}" if n in ("train", "val", "test") else n for n in names]
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise ValueError(f"unknown split {', '.join(unknown)}; the splits are {', '.join(by_name)}.")
    return [by_name[n] for n in dict.fromkeys(names)]


def _dataset(args: argparse.Namespace) -> int:
    import sys

    from towndrive.agent.training.autolabel import generate_split, write_dataset_yaml

    try:
        specs = dataset_specs(args)
    except ValueError as exc:
        print(f"train.py detector dataset: {exc}", file=sys.stderr)
        return 2
    root = Path(args.out)
    t0 = time.perf_counter()
    summary_path = root / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    for spec in specs:
        t_split = time.perf_counter()
        summary[spec.name] = generate_split(root, spec, args.seed)
        summary[spec.name]["towns"] = list(spec.town_seeds)
        summary[spec.name]["weathers"] = list(spec.weathers)
        if spec.pedestrian_count is not None:
            summary[spec.name]["pedestrian_count"] = spec.pedestrian_count
        if spec.town_style is not None:
            summary[spec.name]["town_style"] = spec.town_style
        summary[spec.name]["seconds"] = round(time.perf_counter() - t_split, 1)
    write_dataset_yaml(root)
    summary["seed"] = args.seed
    summary_path.write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1))
    print(f"Dataset written to {root} ({time.perf_counter() - t0:.0f} s).")
    return 0


def _train(args: argparse.Namespace) -> int:
    from towndrive.agent.training.detector_train_loop import train

    return train(args)


def _refiner(args: argparse.Namespace) -> int:
    from towndrive.agent.training.ped_refiner_training import train_refiner

    return train_refiner(args)


def _signs(args: argparse.Namespace) -> int:
    from towndrive.agent.training.sign_reader_training import train_sign_reader

    return train_sign_reader(args)


def _evaluate(args: argparse.Namespace) -> int:
    from towndrive.agent.training.detector_eval import evaluate_command

    return evaluate_command(args)


def _export(args: argparse.Namespace) -> int:
    from towndrive.agent.deploy.onnx_export import export_detector

    out = args.out or str(Path(args.model).with_suffix(".onnx"))
    diff = export_detector(args.model, out)
    print(f"Wrote {out}; largest |ONNX Runtime - torch| difference on the check inputs: {diff:.2e}")
    written = {"detector.pt": Path(args.model), "detector.onnx": Path(out)}
    refiner = args.refiner
    if refiner == "auto":
        refiner = RUN_REFINER if Path(RUN_REFINER).is_file() else "none"
    if refiner != "none":
        from towndrive.agent.deploy.onnx_export import export_refiner

        refiner_out = args.refiner_out or str(Path(refiner).with_suffix(".onnx"))
        diff = export_refiner(refiner, refiner_out)
        print(f"Wrote {refiner_out}; largest |ONNX Runtime - torch| difference: {diff:.2e}")
        written |= {"ped_refiner.pt": Path(refiner), "ped_refiner.onnx": Path(refiner_out)}
    signs = getattr(args, "signs", "none")
    if signs == "auto":
        signs = RUN_SIGNS if Path(RUN_SIGNS).is_file() else "none"
    if signs != "none":
        from towndrive.agent.deploy.onnx_export import export_sign_reader

        signs_out = getattr(args, "signs_out", None) or str(Path(signs).with_suffix(".onnx"))
        diff = export_sign_reader(signs, signs_out)
        print(f"Wrote {signs_out}; largest |ONNX Runtime - torch| difference: {diff:.2e}")
        written |= {"sign_reader.pt": Path(signs), "sign_reader.onnx": Path(signs_out)}
    if args.replace_shipped:
        from towndrive.agent.training.outputs import replace_shipped

        replace_shipped(list(written.values()), list(written))
    return 0


def _sheet(args: argparse.Namespace) -> int:
    """Half dusk, half night frames with the most labelled objects, spread over the split; 2 columns."""
    import cv2
    import numpy as np

    from towndrive.agent.overlays import draw_detections
    from towndrive.agent.perception.detector import OnnxDetector
    from towndrive.agent.training.detector_eval import load_split, read_rgb

    samples = load_split(args.data, args.split)
    from towndrive.agent.training.detector_eval import resolve_refiner, resolve_signs

    detector = OnnxDetector(args.model, score_threshold=0.3, refiner=resolve_refiner(args.refiner, args.model),
                            signs=resolve_signs(getattr(args, "signs", "auto"), args.model))
    tiles = []
    for weather in ("dusk", "night"):
        cand = [(k, s) for k, s in enumerate(samples) if s.weather == weather]
        cand.sort(key=lambda ks: (-int((~ks[1].ignore).sum()), ks[0]))
        chosen: list[int] = []
        for k, _ in cand:  # the busiest frames, at least 40 frames apart (other stretches of road)
            if len(chosen) < args.frames // 2 and all(abs(k - c) >= 40 for c in chosen):
                chosen.append(k)
        for s in (samples[k] for k in sorted(chosen)):
            rgb = read_rgb(s.image)
            tile = draw_detections(rgb, detector(rgb))
            cv2.putText(tile, f"{weather} {Path(s.image).stem}", (4, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                        (255, 255, 255), 1, cv2.LINE_AA)
            tiles.append(tile)
    if not tiles:
        print("No dusk or night frames in the split; generate the dataset first.")
        return 1
    if len(tiles) % 2:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[k:k + 2], axis=1) for k in range(0, len(tiles), 2)]
    sheet = np.concatenate(rows, axis=0)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    print(f"Wrote {args.out} ({len(tiles)} frames)")
    return 0
