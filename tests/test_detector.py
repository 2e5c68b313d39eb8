"""The detector: NMS, targets, loss, AP, ONNX parity, overlays, the HSV baseline and the shipped model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from towndrive.agent.overlays import CLASS_COLORS, draw_detections
from towndrive.agent.perception.detector import (
    DecodedDetector,
    Detection,
    Detector,
    DetectorConfig,
    OnnxDetector,
    TorchDetector,
    box_iou,
    nms_numpy,
    postprocess,
)
from towndrive.agent.perception.light_state import hsv_state
from towndrive.agent.training.autolabel import CLASSES, render_and_label
from towndrive.agent.training.detector_eval import Sample, class_ap
from towndrive.agent.training.detector_train_loop import build_targets, yolo_loss
from towndrive.sim.objects import SemanticClass
from towndrive.sim.render import CameraConfig, SceneRenderer
from towndrive.sim.world import World, WorldConfig

MODELS = Path(__file__).resolve().parents[1] / "data" / "models"


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Small tensors on a shared 2-core machine: one thread is several times faster than two fighting."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def cells(entries: list[tuple[tuple[float, float, float, float], int, float]]) -> np.ndarray:
    """Decoded-cell rows (x0, y0, x1, y1, objectness, class probabilities) for postprocess."""
    out = np.zeros((len(entries), 5 + len(CLASSES)), np.float32)
    for k, (box, cls, score) in enumerate(entries):
        out[k, :4], out[k, 4], out[k, 5 + cls] = box, score, 1.0
    return out


def test_nms_groups_light_states_but_keeps_a_person_beside_a_car():
    car, ped, red, green = (CLASSES.index(n) for n in ("car", "pedestrian", "light_red", "light_green"))
    pred = cells([((100, 60, 160, 100), car, 0.9), ((102, 61, 161, 101), car, 0.8),  # duplicate car
                  ((110, 50, 130, 100), ped, 0.7),  # person overlapping the car: another group, kept
                  ((200, 20, 206, 40), red, 0.8), ((200, 21, 206, 41), green, 0.6),  # one light, two states
                  ((10, 10, 20, 20), car, 0.1)])  # below the threshold
    dets = postprocess(pred, score_threshold=0.3, iou_threshold=0.5)
    assert sorted((d.name, round(d.score, 2)) for d in dets) == [("car", 0.9), ("light_red", 0.8), ("pedestrian", 0.7)]


def test_opencv_nms_agrees_with_numpy_reference():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 250, (60, 2))
    boxes = np.concatenate([xy, xy + rng.uniform(10, 60, (60, 2))], 1).astype(np.float32)
    scores = rng.uniform(0.31, 1.0, 60).astype(np.float32)
    pred = cells([(tuple(b), 0, float(s)) for b, s in zip(boxes, scores, strict=True)])
    got = sorted(round(d.score, 5) for d in postprocess(pred, 0.3, 0.45))
    ref = sorted(round(float(scores[k]), 5) for k in nms_numpy(boxes, scores, 0.45))
    assert got == ref


def test_targets_put_a_small_object_on_the_stride_8_map_at_its_centre_cell():
    boxes = np.array([[100.0, 60.0, 110.0, 90.0], [0.0, 0.0, 100.0, 100.0]], np.float32)
    tg = build_targets(boxes, np.array([2, 0]), np.array([False, True]))
    # Centre (105, 75) -> stride-8 cell (13, 9); neighbours toward the centre: (12, 9)? 105/8 = 13.1 -> left.
    pos = {(int(p % 40), int(p // 40)) for p in tg[0]["pos"]}
    assert pos == {(13, 9), (12, 9), (13, 8)}
    assert set(tg[0]["cls"].tolist()) == {2} and len(tg[1]["pos"]) == 0  # 30 px: not on the stride-16 map
    w = tg[0]["weight"].reshape(20, 40)
    assert w[5, 5] == 0.0 and w[15, 30] == 1.0  # inside the ignore region: no objectness loss


@pytest.mark.parametrize("classes", [len(CLASSES), 6], ids=["all classes", "six without the signs"])
def test_loss_decreases_on_a_tiny_batch(classes):
    """The loss trains a model of all classes and one of the six without the road signs (``--classes 6``)."""
    torch.manual_seed(0)
    img = torch.full((2, 3, 160, 320), 0.3)
    img[0, :, 60:90, 100:160] = torch.tensor([0.9, 0.1, 0.1])[:, None, None]
    img[1, :, 40:100, 200:220] = torch.tensor([0.1, 0.2, 0.9])[:, None, None]
    targets = [build_targets(np.array([[100, 60, 160, 90]], np.float32), np.array([0]), np.array([False])),
               build_targets(np.array([[200, 40, 220, 100]], np.float32), np.array([2]), np.array([False]))]
    model = Detector(DetectorConfig(width=8, num_classes=classes))  # narrow: the loss is under test, not capacity
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    losses = []
    for _ in range(20):
        loss, _ = yolo_loss(model(img), targets)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.6 * losses[0] and losses[-1] < min(losses[:3])


def test_ap_counts_ignore_regions_neither_way():
    s = Sample("x.png", "noon", np.array([[10, 10, 50, 40], [100, 10, 140, 40], [200, 10, 240, 40]], np.float32),
               np.array([0, 0, 0]), np.array([False, False, True]), np.array([10.0, 50.0, 20.0], np.float32))
    perfect = [Detection((10, 10, 50, 40), 0, 0.9), Detection((100, 10, 140, 40), 0, 0.8),
               Detection((200, 10, 240, 40), 0, 0.95)]  # the last one sits on the ignore region
    assert class_ap([s], [perfect], 0)["ap50"] == pytest.approx(1.0)
    with_fp = [*perfect, Detection((260, 100, 300, 140), 0, 0.99)]  # a false positive ranked first
    assert class_ap([s], [with_fp], 0)["ap50"] < 0.9
    near = class_ap([s], [perfect], 0, max_distance_m=40.0)  # the 50 m car becomes an ignore region
    assert near["gt"] == 1 and near["ap50"] == pytest.approx(1.0)


def test_onnx_export_matches_torch_and_runs_in_onnx_runtime(tmp_path):
    from towndrive.agent.deploy.onnx_export import export_detector
    from towndrive.agent.training.detector_train_loop import save_checkpoint

    torch.manual_seed(1)
    save_checkpoint(tmp_path / "d.pt", Detector(), {})
    diff = export_detector(tmp_path / "d.pt", tmp_path / "d.onnx")
    assert diff < 1e-4
    frame = np.random.default_rng(0).integers(0, 255, (160, 320, 3), dtype=np.uint8)
    a = TorchDetector(tmp_path / "d.pt").raw(frame)
    b = OnnxDetector(tmp_path / "d.onnx", threads=1).raw(frame)
    assert a.shape == b.shape == (20 * 40 + 10 * 20, 5 + len(CLASSES))
    assert np.max(np.abs(a - b)) < 1e-3


def test_stride_4_head_targets_export_and_checkpoints_without_strides(tmp_path):
    from towndrive.agent.deploy.onnx_export import export_detector
    from towndrive.agent.perception.detector import load_detector
    from towndrive.agent.training.detector_train_loop import save_checkpoint

    strides = (4, 8, 16)
    boxes = np.array([[100.0, 60.0, 103.0, 72.0], [40.0, 40.0, 60.0, 80.0], [150, 20, 250, 120]], np.float32)
    tg = build_targets(boxes, np.array([2, 2, 0]), np.array([False, False, False]), strides)
    # 3x12 px pedestrian: only the stride-4 map (centre (101.5, 66) -> cell (25, 16)); 20x40 (longer side
    # 40, over 32): strides 8 and 16; 100x100 car: stride 16 only.
    assert {(int(p % 80), int(p // 80)) for p in tg[0]["pos"]} >= {(25, 16)}
    assert set(tg[0]["cls"].tolist()) == {2} and len(tg[0]["pos"]) == 3 and len(tg[1]["pos"]) == 3
    assert set(tg[1]["cls"].tolist()) == {2} and set(tg[2]["cls"].tolist()) == {0, 2}
    torch.manual_seed(1)
    model = Detector(DetectorConfig(strides=strides))
    assert [m.shape[2] for m in model(torch.zeros(1, 3, 160, 320))] == [40, 20, 10]
    save_checkpoint(tmp_path / "s4.pt", model, {})
    assert load_detector(tmp_path / "s4.pt").config.strides == strides
    assert export_detector(tmp_path / "s4.pt", tmp_path / "s4.onnx") < 1e-4
    frame = np.random.default_rng(0).integers(0, 255, (160, 320, 3), dtype=np.uint8)
    assert OnnxDetector(tmp_path / "s4.onnx", threads=1).raw(frame).shape == (40 * 80 + 20 * 40 + 10 * 20,
                                                                              5 + len(CLASSES))
    # A checkpoint written before strides were configurable (no "strides" key) is the (8, 16) model.
    old = torch.load(tmp_path / "s4.pt", weights_only=False)
    old["config"].pop("strides")
    old["state_dict"] = Detector(DetectorConfig()).state_dict()
    torch.save(old, tmp_path / "old.pt")
    assert load_detector(tmp_path / "old.pt").config.strides == (8, 16)
    # A detector trained before the road signs were appended (six classes) still loads, with six class channels.
    six = torch.load(tmp_path / "old.pt", weights_only=False)
    six["classes"], six["config"]["num_classes"] = CLASSES[:6], 6
    six["state_dict"] = Detector(DetectorConfig(num_classes=6)).state_dict()
    torch.save(six, tmp_path / "six.pt")
    assert load_detector(tmp_path / "six.pt").config.num_classes == 6


def test_stride_4_refinement_blocks_start_as_the_identity_and_export(tmp_path):
    from towndrive.agent.deploy.onnx_export import export_detector
    from towndrive.agent.perception.detector import load_detector
    from towndrive.agent.training.detector_train_loop import save_checkpoint

    torch.manual_seed(2)
    plain = Detector(DetectorConfig(strides=(4, 8, 16))).eval()
    deeper = Detector(DetectorConfig(strides=(4, 8, 16), s4_blocks=2)).eval()
    own = deeper.state_dict()
    missing, _ = deeper.load_state_dict({k: v for k, v in plain.state_dict().items() if k in own}, strict=False)
    assert missing and all(k.startswith("refine4.") for k in missing)  # what --init leaves to the new blocks
    x = torch.rand(1, 3, 160, 320)
    with torch.no_grad():
        assert all(torch.equal(a, b) for a, b in zip(plain(x), deeper(x), strict=True))
    save_checkpoint(tmp_path / "b2.pt", deeper, {})
    assert load_detector(tmp_path / "b2.pt").config.s4_blocks == 2
    assert export_detector(tmp_path / "b2.pt", tmp_path / "b2.onnx") < 1e-4
    with pytest.raises(ValueError, match="s4_blocks"):
        DetectorConfig(strides=(8, 16), s4_blocks=1)


def test_stride_4_pixel_projection_starts_at_zero_and_sees_single_pixel_columns(tmp_path):
    from towndrive.agent.deploy.onnx_export import export_detector
    from towndrive.agent.perception.detector import load_detector
    from towndrive.agent.training.detector_train_loop import save_checkpoint

    torch.manual_seed(3)
    blocks = Detector(DetectorConfig(strides=(4, 8, 16), s4_blocks=2)).eval()
    pixels = Detector(DetectorConfig(strides=(4, 8, 16), s4_blocks=2, s4_pixels=True)).eval()
    own = pixels.state_dict()
    missing, _ = pixels.load_state_dict({k: v for k, v in blocks.state_dict().items() if k in own}, strict=False)
    assert missing and all(k.startswith("pixels4.") for k in missing)
    x = torch.rand(1, 3, 160, 320)
    with torch.no_grad():
        assert all(torch.equal(a, b) for a, b in zip(blocks(x), pixels(x), strict=True))
        # A dark stripe 2 px wide in column 0-1 or 1-2 of the same 4x4 cell: the projection tells them apart.
        nn.init.normal_(pixels.pixels4[-1].weight)
        a, b = torch.ones(1, 3, 160, 320), torch.ones(1, 3, 160, 320)
        a[..., 40:44, 80:82] = 0.0
        b[..., 40:44, 81:83] = 0.0
        pa, pb = pixels.pixels4(a)[0, :, 10, 20], pixels.pixels4(b)[0, :, 10, 20]
        assert not torch.allclose(pa, pb)
    save_checkpoint(tmp_path / "px.pt", pixels, {})
    assert load_detector(tmp_path / "px.pt").config.s4_pixels
    assert export_detector(tmp_path / "px.pt", tmp_path / "px.onnx") < 1e-4
    with pytest.raises(ValueError, match="s4_pixels"):
        DetectorConfig(strides=(8, 16), s4_pixels=True)


def test_iou_aware_objectness_and_pixel_exact_shifts():
    from towndrive.agent.training.detector_train_loop import augment

    torch.manual_seed(0)
    model = Detector(DetectorConfig(width=8, strides=(4, 8, 16)))
    tg = [build_targets(np.array([[100, 60, 103, 72]], np.float32), np.array([2]), np.array([False]), (4, 8, 16))]
    maps = model(torch.rand(1, 3, 160, 320))
    plain, _ = yolo_loss(maps, tg, (4, 8, 16))
    aware, _ = yolo_loss(maps, tg, (4, 8, 16), obj_iou=0.5)
    assert torch.isfinite(aware) and not torch.equal(plain, aware)  # lower targets for badly placed boxes
    # scale_prob 0: every frame is only flipped and shifted by whole pixels (and colour-jittered), so a 3 px
    # box stays 3 px wide and on the pixel grid.
    img = np.random.default_rng(0).integers(0, 255, (160, 320, 3), dtype=np.uint8)
    boxes = np.array([[100, 60, 103, 72]], np.float32)
    for seed in range(5):
        out, b, ok = augment(img, boxes, np.random.default_rng(seed), scale_prob=0.0)
        assert ok.all() and np.allclose(b[0, 2:] - b[0, :2], (3, 12)) and np.allclose(b, np.round(b))


def test_box_l1_pulls_a_too_wide_box_to_the_object_width():
    """With the L1 edge term, the loss's gradient narrows a box 1.5x too wide for a 2 px pedestrian; off (0), the
    loss is exactly GIoU's."""
    torch.manual_seed(0)
    model = Detector(DetectorConfig(width=8, strides=(4, 8, 16)))
    tg = [build_targets(np.array([[100, 60, 102, 70]], np.float32), np.array([2]), np.array([False]), (4, 8, 16))]
    maps = [m.detach().clone() for m in model(torch.rand(1, 3, 160, 320))]
    pos = tg[0][0]["pos"]
    gx = torch.from_numpy(pos % 80).float()
    with torch.no_grad():  # stride-4 positives: boxes centred on the object, 3 px wide (1.5x), 10 px tall
        flat = maps[0].view(1, maps[0].shape[1], -1)
        flat[0, 0, pos] = torch.logit(((101.0 / 4 - gx + 0.5) / 2).clamp(0.01, 0.99))
        flat[0, 1, pos] = 0.0  # centre y in the middle of the cell's row
        flat[0, 2, pos] = float(np.log(3.0 / 4))
        flat[0, 3, pos] = float(np.log(10.0 / 4))
    maps[0].requires_grad_(True)
    base, parts = yolo_loss(maps, tg, (4, 8, 16))
    again, _ = yolo_loss(maps, tg, (4, 8, 16), box_l1=0.0)
    assert torch.equal(base, again) and "l1" not in parts
    loss, parts = yolo_loss(maps, tg, (4, 8, 16), box_l1=4.0)
    assert loss > base and parts["l1"] > 0
    (grad_plain,) = torch.autograd.grad(base, maps[0])
    (grad_l1,) = torch.autograd.grad(loss, maps[0])
    w_plain = grad_plain.view(1, grad_plain.shape[1], -1)[0, 2, pos]
    w_l1 = grad_l1.view(1, grad_l1.shape[1], -1)[0, 2, pos]
    assert (w_l1 > w_plain).all()  # a stronger push to shrink the width (gradient descent lowers log-width)


