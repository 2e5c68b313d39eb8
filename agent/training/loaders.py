"""Training batches built by DataLoader worker processes (``--loader-workers N``), the same for a seed.

Why: PilotNet's and the detector's batches are augmented sample by sample on the CPU (re-projection, flips,
HSV jitter, target assignment). In the training process that work and the optimiser step take turns, so a GPU
waits for every batch. With N worker processes the next batches are built while the current one trains, and on
CUDA they arrive in pinned memory, ready for a non-blocking copy.

How the draws stay deterministic: a batch's random numbers come from a generator seeded by the batch's key
(seed, epoch, rank) and its number, never from the worker that happens to build it or from the order in which
workers finish (the DataLoader hands batches back in order). So a seed gives the same batches, and the same
weights, for any N >= 1. N = 0, the default, is the training process's own single random stream, as before
loader workers existed: the same seed gives the same weights as it always did. N = 0 and N >= 1 draw different
(equally valid) augmentations.

Why fork, and what the workers may touch: the frames are preloaded into numpy arrays (PilotNet's preprocessed
frames, the detector's images), which forked workers share copy-on-write instead of receiving a pickled copy
each. Nothing a worker uses may hold an open file: h5py handles (like most file handles of C libraries) do not
survive a fork, so the episodes' HDF5 files are read and closed while loading (``pilotnet_data.load_frames``, in
worker processes of its own that each open the files they read), never kept in a dataset. Nor does OpenCV's
thread pool: the training process sets OpenCV to one thread before it forks (``single_threaded_opencv``).
``worker_init`` gives each worker one thread for torch and OpenCV (N workers use N cores) and seeds the global
generators from the DataLoader's seeded generator, for any code that still reaches for them.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import random
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import torch

# A callable that builds one batch from its own generator and the sample indices it holds.
MakeBatch = Callable[[np.random.Generator, np.ndarray], Any]


def check_loader_workers(n: int) -> int:
    if not isinstance(n, int) or n < 0:
        raise ValueError(f"--loader-workers {n}: give 0 (batches built in the training process) or more workers.")
    return n


class SeededBatches:
    """An epoch's batches as a map-style dataset: batch ``b`` holds ``picks[b * batch:(b + 1) * batch]`` and is
    built by ``make`` with a generator seeded by ``(*key, b)``, in whichever process asks for it."""

    def __init__(self, make: MakeBatch, picks: np.ndarray, batch: int, key: tuple[int, ...]) -> None:
        self.make, self.picks, self.batch, self.key = make, np.asarray(picks), int(batch), tuple(int(k) for k in key)

    def __len__(self) -> int:
        return math.ceil(len(self.picks) / self.batch)

    def __getitem__(self, b: int) -> Any:
        if not 0 <= b < len(self):
            raise IndexError(b)
        rng = np.random.default_rng((*self.key, b))
        return self.make(rng, self.picks[b * self.batch:(b + 1) * self.batch])


def as_built(batch: Any) -> Any:
    """The batch as ``make`` built it (the DataLoader's default would turn the detector's numpy targets into
    tensors)."""
    return batch


def seed_of(key: tuple[int, ...]) -> int:
    """A seed for the DataLoader's own generator from a batch key (the same on every run and Python)."""
    return int(np.random.SeedSequence([int(k) for k in key]).generate_state(1)[0])


def worker_init(worker_id: int) -> None:
    """One thread per worker for torch and OpenCV; the global generators seeded from the worker's torch seed
    (which the DataLoader derives from its seeded generator, so it is the same every run)."""
    import torch

    torch.set_num_threads(1)
    seed = torch.initial_seed() % 2**32
    np.random.seed(seed)
    random.seed(seed)
    try:
        import cv2

        cv2.setNumThreads(1)
    except ImportError:  # pragma: no cover - OpenCV is a dependency of every training command
        pass


def single_threaded_opencv() -> None:
    """OpenCV's own thread pool does not survive a fork: a forked worker that calls a parallel OpenCV function
    (``cv2.remap``, ``cv2.resize``) can wait forever for threads it does not have. Set to one thread before the
    fork, the pool is gone; the training process has no augmentation left to do once workers build the batches."""
    try:
        import cv2
    except ImportError:  # pragma: no cover - OpenCV is a dependency of every training command
        return
    cv2.setNumThreads(1)


def batch_loader(batches: SeededBatches, workers: int, device: torch.device, seed: int) -> torch.utils.data.DataLoader:
    """Batches in order, built by ``workers`` forked processes (``0``: here, when iterated), pinned on CUDA."""
    import torch

    generator = torch.Generator()
    generator.manual_seed(int(seed))
    context = None
    if workers > 0 and "fork" in mp.get_all_start_methods():
        context = mp.get_context("fork")  # the preloaded frames shared copy-on-write, not pickled per worker
        single_threaded_opencv()
    return torch.utils.data.DataLoader(
        batches, batch_size=None, shuffle=False, num_workers=workers, pin_memory=device.type == "cuda",
        collate_fn=as_built, worker_init_fn=worker_init if workers > 0 else None, generator=generator,
        multiprocessing_context=context,
        prefetch_factor=2 if workers > 0 else None, persistent_workers=False)
