"""Training batches from DataLoader worker processes (agent/training/loaders.py): 0 workers is the old stream,
any number of workers gives the same batches and weights for a seed. Synthetic frames keep it fast."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest
import torch

from towndrive.agent.perception.pilotnet import build
from towndrive.agent.training import pilotnet_training
from towndrive.agent.training.loaders import SeededBatches, batch_loader, check_loader_workers
from towndrive.agent.training.pilotnet_data import Augmenter, FrameSet
from towndrive.sim.render import CameraConfig


@pytest.fixture(autouse=True)
def one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def frames() -> tuple[FrameSet, FrameSet]:
    rng = np.random.default_rng(0)
    n = 96
    fs = FrameSet(rng.integers(0, 255, (n, 66, 200, 3), dtype=np.uint8), rng.uniform(-1, 1, n).astype(np.float32),
                  rng.uniform(2, 10, n).astype(np.float32), rng.integers(0, 4, n).astype(np.int64), np.arange(n) % 4,
                  [Path(f"episode_{k}") for k in range(4)])
    return fs.subset(fs.episode != 0), fs.subset(fs.episode == 0)


def trained_weights(frames: tuple[FrameSet, FrameSet], out: Path, **flags: int) -> dict[str, torch.Tensor]:
    """PilotNet after one short epoch; ``flags`` are added to the arguments (none: the arguments as they were
    before --loader-workers existed)."""
    args = argparse.Namespace(epochs=1, lr=1e-3, samples_per_epoch=48, batch=16, seed=3, no_augment=False,
                              no_flip=False, precision="fp32", **flags)
    torch.manual_seed(3)
    model = build(True)
    out.mkdir(parents=True)
    pilotnet_training.fit(model, *frames, args, out)
    return model.state_dict()


def same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return all(torch.equal(a[k], b[k]) for k in a)


def test_zero_loader_workers_is_the_old_in_process_stream_and_workers_agree_with_each_other(frames, tmp_path):
    before = trained_weights(frames, tmp_path / "before")  # no loader_workers at all: the code path of before
    zero = trained_weights(frames, tmp_path / "zero", loader_workers=0)
    one = trained_weights(frames, tmp_path / "one", loader_workers=1)
    two = trained_weights(frames, tmp_path / "two", loader_workers=2)
    assert same(before, zero)  # the default keeps the old weights for a seed
    assert same(one, two)  # batch b's draws come from (seed, epoch, rank, b), not from the worker that built it
    assert not same(zero, two)  # (and the workers really drew their own augmentations)


def test_a_batch_built_by_a_worker_process_is_the_one_built_here(frames):
    train, _ = frames
    make = pilotnet_training.functools.partial(pilotnet_training._batch, train=train,
                                               augmenter=Augmenter(CameraConfig()))
    picks = np.random.default_rng(1).choice(len(train), size=40)
    batches = SeededBatches(make, picks, 16, (7, 0, 0))
    assert len(batches) == 3
    here = [batches[b] for b in range(len(batches))]
    loaded = list(batch_loader(batches, 2, torch.device("cpu"), seed=7))
    assert [len(b[2]) for b in loaded] == [16, 16, 8]
    for mine, theirs in zip(here, loaded, strict=True):
        assert all(torch.equal(x, y) for x, y in zip(mine, theirs, strict=True))
    assert not torch.equal(here[0][0], batches.__class__(make, picks, 16, (8, 0, 0))[0][0])  # another seed, other draws


def test_a_negative_loader_worker_count_is_one_sentence(tmp_path, capsys):
    with pytest.raises(ValueError, match="--loader-workers -1: give 0"):
        check_loader_workers(-1)
    import train

    assert train.main(["pilotnet", "--data", str(tmp_path), "--out", str(tmp_path / "o"), "--loader-workers", "-1",
                       "--device", "cpu"]) == 2
    assert "--loader-workers -1" in capsys.readouterr().err


def test_detector_batches_keep_their_numpy_targets_through_worker_processes():
    from towndrive.agent.training.detector_eval import Sample
    from towndrive.agent.training.detector_train_loop import _seeded_batch

    rng = np.random.default_rng(2)
    images = rng.integers(0, 255, (6, 160, 320, 3), dtype=np.uint8)
    samples = [Sample(f"frame_{k}.png", "noon", np.array([[40.0 + k, 50, 70 + k, 90], [200, 60, 204, 70]], np.float32),
                      np.array([0, 2]), np.array([False, k % 2 == 1]), np.array([20.0, 30.0], np.float32))
               for k in range(6)]
    make = pilotnet_training.functools.partial(_seeded_batch, images=images, samples=samples, strides=(4, 8, 16),
                                               scale_prob=0.5)
    batches = SeededBatches(make, np.array([5, 0, 3, 1, 4, 2]), 3, (0, 1, 0))
    here = [batches[b] for b in range(len(batches))]
    loaded = list(batch_loader(batches, 2, torch.device("cpu"), seed=0))
    assert len(loaded) == 2
    for (x, targets), (x2, targets2) in zip(here, loaded, strict=True):
        assert torch.equal(x, x2) and x.shape == (3, 3, 160, 320)
        for image, image2 in zip(targets, targets2, strict=True):
            for level, level2 in zip(image, image2, strict=True):
                assert all(isinstance(v, np.ndarray) and np.array_equal(v, level2[k]) for k, v in level.items())
    assert sum(len(level["pos"]) for image in here[0][1] for level in image) > 0  # there were targets to carry