def test_overlay_draws_boxes_labels_ids_and_distances():
    frame = np.zeros((160, 320, 3), np.uint8)
    dets = [Detection((100, 60, 160, 100), 0, 0.9), Detection((10, 10, 20, 40), 3, 0.8)]
    out = draw_detections(frame, dets, scale=2, track_ids=[7, None], distances_m=[12.3, None])
    assert out.shape == (320, 640, 3)
    assert np.all(out[150, 200] == CLASS_COLORS["car"])  # left edge of the car's box, midway down
    assert out.sum() > 0 and frame.sum() == 0  # draws on a copy
    with pytest.raises(ValueError, match="track_ids"):
        draw_detections(frame, dets, track_ids=[1])


def test_hsv_baseline_reads_lit_lamps():
    img = np.full((40, 20, 3), 25, np.uint8)
    img[5:10, 8:12] = (255, 30, 20)
    assert hsv_state(img, (0, 0, 20, 40)) == "red"
    img[5:10, 8:12] = 25
    img[28:33, 8:12] = (38, 255, 90)
    assert hsv_state(img, (0, 0, 20, 40)) == "green"
    assert hsv_state(np.full((40, 20, 3), 25, np.uint8), (0, 0, 20, 40)) == "none"


@pytest.mark.skipif(not (MODELS / "detector.onnx").is_file(), reason="no shipped detector")
@pytest.mark.parametrize("backend", ["torch", "onnx"])
def test_shipped_model_detects_a_car_ahead(town, backend):
    world = World(town, WorldConfig(npc_count=0, pedestrian_count=0), seed=5, spawn_traffic=False)
    lane, s = world.ego_lane[0], world.ego_lane[1]
    world.spawn_npc(lane, s + 18.0, kind=SemanticClass.CAR, color=(0.2, 0.3, 0.8))
    renderer = SceneRenderer(town, seed=town.seed)
    try:
        frame, labels = render_and_label(renderer, world, CameraConfig(), "dusk")
    finally:
        renderer.close()
    car = next(lab for lab in labels if lab.name == "car")
    det = TorchDetector(MODELS / "detector.pt") if backend == "torch" else OnnxDetector(MODELS / "detector.onnx")
    cars = [d for d in det(frame.rgb) if d.name == "car"]
    assert cars, "the shipped detector missed a car 17 m ahead"
    best = max(box_iou(np.array([d.box for d in cars]), np.array([car.box], np.float32))[:, 0])
    assert best >= 0.5


