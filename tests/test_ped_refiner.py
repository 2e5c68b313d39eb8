"""The pedestrian refiner: crop geometry, how it re-places and re-scores boxes, its training samples, ONNX
parity and the shipped model on a rendered pedestrian."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from towndrive.agent.deploy.onnx_export import export_refiner
from towndrive.agent.perception.detector import Detection, OnnxDetector, TorchDetector, box_iou
from towndrive.agent.perception.ped_refiner import (
    CROP_HW,
    PEDESTRIAN,
    PedRefiner,
    Refine,
    RefinerConfig,
    crop_windows,
    from_window,
    load_refiner,
    onnx_refine,
    to_window,
    torch_refine,
    windows,
)
from towndrive.agent.training.autolabel import CLASSES, render_and_label
from towndrive.agent.training.detector_eval import Sample
from towndrive.agent.training.ped_refiner_training import build_samples, refiner_loss

MODELS = Path(__file__).resolve().parents[1] / "data" / "models"
CAR = CLASSES.index("car")


@pytest.fixture(autouse=True)
def one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_crop_shows_the_box_where_window_units_say():
    rgb = np.zeros((160, 320, 3), np.uint8)
    rgb[60:72, 100:104] = 255  # a 4 x 12 px "pedestrian", pixel-exact edges
    box = np.array([[100.0, 60.0, 104.0, 72.0]], np.float32)
    win = windows(box, RefinerConfig())
    assert win[0, 3] == 24.0 and win[0, 2] == 12.0  # twice the box, 2:1 tall
    crop = crop_windows(rgb, win)[0]
    inner = to_window(box, win)[0] * [CROP_HW[1], CROP_HW[0], CROP_HW[1], CROP_HW[0]]
    x0, y0, x1, y1 = (int(round(v)) for v in inner)
    assert (x0, y0, x1, y1) == (5, 8, 11, 24)  # 4 px of a 12 px wide window on 16 crop columns
    assert crop[y0 + 1:y1 - 1, x0 + 1:x1 - 1].min() == 255  # inside: white
    assert crop[:y0 - 1].max() == 0 and crop[:, :x0 - 1].max() == 0 and crop[:, x1 + 1:].max() == 0  # outside
    np.testing.assert_allclose(from_window(to_window(box, win), win), box, atol=1e-4)


def _fixed(edges: tuple[float, float, float, float], logit: float):
    return lambda x: np.tile(np.array([[*edges, logit]], np.float32), (len(x), 1))


def test_refine_moves_rescored_pedestrians_snaps_them_and_leaves_other_classes():
    cfg = RefinerConfig(score_weight=0.5, snap_to_pixels=True)
    rgb = np.zeros((160, 320, 3), np.uint8)
    dets = [Detection((10.2, 20.3, 30.0, 60.0), CAR, 0.9),
            Detection((100.3, 50.2, 103.6, 62.4), PEDESTRIAN, 0.64),
            Detection((200.0, 50.0, 203.0, 60.0), PEDESTRIAN, 0.005)]  # below candidate_score: dropped
    out = Refine(_fixed((0.0, 0.0, 0.0, 0.0), 0.0), cfg)(rgb, dets, 0.01)
    assert [d.cls for d in out] == [CAR, PEDESTRIAN]
    assert out[0] == dets[0]
    assert out[1].box == (100.0, 50.0, 104.0, 62.0)  # snapped to the pixel grid
    assert out[1].score == pytest.approx((0.64 * 0.5) ** 0.5)
    # An edge change of a quarter window moves the box by a quarter of the window's width.
    win = windows(np.array([dets[1].box], np.float32), cfg)[0]
    moved = Refine(_fixed((0.25, 0.0, 0.25, 0.0), 5.0), RefinerConfig(snap_to_pixels=False))(rgb, dets[1:2], 0.01)
    assert moved[0].box[0] == pytest.approx(100.3 + 0.25 * win[2], abs=1e-4)
    # Below the threshold after re-scoring: gone; the lowest candidate score follows the blend.
    assert not Refine(_fixed((0.0, 0.0, 0.0, 0.0), -8.0), cfg)(rgb, dets[1:2], 0.3)
    assert cfg.lowest_candidate(0.3) == pytest.approx(0.09)


def test_candidate_depth_reaches_low_scored_pedestrians_only_when_every_detection_is_asked_for():
    faint = [Detection((100.0, 50.0, 103.0, 60.0), PEDESTRIAN, 5e-4)]  # a person at night the detector barely saw
    rgb = np.zeros((160, 320, 3), np.uint8)
    sure = _fixed((0.0, 0.0, 0.0, 0.0), 6.0)
    deep, shallow = RefinerConfig(score_weight=0.6, candidate_score=1e-4), RefinerConfig(score_weight=0.6)
    assert not Refine(sure, shallow)(rgb, faint, 0.01)  # below the default depth (0.01): never looked at
    lifted = Refine(sure, deep)(rgb, faint, 0.01)
    assert len(lifted) == 1 and lifted[0].score == pytest.approx(5e-4 ** 0.4 * (1 / (1 + np.exp(-6.0))) ** 0.6)
    # At the driver's threshold the blend alone sets the depth: a candidate needs 0.3^2.5 = 0.049 either way.
    assert deep.lowest_candidate(0.3) == shallow.lowest_candidate(0.3) == pytest.approx(0.3 ** 2.5)
    assert not Refine(sure, deep)(rgb, faint, 0.3)


def test_refined_boxes_that_meet_are_merged():
    two = [Detection((100.0, 50.0, 104.0, 62.0), PEDESTRIAN, 0.8), Detection((102.6, 50.0, 106.6, 62.0), PEDESTRIAN, 0.7)]
    out = Refine(_fixed((0.0, 0.0, 0.0, 0.0), 2.0), RefinerConfig())(np.zeros((160, 320, 3), np.uint8), two, 0.01)
    assert len(out) == 2  # 3 px apart: IoU 1/7
    # The second one moved 2.6 px left (0.22 of its 12 px wide window) lands on the first: one is kept.
    pull = Refine(lambda x: np.array([[0, 0, 0, 0, 2.0], [-0.22, 0, -0.22, 0, 2.0]], np.float32), RefinerConfig())
    merged = pull(np.zeros((160, 320, 3), np.uint8), two, 0.01)
    assert len(merged) == 1 and merged[0].box == (100.0, 50.0, 104.0, 62.0)


def test_training_samples_label_candidates_and_drop_those_on_ignore_regions(tmp_path):
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (160, 320, 3), dtype=np.uint8)
    sample = Sample("x.png", "noon", np.array([[100, 50, 104, 62], [200, 40, 203, 48]], np.float32),
                    np.array([PEDESTRIAN, PEDESTRIAN]), np.array([False, True]), np.array([20.0, 45.0]))
    dets = [Detection((101.0, 50.0, 105.0, 62.0), PEDESTRIAN, 0.9),  # on the labelled one
            Detection((200.0, 40.0, 203.0, 48.0), PEDESTRIAN, 0.5),  # on the ignore region: dropped
            Detection((20.0, 40.0, 23.0, 48.0), PEDESTRIAN, 0.4),  # on nothing: a negative
            Detection((50.0, 40.0, 60.0, 48.0), CAR, 0.9)]  # not a pedestrian: not a candidate
    data = build_samples([sample], [rgb], [dets], RefinerConfig(), jitter=1, rng=rng)
    assert data["label"].tolist() == [1.0, 0.0, 1.0]  # the jittered copy of the labelled one comes last
    assert data["crops"].shape == (3, *CROP_HW, 3)
    np.testing.assert_allclose(from_window(data["target"][:1], windows(np.array([dets[0].box], np.float32),
                                                                         RefinerConfig())), [[100, 50, 104, 62]],
                               atol=1e-4)
    # The loss: zero for a perfect edge change with a confident logit; box loss only from positives.
    out = torch.zeros(3, 5)
    out[:, :4] = torch.from_numpy(data["target"] - data["cand"])
    out[:, 4] = torch.tensor([20.0, -20.0, 20.0])
    cls, box = refiner_loss(out, data["cand"], data["target"], data["label"])
    assert cls.item() < 1e-6 and box.item() < 1e-6


def test_export_matches_torch_and_carries_its_config(tmp_path):
    torch.manual_seed(0)
    model = PedRefiner(RefinerConfig(score_weight=0.4)).eval()
    ckpt = tmp_path / "r.pt"
    torch.save({"kind": "ped_refiner", "config": {"score_weight": 0.4}, "state_dict": model.state_dict()}, ckpt)
    diff = export_refiner(ckpt, tmp_path / "r.onnx")
    assert diff < 1e-4
    rgb = np.random.default_rng(1).integers(0, 255, (160, 320, 3), dtype=np.uint8)
    dets = [Detection((100.3, 50.2, 103.6, 62.4), PEDESTRIAN, 0.6), Detection((10.0, 60.0, 16.0, 80.0), PEDESTRIAN, 0.3)]
    a, b = torch_refine(ckpt)(rgb, dets, 0.0), onnx_refine(tmp_path / "r.onnx", threads=1)(rgb, dets, 0.0)
    assert onnx_refine(tmp_path / "r.onnx").config.score_weight == 0.4
    assert len(a) == len(b) == 2
    for x, y in zip(a, b, strict=True):
        assert x.box == y.box and x.score == pytest.approx(y.score, abs=1e-5)
    torch.save({"state_dict": {}}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="bad.pt"):
        load_refiner(tmp_path / "bad.pt")


@pytest.mark.skipif(not (MODELS / "ped_refiner.onnx").is_file(), reason="no shipped refiner")
@pytest.mark.parametrize("backend", ["torch", "onnx"])
def test_shipped_detector_and_refiner_box_a_pedestrian_at_the_kerb(town, backend):
    from towndrive.sim.pedestrians import PedestrianCrowd
    from towndrive.sim.render import CameraConfig, SceneRenderer
    from towndrive.sim.world import World, WorldConfig

    world = World(town, WorldConfig(npc_count=0, pedestrian_count=0), seed=5, spawn_traffic=False)
    (start, end, _), _, _ = world.ego_lane
    lane = town.lane((start, end, 0))  # the kerb is 1.5 lane widths right of lane 0's centre (envs/scenarios.py)
    s = lane.local_coordinates(world.ego.position)[0] + 24.0
    world.crowd = PedestrianCrowd(town, 1, np.random.default_rng(0), 1000)
    ped = world.crowd.peds[0]
    ped.position, ped.heading = lane.position(s, 1.5 * town.lane_width + 0.4).copy(), 0.0
    renderer = SceneRenderer(town, seed=town.seed)
    try:
        frame, labels = render_and_label(renderer, world, CameraConfig(), "dusk")
    finally:
        renderer.close()
    person = next(lab for lab in labels if lab.name == "pedestrian")
    det = (TorchDetector(MODELS / "detector.pt", refiner=MODELS / "ped_refiner.pt") if backend == "torch"
           else OnnxDetector(MODELS / "detector.onnx", refiner=MODELS / "ped_refiner.onnx"))
    peds = [d for d in det(frame.rgb) if d.cls == PEDESTRIAN]
    assert peds, f"missed a pedestrian {person.distance_m:.0f} m ahead at the kerb"
    assert max(box_iou(np.array([d.box for d in peds]), np.array([person.box], np.float32))[:, 0]) >= 0.5
    # The refiner is sure of a person standing in the open: it raises the detector's score.
    alone = [d for d in OnnxDetector(MODELS / "detector.onnx", score_threshold=0.01)(frame.rgb) if d.cls == PEDESTRIAN]
    assert max(d.score for d in peds) > max(d.score for d in alone)


@pytest.mark.skipif(not (MODELS / "ped_refiner.onnx").is_file(), reason="no shipped refiner")
def test_deployment_profiles_run_the_refiner_unless_it_is_disabled():
    from towndrive.agent.deploy.backends import open_detector
    from towndrive.agent.deploy.profiles import load_profile, profile_from_dict

    assert open_detector(load_profile("cpu")).refine is not None
    off = profile_from_dict({"modules": {"refiner": {"enabled": False}}})
    assert open_detector(off).refine is None
