"""Where training runs: ``--device auto|cpu|cuda|cuda:K``, mixed precision on CUDA, and torchrun's processes.

``resolve_device`` turns the flag into a ``torch.device`` (auto: CUDA when torch sees one). ``Distributed``
reads the environment ``torchrun`` sets (RANK, WORLD_SIZE, LOCAL_RANK); ``start_training`` gives a command its
process and device, ``process_group`` starts and ends the group (nccl on CUDA, gloo on the CPU) and
``data_parallel`` wraps the model. PilotNet and the detector train under torchrun through these same calls.
Nothing here changes the single-process CPU path.
"""

from __future__ import annotations

import argparse
import contextlib
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # torch is imported where it is used: the flags' modules must load without it (fast --help)
    import torch

DEVICE_HELP = "auto (CUDA when present), cpu, cuda or cuda:K; mixed precision on CUDA"


def add_device_argument(p: argparse.ArgumentParser, default: str = "auto", more: str = "") -> None:
    """``--device``, the same for every training command (``more``: what this command adds to the help)."""
    p.add_argument("--device", default=default, help=f"where to train: {DEVICE_HELP}" + (f". {more}" if more else ""))


def add_loader_argument(p: argparse.ArgumentParser) -> None:
    """``--loader-workers``, the same for PilotNet and the detector (see ``loaders.py``)."""
    p.add_argument("--loader-workers", type=int, default=0, metavar="N",
                   help="build the batches in N DataLoader worker processes (pinned memory on CUDA), so that a GPU "
                        "does not wait for augmentation; 0 (default): in the training process, as before. The same "
                        "seed gives the same weights for any N >= 1; 0 and N >= 1 draw different augmentations")


def resolve_device(text: str = "auto", local_rank: int | None = None) -> torch.device:
    """``auto``/``cpu``/``cuda``/``cuda:K`` as a device; ValueError in one sentence when it is not there."""
    import torch

    text = (text or "auto").strip().lower()
    if text == "auto":
        text = "cuda" if torch.cuda.is_available() else "cpu"
    if text == "cpu":
        return torch.device("cpu")
    if text == "cuda" or text.startswith("cuda:"):
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if text == "cuda":
            index = local_rank if local_rank is not None else 0
        else:
            try:
                index = int(text.split(":", 1)[1])
            except ValueError:
                raise ValueError(f"--device {text}: expected auto, cpu, cuda or cuda:K with K a number") from None
        if index >= count:
            seen = f"{count} CUDA device{'s' if count != 1 else ''}" if count else "no CUDA device"
            raise ValueError(f"--device {text}: torch sees {seen} here (torch {torch.__version__}, "
                             f"CUDA build {torch.version.cuda or 'none'}); use --device cpu or auto")
        return torch.device("cuda", index)
    raise ValueError(f"--device {text}: expected auto, cpu, cuda or cuda:K")


def autocast(device: torch.device, dtype: torch.dtype | None = None):
    """Mixed precision on CUDA (bf16 where supported, else fp16); a no-op context elsewhere."""
    import torch

    if device.type != "cuda":
        return contextlib.nullcontext()
    return torch.autocast("cuda", dtype=dtype or cuda_amp_dtype(device))


def cuda_amp_dtype(device: torch.device) -> torch.dtype:
    import torch

    return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16


def grad_scaler(device: torch.device) -> torch.amp.GradScaler | None:
    """A GradScaler for fp16 autocast on CUDA; None where none is needed (CPU, bf16)."""
    import torch

    if device.type == "cuda" and cuda_amp_dtype(device) == torch.float16:
        return torch.amp.GradScaler("cuda")
    return None


def backward_step(loss: torch.Tensor, opt: torch.optim.Optimizer, scaler: torch.amp.GradScaler | None,
                  clip: tuple[Iterable[torch.Tensor], float] | None = None) -> None:
    """``loss.backward()``, then (``clip``: parameters and a max norm) gradients clipped, unscaled first, then
    ``opt.step()``; through the scaler when there is one. Without a scaler (the CPU, bf16) these are exactly the
    plain steps."""
    import torch

    if scaler is None:
        loss.backward()
        if clip is not None:
            torch.nn.utils.clip_grad_norm_(*clip)
        opt.step()
    else:
        scaler.scale(loss).backward()
        if clip is not None:
            scaler.unscale_(opt)
            torch.nn.utils.clip_grad_norm_(*clip)
        scaler.step(opt)
        scaler.update()


def to_device(t: torch.Tensor, device: torch.device) -> torch.Tensor:
    """Move a CPU batch: pinned and non-blocking on CUDA, untouched on the CPU."""
    if device.type != "cuda":
        return t
    return t.pin_memory().to(device, non_blocking=True)


@dataclass(frozen=True)
class Distributed:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def barrier(self) -> None:
        import torch

        if self.enabled and torch.distributed.is_initialized():
            torch.distributed.barrier()

    def close(self) -> None:
        import torch

        if self.enabled and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()

    def agree(self, flag: bool) -> bool:
        """True on every rank when it is true on any (a time limit, say: all ranks must stop at the same step, or
        the others wait forever in their next all-reduce)."""
        import torch

        if not (self.enabled and torch.distributed.is_initialized()):
            return flag
        t = torch.tensor([1.0 if flag else 0.0])
        if torch.distributed.get_backend() == "nccl":
            t = t.cuda()
        torch.distributed.all_reduce(t, op=torch.distributed.ReduceOp.MAX)
        return bool(t.item() > 0)

    @property
    def label(self) -> str:
        return f", rank {self.rank} of {self.world_size}" if self.enabled else ""


def distributed_from_env() -> Distributed:
    """The torchrun process this is (rank 0 of 1 when not started by torchrun)."""
    world = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if world <= 1 or "RANK" not in os.environ:
        return Distributed()
    return Distributed(int(os.environ["RANK"]), world, int(os.environ.get("LOCAL_RANK", os.environ["RANK"])))


def init_distributed(dist: Distributed, device: torch.device) -> None:
    """Start the process group: nccl for CUDA devices, gloo on the CPU."""
    import torch

    if not dist.enabled or torch.distributed.is_initialized():
        return
    if device.type == "cuda":
        torch.cuda.set_device(device)
    torch.distributed.init_process_group("nccl" if device.type == "cuda" else "gloo",
                                         rank=dist.rank, world_size=dist.world_size)


def start_training(device_text: str) -> tuple[Distributed, torch.device]:
    """This process's place in a torchrun job (rank 0 of 1 without torchrun) and its device; ``cuda`` is the
    local rank's GPU under torchrun. ValueError in one sentence for a device that is not there."""
    dist = distributed_from_env()
    return dist, resolve_device(device_text, dist.local_rank if dist.enabled else None)


@contextlib.contextmanager
def process_group(dist: Distributed, device: torch.device) -> Iterator[Distributed]:
    """The process group for the duration of a training run (nothing without torchrun)."""
    init_distributed(dist, device)
    try:
        yield dist
    finally:
        dist.close()


def data_parallel(model: torch.nn.Module, device: torch.device, dist: Distributed) -> torch.nn.Module:
    """The model as the training loop drives it: under torchrun wrapped in DistributedDataParallel (rank 0's
    initial weights and buffers broadcast to every rank, gradients averaged), else the model itself."""
    import torch

    if not dist.enabled:
        return model
    return torch.nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