def test_decoded_detector_has_one_output_row_per_cell():
    out = DecodedDetector(Detector().eval())(torch.rand(1, 3, 160, 320))
    assert out.shape == (1, 1000, 5 + len(CLASSES))
    assert torch.all(out[..., 2] > out[..., 0]) and torch.all((out[..., 4:] >= 0) & (out[..., 4:] <= 1))


def test_training_splits_share_no_town_with_val_or_test():
    from towndrive.agent.training.autolabel import WEATHERS, default_splits

    specs = {s.name: s for s in default_splits()}
    assert set(specs) == {"train", "val", "test", "train_peds", "train_peds2", "train_rigs", "val_rigs", "test_rigs",
                          "train_agent"}
    held_out = set(specs["val"].town_seeds) | set(specs["test"].town_seeds)
    training = [specs[n] for n in ("train", "train_peds", "train_peds2", "train_rigs", "train_agent")]
    for spec in training:
        assert not set(spec.town_seeds) & held_out, spec.name
        assert spec.weathers == WEATHERS
    assert not set(specs["train_peds"].town_seeds) & set(specs["train_peds2"].town_seeds)
    assert specs["train_peds2"].town_seeds == tuple(range(60, 100))
    assert specs["train_peds"].pedestrian_count == specs["train_peds2"].pedestrian_count == 60
    # the rig splits: another car's camera per frame, on the same held-out towns as val and test
    assert specs["val_rigs"].town_seeds == specs["val"].town_seeds and specs["test_rigs"].town_seeds == specs["test"].town_seeds
    assert all(specs[n].rigs is not None for n in ("train_rigs", "val_rigs", "test_rigs"))
    assert all(specs[n].rigs is None for n in ("train", "val", "test", "train_peds", "train_peds2"))
    assert [n for n, spec in specs.items() if spec.driver == "agent"] == ["train_agent"]


