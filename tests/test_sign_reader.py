"""The sign reader: crops, relabelling and re-scoring of sign boxes, checkpoints and ONNX export."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from towndrive.agent.perception.classes import CLASSES, SIGN_CLASSES
from towndrive.agent.perception.detections import Detection
from towndrive.agent.perception.sign_reader import (
    CROP,
    NO_SIGN,
    Read,
    SignReader,
    SignReaderConfig,
    crop_windows,
    onnx_read,
    reader_inputs,
    relabel,
    torch_read,
    windows,
)


@pytest.fixture(autouse=True)
def one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_windows_are_square_centred_and_magnify_small_plates():
    cfg = SignReaderConfig()
    win = windows(np.array([[100, 50, 106, 56], [10, 10, 40, 30]], np.float32), cfg)
    assert win[0].tolist() == pytest.approx([103 - 6, 53 - 6, 12, 12])  # 6 px plate: the 12 px minimum
    assert win[1].tolist() == pytest.approx([25 - 24, 20 - 24, 48, 48])  # 1.6 x the longer side
    frame = np.zeros((160, 320, 3), np.uint8)
    frame[50:56, 100:106] = (200, 30, 30)
    crop = crop_windows(frame, win[:1])[0]
    assert crop.shape == (CROP, CROP, 3)
    red = crop[..., 0] > 100
    ys, xs = np.nonzero(red)
    assert abs(xs.mean() - 15.5) < 1.0 and abs(ys.mean() - 15.5) < 1.0 and 12 <= xs.max() - xs.min() + 1 <= 18
    x = reader_inputs(crop[None])
    assert x.shape == (1, 3, CROP, CROP) and x.dtype == np.float32 and x.min() >= -0.5 and x.max() <= 0.5


def test_reader_relabels_sign_boxes_rescores_them_and_passes_the_rest_on():
    stop, limit30, ped = CLASSES.index("stop_sign"), CLASSES.index("speed_limit_30"), CLASSES.index("pedestrian")
    p = np.zeros((2, NO_SIGN + 1), np.float32)
    p[0, SIGN_CLASSES.index("speed_limit_50")] = 0.81  # the detector said 30; the reader reads 50
    p[0, NO_SIGN] = 0.19
    p[1, NO_SIGN] = 0.96  # no sign at all: its best sign has 0.04
    p[1, SIGN_CLASSES.index("yield_sign")] = 0.04
    signs = [Detection((10, 10, 20, 20), limit30, 0.64), Detection((50, 10, 60, 20), stop, 0.5)]
    out = relabel(signs, p, 0.5)
    assert [d.name for d in out] == ["speed_limit_50", "yield_sign"]
    assert out[0].score == pytest.approx((0.64 * 0.81) ** 0.5) and out[1].score == pytest.approx((0.5 * 0.04) ** 0.5)
    assert out[0].box == signs[0].box

    logits = np.log(np.maximum(p, 1e-6))
    read = Read(lambda x: logits[:len(x)], SignReaderConfig())
    person = Detection((100, 40, 104, 52), ped, 0.05)  # below the threshold: left for the pedestrian refiner
    frame = np.zeros((160, 320, 3), np.uint8)
    got = read(frame, [person, *signs], 0.3)
    assert got[0] == person and [d.name for d in got[1:]] == ["speed_limit_50"]  # the "no sign" box dropped


def test_checkpoint_and_onnx_export_read_alike(tmp_path):
    from dataclasses import asdict

    from towndrive.agent.deploy.onnx_export import export_sign_reader
    from towndrive.agent.perception.checkpoints import save_checkpoint

    torch.manual_seed(0)
    model = SignReader().eval()
    cfg = SignReaderConfig(score_weight=0.7)
    save_checkpoint(tmp_path / "r.pt", {"state_dict": model.state_dict(), "config": asdict(cfg),
                                         "classes": SIGN_CLASSES})
    assert export_sign_reader(tmp_path / "r.pt", tmp_path / "r.onnx") < 1e-4
    a, b = torch_read(tmp_path / "r.pt"), onnx_read(tmp_path / "r.onnx", threads=1)
    assert a.config == b.config == cfg
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 255, (160, 320, 3), dtype=np.uint8)
    boxes = np.array([[10, 10, 22, 22], [300, 150, 318, 160]], np.float32)
    assert np.allclose(a.probabilities(frame, boxes), b.probabilities(frame, boxes), atol=1e-5)
