"""SORT: box algebra, the Kalman filter's constant-velocity prediction, identity keeping through a
dropout and a crossing, track deletion, detect-every-k, and the update rate target."""

from __future__ import annotations

import time

import numpy as np
import pytest

from towndrive.agent.perception.tracking import (
    BoxKalman,
    KalmanNoise,
    SkipTracker,
    Sort,
    SortConfig,
    box_to_z,
    iou_matrix,
    z_to_box,
)


def test_box_conversions_and_iou() -> None:
    box = np.array([10.0, 20.0, 50.0, 40.0])
    z = box_to_z(box)
    assert np.allclose(z, [30, 30, 800, 2.0])
    assert np.allclose(z_to_box(z), box)
    a = np.array([[0, 0, 10, 10], [100, 100, 110, 110]], float)
    b = np.array([[5, 0, 15, 10]], float)
    iou = iou_matrix(a, b)
    assert iou.shape == (2, 1)
    assert iou[0, 0] == pytest.approx(50 / 150)
    assert iou[1, 0] == 0.0
    assert iou_matrix(np.zeros((0, 4)), b).shape == (0, 1)


def test_kalman_learns_constant_velocity() -> None:
    kf = BoxKalman(np.array([0, 0, 20, 10], float), KalmanNoise())
    for k in range(1, 15):
        kf.predict()
        kf.update(np.array([3 * k, 1 * k, 3 * k + 20, 1 * k + 10], float))
    predicted = kf.predict()
    assert np.allclose(predicted, [45, 15, 65, 25], atol=0.5)


def moving_boxes(n_frames: int) -> list[np.ndarray]:
    """Two boxes: one moving right, one moving left, crossing vertically apart (no overlap)."""
    frames = []
    for k in range(n_frames):
        a = [10 + 4 * k, 20, 40 + 4 * k, 40]
        b = [250 - 4 * k, 90, 280 - 4 * k, 120]
        frames.append(np.array([a, b], float))
    return frames


def test_sort_keeps_identities_through_a_dropout() -> None:
    sort = Sort(SortConfig(max_age=3, min_hits=3))
    frames = moving_boxes(30)
    ids_seen: dict[int, set[int]] = {0: set(), 1: set()}
    for k, dets in enumerate(frames):
        if k == 12:
            dets = dets[:1]  # object 1 is missed for one frame
        tracks = sort.update(dets)
        for t in tracks:
            which = 0 if t.box[1] < 60 else 1
            ids_seen[which].add(t.track_id)
        if k == 12:  # the missed object is still reported, at its prediction (coasting)
            assert len(tracks) == 2
    assert len(ids_seen[0]) == 1 and len(ids_seen[1]) == 1
    assert ids_seen[0] != ids_seen[1]


def test_sort_deletes_lost_tracks_and_waits_for_min_hits() -> None:
    sort = Sort(SortConfig(max_age=2, min_hits=3))
    box = np.array([[50, 50, 80, 80]], float)
    for _ in range(5):
        assert len(sort.update(box)) == 1
    for _ in range(3):
        sort.update(np.zeros((0, 4)))
    assert sort._tracks == []
    # After the warm-up frames a new object is only reported from its min_hits-th match on.
    counts = [len(sort.update(box)) for _ in range(4)]
    assert counts == [0, 0, 1, 1]


def test_a_track_keeps_the_class_most_of_its_detections_had() -> None:
    """A pedestrian (class 2) tracked for 10 frames and then called a truck (1) for 3 stays a pedestrian; a truck
    seen as a truck for longer than it was a pedestrian becomes one; a new track takes its first label."""
    sort = Sort(SortConfig(max_age=3, min_hits=1))
    box = np.array([[100, 50, 110, 80]], float)
    labels = [2] * 10 + [1] * 3
    for lab in labels:
        (track,) = sort.update(box, np.array([lab]))
    assert track.label == 2
    for _ in range(8):
        (track,) = sort.update(box, np.array([1]))
    assert track.label == 1  # 11 truck votes against 10
    other = Sort(SortConfig(min_hits=1))
    (first,) = other.update(box, np.array([0]))
    assert first.label == 0


def test_skip_tracker_runs_the_detector_every_k_frames() -> None:
    frames = moving_boxes(20)
    calls = []

    def detect(k: int) -> tuple[np.ndarray, None]:
        calls.append(k)
        return frames[k], None

    tracker = SkipTracker(detect, every=5, config=SortConfig(min_hits=1))
    outputs = [tracker.step(k) for k in range(20)]  # the "frame" here is its index
    assert calls == [0, 5, 10, 15]
    # Between detections the tracks are predicted forward: by frame 14 the first box has moved on.
    assert len(outputs[14]) == 2
    first = min(outputs[14], key=lambda t: t.box[1])
    assert first.box[0] == pytest.approx(frames[14][0][0], abs=3.0)
    with pytest.raises(ValueError):
        SkipTracker(detect, every=0)


def test_update_rate_target() -> None:
    rng = np.random.default_rng(0)
    sort = Sort()
    base = rng.uniform(0, 250, (6, 2))
    start = time.perf_counter()
    n = 0
    while n < 600:
        k = n % 60
        boxes = np.concatenate([base + 2 * k, base + 2 * k + 25], 1) + rng.normal(0, 1, (6, 4))
        sort.update(boxes)
        n += 1
    rate = n / (time.perf_counter() - start)
    assert rate >= 500, f"{rate:.0f} updates/s"