def test_init_grows_a_six_class_head_copying_its_channels_exactly(tmp_path):
    """``train.py detector train --init`` from a model of before the road signs: every tensor is taken, the heads'
    box, objectness and six class rows exactly; the four sign rows keep their fresh prior; the old classes' outputs
    are unchanged; the six-class checkpoint still loads (as a six-class model)."""
    from towndrive.agent.perception.detector import load_detector
    from towndrive.agent.training.detector_train_loop import init_from, save_checkpoint

    torch.manual_seed(0)
    old = Detector(DetectorConfig(strides=(4, 8, 16), num_classes=6))
    for m in old.modules():  # trained-looking statistics, so that BN is not the identity
        if isinstance(m, nn.BatchNorm2d):
            m.running_mean.uniform_(-0.2, 0.2)
            m.running_var.uniform_(0.5, 1.5)
    for head in old.heads():
        nn.init.normal_(head.weight, std=0.05)
        nn.init.normal_(head.bias, std=0.5)
    save_checkpoint(tmp_path / "six.pt", old.eval(), {})
    assert load_detector(tmp_path / "six.pt").config.num_classes == 6

    new = Detector(DetectorConfig(strides=(4, 8, 16)))
    fresh = {k: v.clone() for k, v in new.state_dict().items()}
    msg = init_from(new, torch.load(tmp_path / "six.pt", weights_only=True)["state_dict"])
    assert "grown heads" in msg and "head4.weight 11->15" in msg
    src, got = old.state_dict(), new.state_dict()
    for k, v in got.items():
        if k.startswith("head"):
            assert torch.equal(v[:11], src[k]), k
            assert torch.equal(v[11:], fresh[k][11:]), k  # the new classes' rows as initialised
        else:
            assert torch.equal(v, src[k]), k
    x = torch.rand(2, 3, 160, 320)
    with torch.no_grad():
        a, b = DecodedDetector(old.eval())(x), DecodedDetector(new.eval())(x)
    assert b.shape[-1] == 5 + len(CLASSES) == 15
    assert torch.allclose(a, b[..., :11], rtol=0, atol=1e-4)  # a wider 1x1 conv may sum in another order
    assert float(b[..., 11:].mean()) < 0.1  # the signs' prior, sigmoid(-3) = 0.05, not yet trained


