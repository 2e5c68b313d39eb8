"""SORT multi-object tracking, written here from the paper's description (Bewley et al. 2016; the
reference code is GPL, so none of it is used), and seed 000's "detect every k frames, track in between".

Each track is a constant-velocity Kalman filter on the box's centre (u, v), area s and aspect ratio r
(r has no velocity: boxes do not keep stretching). Each frame: predict every track, match detections to
predictions by IoU with the Hungarian method (``scipy.optimize.linear_sum_assignment``), drop matches
below ``iou_threshold``, update matched tracks, start tracks from unmatched detections, and delete tracks
not matched for more than ``max_age`` frames. A track is reported once it has ``min_hits`` matches in a
row (or in the first ``min_hits`` frames of a sequence); this is what keeps SORT's false positives low.
Two changes from the paper. A track that has not yet learnt its velocity (``young_hits`` matches or
fewer) may also be matched, in a second Hungarian stage, by centre distance (within ``centre_gate`` box
sizes) when IoU fails: with the detector running every k frames an object moves more than its own width
between detections, before the filter knows it moves at all. And a confirmed track stays confirmed,
and for up to ``coast_frames`` frames without a match it is reported at its predicted box (the paper
reports matched tracks only, so one dropped detection costs three frames of a known object: the miss
and two frames of re-confirmation).

``SkipTracker`` runs an expensive detector only every ``k``-th frame and reports the Kalman predictions
on the frames in between, the trade seed 000 measured on a Jetson.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment


# --------------------------------------------------------------------------- box helpers
def box_to_z(box: np.ndarray) -> np.ndarray:
    """[x0, y0, x1, y1] -> measurement [u, v, s, r] (centre, area, aspect w / h)."""
    w, h = box[2] - box[0], box[3] - box[1]
    return np.array([box[0] + w / 2, box[1] + h / 2, w * h, w / max(h, 1e-6)])


def z_to_box(z: np.ndarray) -> np.ndarray:
    """[u, v, s, r, ...] -> [x0, y0, x1, y1]."""
    s, r = max(float(z[2]), 1e-6), max(float(z[3]), 1e-6)
    w = np.sqrt(s * r)
    h = s / w
    return np.array([z[0] - w / 2, z[1] - h / 2, z[0] + w / 2, z[1] + h / 2])


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of every box in ``a`` (N x 4) with every box in ``b`` (M x 4)."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)))
    x0 = np.maximum(a[:, None, 0], b[None, :, 0])
    y0 = np.maximum(a[:, None, 1], b[None, :, 1])
    x1 = np.minimum(a[:, None, 2], b[None, :, 2])
    y1 = np.minimum(a[:, None, 3], b[None, :, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    return inter / np.maximum(area_a[:, None] + area_b[None, :] - inter, 1e-9)


# --------------------------------------------------------------------------- Kalman filter
@dataclass(frozen=True)
class KalmanNoise:
    """Standard deviations (pixels, pixels^2, unitless) of the box filter's noises."""

    measure_pos_px: float = 1.0
    measure_area_frac: float = 0.1  # of the box's area
    measure_aspect: float = 0.1
    process_pos_px: float = 1.0
    process_area_frac: float = 0.05
    process_aspect: float = 0.01
    initial_velocity_px: float = 10.0  # prior on the unknown initial velocity, per frame


