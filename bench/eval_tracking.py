"""SORT tracking measured with motmetrics against the simulator's object ids, and the tracker's speed.

    python bench/eval_tracking.py                        # 3 episodes x 300 frames, noisy ground-truth boxes
    python bench/eval_tracking.py --detector data/models/detector.pt   # also with the trained detector, if it exists

Ground truth per frame: the boxes of the cars, trucks and pedestrians visible in the segmentation map
(at least 25 pixels), with their simulator ids. Objects with fewer visible pixels are "ignore" regions, as
in MOT benchmarks: a reported box on one of them (IoU >= 0.5) is neither a hit nor a false positive.
The "detector" is those boxes with noise: each edge moves
by a Gaussian of ``--noise`` x the box's width/height, a box is dropped with probability ``--dropout``,
and ``--false-rate`` spurious boxes per frame appear. Figures: MOTA, IDF1, identity switches (motmetrics,
IoU distance, match if IoU >= 0.5), for SORT on every frame and for detect-every-k with k = 1, 3, 5, 10
(seed 000's frame skipping), plus tracker updates per second.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import motmetrics as mm
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from towndrive.agent.autopilot import Autopilot  # noqa: E402
from towndrive.agent.perception.tracking import SkipTracker, Sort, SortConfig, Track, iou_matrix  # noqa: E402
from towndrive.envs.drive_env import DriveConfig, DriveEnv  # noqa: E402
from towndrive.envs.perception_truth import object_boxes  # noqa: E402


def noisy(boxes: np.ndarray, rng: np.random.Generator, noise: float, dropout: float, false_rate: float,
          size: tuple[int, int]) -> np.ndarray:
    """Ground-truth boxes with jittered edges, dropouts and false positives."""
    keep = rng.random(len(boxes)) >= dropout
    b = boxes[keep].copy()
    if len(b):
        wh = np.stack([b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]], 1)
        b += rng.normal(0.0, noise, b.shape) * np.concatenate([wh, wh], 1)
        b[:, 2:] = np.maximum(b[:, 2:], b[:, :2] + 1.0)
    n_false = rng.poisson(false_rate)
    if n_false:
        w, h = size
        xy = rng.uniform([0, 0], [w - 20, h - 20], (n_false, 2))
        wh = rng.uniform(6, 30, (n_false, 2))
        b = np.concatenate([b, np.concatenate([xy, xy + wh], 1)])
    return b


IGNORED: dict[tuple[int, int], np.ndarray] = {}  # (episode, frame) -> boxes of movers too small to count


def drop_ignored(boxes: np.ndarray, ignore: np.ndarray) -> np.ndarray:
    """Which of ``boxes`` to keep: those not on an ignored (barely visible) object."""
    if len(boxes) == 0 or len(ignore) == 0:
        return np.ones(len(boxes), bool)
    d = iou_distance(boxes, ignore)
    return ~np.any(np.isfinite(d), axis=1)


def record(episodes: int, frames: int, seed: int) -> list[list[tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """Per episode, per frame: (ground-truth boxes, ids, image); small objects go to ``IGNORED``."""
    env = DriveEnv(DriveConfig(observe_segmentation=True, terminate_on_infraction=False,
                               terminate_on_route_deviation=False))
    out = []
    for e in range(episodes):
        driver = Autopilot()
        obs, info = env.reset(seed=seed + e, options={"traffic_density": 3.0})
        driver.reset(env)
        seq = []
        for _ in range(frames):
            obs, _, terminated, truncated, info = env.step(driver.act(obs))
            if terminated or truncated:
                break
            boxes, ids = object_boxes(info)
            small = [o["bbox"] for o in info["objects"] if o["class"] in ("car", "truck", "pedestrian") and o["pixels"] < 25]
            IGNORED[(e, len(seq))] = np.array(small, float).reshape(-1, 4)
            seq.append((boxes, ids, obs["image"]))
        out.append(seq)
    env.close()
    return out


def evaluate(sequences, make_dets, every: int, config: SortConfig, name: str) -> tuple[mm.MOTAccumulator, float, int]:
    """Run detect-every-k SORT over the sequences; one motmetrics accumulator for all of them."""
    acc = mm.MOTAccumulator(auto_id=True)
    tracker_time = 0.0
    updates = 0
    for e, seq in enumerate(sequences):
        state = {"k": 0}

        def detect(image: np.ndarray, seq=seq, state=state, e=e) -> tuple[np.ndarray, None]:
            boxes = make_dets(e, state["k"], seq[state["k"]])
            return boxes, None

        tracker = SkipTracker(detect, every=every, config=config)
        for k, (gt_boxes, gt_ids, image) in enumerate(seq):
            state["k"] = k
            t0 = time.perf_counter()
            tracks: list[Track] = tracker.step(image)
            tracker_time += time.perf_counter() - t0
            updates += 1
            keep = drop_ignored(np.array([t.box for t in tracks]).reshape(-1, 4), IGNORED.get((e, k), np.zeros((0, 4))))
            tracks = [t for t, ok in zip(tracks, keep, strict=True) if ok]
            hyp = np.array([t.box for t in tracks]).reshape(-1, 4)
            dist = iou_distance(gt_boxes, hyp)
            acc.update(list(gt_ids), [t.track_id for t in tracks], dist)
    del name
    return acc, tracker_time, updates


def iou_distance(gt: np.ndarray, hyp: np.ndarray, max_distance: float = 0.5) -> np.ndarray:
    """motmetrics' IoU distance (1 - IoU, NaN when 1 - IoU > ``max_distance``) for x0, y0, x1, y1 boxes.

    ``mm.distances.iou_matrix`` calls ``np.asfarray``, which NumPy 2 removed, so the tracker's own IoU is used.
    """
    a, b = np.asarray(gt, float).reshape(-1, 4), np.asarray(hyp, float).reshape(-1, 4)
    if len(a) == 0 or len(b) == 0:
        return np.empty((len(a), len(b)))
    d = 1.0 - iou_matrix(a, b)
    d[d > max_distance] = np.nan
    return d


def tracker_rate(sequences, config: SortConfig, seconds: float = 3.0) -> float:
    """Sort.update calls per second on recorded noisy detections (detector time excluded)."""
    rng = np.random.default_rng(0)
    dets = [noisy(b, rng, 0.05, 0.1, 0.2, (320, 160)) for seq in sequences for b, _, _ in seq]
    sort = Sort(config)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for d in dets:
            sort.update(d)
            n += 1
        sort.reset()
    return n / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=3)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--noise", type=float, default=0.05, help="edge jitter, share of the box size (std)")
    ap.add_argument("--dropout", type=float, default=0.1, help="probability that a box is missed")
    ap.add_argument("--false-rate", type=float, default=0.2, help="spurious boxes per frame (Poisson mean)")
    ap.add_argument("--picture", type=Path, default=None, help="write frames with SORT's tracks and ids here")
    ap.add_argument("--detector", type=Path, default=None, help="trained detector checkpoint (agent/perception/detector.py)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    t0 = time.perf_counter()
    sequences = record(args.episodes, args.frames, args.seed)
    n_frames = sum(len(s) for s in sequences)
    n_gt = sum(len(ids) for s in sequences for _, ids, _ in s)
    print(f"recorded {len(sequences)} episodes, {n_frames} frames, {n_gt} ground-truth boxes "
          f"({len({(e, i) for e, s in enumerate(sequences) for _, ids, _ in s for i in ids})} objects) "
          f"in {time.perf_counter() - t0:.0f} s")
    config = SortConfig()
    # Noisy detections drawn once per (episode, frame) so every k sees the same detector output.
    rng = np.random.default_rng(args.seed)
    cache = {(e, k): noisy(b, rng, args.noise, args.dropout, args.false_rate, (320, 160))
             for e, s in enumerate(sequences) for k, (b, _, _) in enumerate(s)}
    print(f"noisy ground-truth boxes: edge jitter {args.noise:.0%} of the box size, dropout {args.dropout:.0%}, "
          f"{args.false_rate} false boxes per frame; SORT max_age={config.max_age} min_hits={config.min_hits} "
          f"iou={config.iou_threshold}")
    mh = mm.metrics.create()
    accs, names = [], []
    for every in (1, 3, 5, 10):
        acc, _, _ = evaluate(sequences, lambda e, k, item: cache[(e, k)], every, config, f"k={every}")
        accs.append(acc)
        names.append(f"SORT, detect every {every}")
    # The detector alone, no tracking (ids are per-frame): what tracking adds.
    acc_raw = mm.MOTAccumulator(auto_id=True)
    next_id = 0
    for e, seq in enumerate(sequences):
        for k, (gt_boxes, gt_ids, _) in enumerate(seq):
            d = cache[(e, k)]
            d = d[drop_ignored(d, IGNORED.get((e, k), np.zeros((0, 4))))]
            ids = list(range(next_id, next_id + len(d)))
            next_id += len(d)
            acc_raw.update(list(gt_ids), ids, iou_distance(gt_boxes, d))
    accs.append(acc_raw)
    names.append("noisy boxes, no tracker")
    summary = mh.compute_many(accs, names=names, metrics=["mota", "idf1", "num_switches", "precision", "recall",
                                                          "num_false_positives", "num_misses"])
    print(mm.io.render_summary(summary, formatters=mh.formatters, namemap=mm.io.motchallenge_metric_names))
    if args.picture is not None:
        _picture(sequences[0], [cache[(0, k)] for k in range(len(sequences[0]))], config, args.picture)
    rate = tracker_rate(sequences, config)
    print(f"tracker: {rate:.0f} updates/s (Sort.update on noisy ground-truth boxes, one core)")
    det_path = args.detector
    if det_path is None:
        candidates = sorted(Path("data/models").glob("detector*.pt"))
        det_path = candidates[0] if candidates else None
    if det_path is None or not det_path.exists():
        print("trained detector: not found in data/models (agent/detector*.py has no checkpoint yet); skipped")
        return
    _with_detector(det_path, sequences, config, mh)


def _picture(seq, dets: list[np.ndarray], config: SortConfig, path: Path) -> None:
    """Six frames of one drive: noisy input boxes (thin grey) and SORT's tracks with their ids (coloured)."""
    sort = Sort(config)
    picks = set(np.linspace(20, len(seq) - 1, 6).astype(int).tolist())
    tiles = []
    for k, ((_, _, image), d) in enumerate(zip(seq, dets, strict=True)):
        tracks = sort.update(d)
        if k not in picks:
            continue
        img = cv2.resize(image, (640, 320), interpolation=cv2.INTER_LINEAR)
        for b in d:
            x0, y0, x1, y1 = (int(round(2 * v)) for v in b)
            cv2.rectangle(img, (x0, y0), (x1, y1), (170, 170, 170), 1)
        for t in tracks:
            rng = np.random.default_rng(t.track_id)
            color = tuple(int(c) for c in rng.integers(80, 256, 3))
            x0, y0, x1, y1 = (int(round(2 * v)) for v in t.box)
            cv2.rectangle(img, (x0, y0), (x1, y1), color, 2)
            cv2.putText(img, f"id {t.track_id}", (x0, max(12, y0 - 3)), cv2.FONT_HERSHEY_SIMPLEX, 0.45, color, 1, cv2.LINE_AA)
        cv2.putText(img, f"frame {k}", (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(img)
    rows = [np.concatenate(tiles[i:i + 2], axis=1) for i in range(0, len(tiles) - 1, 2)]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(np.concatenate(rows, axis=0), cv2.COLOR_RGB2BGR))
    print(f"picture: {path}")


def _with_detector(path: Path, sequences, config: SortConfig, mh) -> None:
    """MOTA with the trained detector's car, truck and pedestrian boxes (agent/perception/detector.py's TorchDetector),
    followed by the pedestrian refiner as the agent runs it when the shipped one is there."""
    try:
        from towndrive.agent.perception.detector import TorchDetector
        from towndrive.agent.training.detector_eval import resolve_refiner
        refiner = resolve_refiner("auto", str(path))
        model = TorchDetector(path, refiner=refiner)
    except Exception as exc:  # the detector is someone else's work; say why it could not be used
        print(f"trained detector: cannot load {path} ({exc}); skipped")
        return
    from towndrive.agent.perception.checkpoints import load_checkpoint

    # The checkpoint's own record: a log file beside it may belong to an earlier run of the same name.
    meta = load_checkpoint(path, "detector")
    print(f"trained detector {path}: epoch {meta.get('epoch')}, val mAP@0.5 {meta.get('val_map50', float('nan')):.3f}"
          f"; pedestrian refiner: {refiner or 'none'}")
    movers = {"car", "truck", "pedestrian"}

    def boxes_of(image: np.ndarray) -> np.ndarray:
        return np.array([d.box for d in model(image) if d.name in movers], float).reshape(-1, 4)

    cache = {(e, k): boxes_of(img) for e, s in enumerate(sequences) for k, (_, _, img) in enumerate(s)}
    accs, names = [], []
    for every in (1, 5):
        acc, _, _ = evaluate(sequences, lambda e, k, item: cache[(e, k)], every, config, "")
        accs.append(acc)
        names.append(f"detector + SORT, every {every}")
    summary = mh.compute_many(accs, names=names, metrics=["mota", "idf1", "num_switches", "precision", "recall",
                                                          "num_false_positives", "num_misses"])
    print(mm.io.render_summary(summary, formatters=mh.formatters, namemap=mm.io.motchallenge_metric_names))


if __name__ == "__main__":
    main()