def test_sign_classes_share_one_nms_group():
    stop, limit30, limit50, car = (CLASSES.index(n) for n in ("stop_sign", "speed_limit_30", "speed_limit_50", "car"))
    pred = cells([((100, 40, 110, 50), limit50, 0.8), ((100, 41, 110, 51), limit30, 0.6),  # one plate, two values
                  ((100, 40, 110, 50), car, 0.5), ((200, 40, 210, 50), stop, 0.7)])
    dets = postprocess(pred, score_threshold=0.3)
    assert sorted(d.name for d in dets) == ["car", "speed_limit_50", "stop_sign"]


def test_dataset_splits_of_town_styles_follow_the_town_seed_splits():
    import argparse

    from towndrive.agent.training.detector_training import add_arguments, dataset_specs
    from towndrive.sim.splits import split_of

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["dataset", "--town-style", "suburb", "--splits", "train,val,test,test_downtown,train_peds",
                              "--val-frames", "300"])
    specs = dataset_specs(args)
    assert [s.name for s in specs] == ["train_suburb", "val_suburb", "test_suburb", "test_downtown", "train_peds"]
    for spec, split in zip(specs[:4], ("train", "validation", "test", "test"), strict=True):
        assert {split_of(t) for t in spec.town_seeds} == {split} and spec.sign_boost
    assert specs[0].town_style == "suburb" and specs[3].town_style == "downtown" and specs[4].town_style is None
    assert specs[1].frames == 300 and len(specs[0].town_seeds) == 30 and specs[2].town_seeds[0] == 5000
    with pytest.raises(ValueError, match="unknown split"):
        dataset_specs(parser.parse_args(["dataset", "--splits", "train_uptown"]))
    with pytest.raises(ValueError, match="unknown town style"):
        dataset_specs(parser.parse_args(["dataset", "--town-style", "uptown"]))