class BoxKalman:
    """Constant-velocity Kalman filter on x = [u, v, s, r, du, dv, ds]."""

    F = np.eye(7)
    F[0, 4] = F[1, 5] = F[2, 6] = 1.0
    H = np.eye(4, 7)

    def __init__(self, box: np.ndarray, noise: KalmanNoise) -> None:
        z = box_to_z(box)
        self.noise = noise
        self.x = np.r_[z, 0.0, 0.0, 0.0]
        v0 = noise.initial_velocity_px
        self.P = np.diag([4.0, 4.0, (0.2 * z[2]) ** 2, 0.04, v0 ** 2, v0 ** 2, (0.2 * z[2]) ** 2])

    def _q(self) -> np.ndarray:
        n = self.noise
        s = max(self.x[2], 1.0)
        q_pos, q_area, q_r = n.process_pos_px ** 2, (n.process_area_frac * s) ** 2, n.process_aspect ** 2
        return np.diag([q_pos, q_pos, q_area, q_r, q_pos, q_pos, q_area])

    def _r(self) -> np.ndarray:
        n = self.noise
        s = max(self.x[2], 1.0)
        return np.diag([n.measure_pos_px ** 2, n.measure_pos_px ** 2, (n.measure_area_frac * s) ** 2, n.measure_aspect ** 2])

    def predict(self) -> np.ndarray:
        if self.x[2] + self.x[6] <= 1.0:  # the area would go negative: stop shrinking
            self.x[6] = 0.0
        self.x = self.F @ self.x
        self.P = self.F @ self.P @ self.F.T + self._q()
        return z_to_box(self.x)

    def update(self, box: np.ndarray) -> None:
        y = box_to_z(box) - self.H @ self.x
        s = self.H @ self.P @ self.H.T + self._r()
        k = self.P @ self.H.T @ np.linalg.inv(s)
        self.x = self.x + k @ y
        self.P = (np.eye(7) - k @ self.H) @ self.P

    @property
    def box(self) -> np.ndarray:
        return z_to_box(self.x)


@dataclass
class Track:
    """One tracked object as reported to the caller."""

    track_id: int
    box: np.ndarray  # [x0, y0, x1, y1]
    hits: int
    age: int  # frames since the track started
    time_since_update: int
    label: int = -1  # the class most of its matched detections had, ties to the latest (-1: unknown)


class _State:
    def __init__(self, track_id: int, box: np.ndarray, noise: KalmanNoise, label: int) -> None:
        self.track_id = track_id
        self.kf = BoxKalman(box, noise)
        self.hits = 1
        self.hit_streak = 1
        self.confirmed = False
        self.age = 0
        self.time_since_update = 0
        self.label = label
        self.votes: dict[int, int] = {label: 1}

    def vote(self, label: int) -> None:
        """Count one more detection of ``label``. The track's class is the one seen most often (ties: the
        latest), so a detector that calls a person beside a truck "truck" for a few frames does not turn a
        pedestrian tracked for seconds into a vehicle, to which a driver's pedestrian rules no longer apply."""
        self.votes[label] = self.votes.get(label, 0) + 1
        if self.votes[label] >= self.votes.get(self.label, 0):
            self.label = label


# --------------------------------------------------------------------------- SORT
@dataclass(frozen=True)
class SortConfig:
    max_age: int = 3  # frames a track survives without a match
    min_hits: int = 3  # matches in a row before a track is reported
    iou_threshold: float = 0.3
    coast_frames: int = 2  # a confirmed track is still reported (predicted) this many frames after its last match
    young_hits: int = 2  # tracks with this many matches or fewer may be matched by centre distance
    centre_gate: float = 1.0  # ... within this many box sizes (sqrt of the area)
    noise: KalmanNoise = KalmanNoise()


class Sort:
    """Simple Online and Realtime Tracking."""

    def __init__(self, config: SortConfig | None = None) -> None:
        self.config = config or SortConfig()
        self.reset()

    def reset(self) -> None:
        self._tracks: list[_State] = []
        self._next_id = 1
        self.frame_count = 0

    def _predict_all(self) -> np.ndarray:
        boxes = np.zeros((len(self._tracks), 4))
        for k, t in enumerate(self._tracks):
            boxes[k] = t.kf.predict()
            t.age += 1
        return boxes

    def update(self, detections: np.ndarray, labels: np.ndarray | None = None) -> list[Track]:
        """Feed one frame's detections (N x 4 boxes, optionally N labels); returns the tracks to report."""
        cfg = self.config
        self.frame_count += 1
        dets = np.asarray(detections, float).reshape(-1, 4)
        labs = np.full(len(dets), -1) if labels is None else np.asarray(labels).reshape(-1)
        predicted = self._predict_all()
        # Drop tracks whose prediction became invalid (NaN).
        ok = np.all(np.isfinite(predicted), axis=1)
        if not ok.all():
            self._tracks = [t for t, g in zip(self._tracks, ok, strict=True) if g]
            predicted = predicted[ok]
        matches, unmatched_dets = self._associate(dets, predicted)
        matched_tracks = set()
        for d, t in matches:
            tr = self._tracks[t]
            tr.kf.update(dets[d])
            tr.time_since_update = 0
            tr.hits += 1
            tr.hit_streak += 1
            tr.vote(int(labs[d]))
            matched_tracks.add(t)
        for t, tr in enumerate(self._tracks):
            if t not in matched_tracks:
                tr.time_since_update += 1
                tr.hit_streak = 0
        for d in unmatched_dets:
            self._tracks.append(_State(self._next_id, dets[d], cfg.noise, int(labs[d])))
            self._next_id += 1
        self._tracks = [t for t in self._tracks if t.time_since_update <= cfg.max_age]
        out = []
        for t in self._tracks:
            if t.time_since_update == 0 and (t.hit_streak >= cfg.min_hits or self.frame_count <= cfg.min_hits):
                t.confirmed = True
            warm_up = t.time_since_update == 0 and self.frame_count <= cfg.min_hits
            if (t.confirmed and t.time_since_update <= cfg.coast_frames) or warm_up:
                out.append(self._report(t))
        return out

    def predict(self) -> list[Track]:
        """Advance every track one frame without detections and report the confirmed ones' predictions
        (the in-between frames of ``SkipTracker``; a skipped frame is not a missed detection)."""
        self.frame_count += 1
        self._predict_all()
        return [self._report(t) for t in self._tracks if t.confirmed and t.time_since_update <= self.config.coast_frames]

    def _associate(self, dets: np.ndarray, predicted: np.ndarray) -> tuple[list[tuple[int, int]], list[int]]:
        if len(predicted) == 0 or len(dets) == 0:
            return [], list(range(len(dets)))
        cfg = self.config
        iou = iou_matrix(dets, predicted)
        rows, cols = linear_sum_assignment(-iou)
        matches = [(int(r), int(c)) for r, c in zip(rows, cols, strict=True) if iou[r, c] >= cfg.iou_threshold]
        free_d = [d for d in range(len(dets)) if d not in {r for r, _ in matches}]
        used_t = {c for _, c in matches}
        young = [t for t in range(len(predicted)) if t not in used_t and self._tracks[t].hits <= cfg.young_hits]
        if free_d and young:
            dz = np.array([box_to_z(dets[d]) for d in free_d])
            tz = np.array([box_to_z(predicted[t]) for t in young])
            size = np.sqrt(np.maximum(tz[None, :, 2], 1.0))
            dist = np.hypot(dz[:, None, 0] - tz[None, :, 0], dz[:, None, 1] - tz[None, :, 1]) / size
            ratio = dz[:, None, 2] / np.maximum(tz[None, :, 2], 1e-6)
            cost = np.where((ratio > 0.5) & (ratio < 2.0), dist, 1e6)
            r2, c2 = linear_sum_assignment(cost)
            for r, c in zip(r2, c2, strict=True):
                if cost[r, c] <= cfg.centre_gate:
                    matches.append((free_d[r], young[c]))
            matched = {r for r, _ in matches}
            free_d = [d for d in range(len(dets)) if d not in matched]
        return matches, free_d

    @staticmethod
    def _report(t: _State) -> Track:
        return Track(t.track_id, t.kf.box, t.hits, t.age, t.time_since_update, t.label)


class SkipTracker:
    """Run ``detect(frame)`` every ``every`` frames and SORT on its boxes; in between, report SORT's predictions."""

    def __init__(self, detect: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray | None]], every: int = 5,
                 config: SortConfig | None = None) -> None:
        if every < 1:
            raise ValueError("every must be at least 1 (1 = detect on every frame).")
        self.detect = detect
        self.every = every
        self.sort = Sort(config)
        self._frame = 0

    def reset(self) -> None:
        self.sort.reset()
        self._frame = 0

    def step(self, frame: np.ndarray) -> list[Track]:
        """Tracks for this frame; the detector runs only on frames 0, k, 2k, ..."""
        run = self._frame % self.every == 0
        self._frame += 1
        if run:
            boxes, labels = self.detect(frame)
            return self.sort.update(boxes, labels)
        return self.sort.predict()