def test_frames_with_a_labelled_limit_or_stop_sign_are_never_mirrored():
    """A mirrored 30 reads as "0Ɛ" and a mirrored 50 nearly as "02": such frames keep their orientation; others flip."""
    from towndrive.agent.training.detector_train_loop import make_batch

    img = np.zeros((1, 160, 320, 3), np.uint8)
    img[0, 20:140, 60:72] = 255  # a (tall) plate in the left half, wherever the shifts (at most 32 x 16 px) take it

    def sample(name: str, ignore: bool) -> Sample:
        return Sample("-", "noon", np.array([[60.0, 20.0, 72.0, 140.0]], np.float32), np.array([CLASSES.index(name)]),
                      np.array([ignore]), np.array([10.0], np.float32))

    def flips(s: Sample) -> int:
        count = 0
        for seed in range(24):
            x, _ = make_batch(img, [s], np.array([0]), np.random.default_rng(seed), (4, 8, 16), scale_prob=0.0)
            count += int(int(x[0, :, 80].sum(0).argmax()) > 160)  # the plate (brighter than the grey border) is right
        return count

    assert flips(sample("speed_limit_30", False)) == flips(sample("stop_sign", False)) == 0
    assert flips(sample("yield_sign", False)) > 5 and flips(sample("speed_limit_50", True)) > 5  # symmetric; ignored
