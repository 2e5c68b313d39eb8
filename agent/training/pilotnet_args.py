"""The flags of ``towndrive train pilotnet``, apart from the training code so that ``--help`` needs no torch."""

from __future__ import annotations

import argparse
from pathlib import Path

from towndrive.agent.training.devices import add_device_argument, add_loader_argument
from towndrive.agent.training.outputs import add_replace_shipped


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, nargs="+", default=[Path("data/episodes/autopilot")],
                   help="episode folders (towndrive record output, or towndrive data import-udacity output)")
    p.add_argument("--out", type=Path, default=Path("out/pilotnet"), help="run folder: checkpoints, log.csv, loss.png")
    p.add_argument("--model", type=Path, default=None,
                   help="where the best model (.pt and .onnx) goes (default: pilotnet.pt in the run folder)")
    add_replace_shipped(p, "PilotNet (pilotnet.pt and .onnx)")
    p.add_argument("--epochs", type=int, default=12, help="training epochs")
    p.add_argument("--samples-per-epoch", type=int, default=0, help="balanced draws per epoch (0: the train set size)")
    p.add_argument("--batch", type=int, default=64, help="frames per batch")
    p.add_argument("--lr", type=float, default=1e-3, help="learning rate (Adam)")
    p.add_argument("--seed", type=int, default=0, help="seed of the split, initialisation and sampling")
    p.add_argument("--validation", type=float, default=0.15, help="fraction of episodes held out for validation")
    p.add_argument("--unconditional", action="store_true", help="plain PilotNet without the route command")
    p.add_argument("--no-augment", action="store_true", help="train without augmentation (brightness, shadows, shifts, flips)")
    p.add_argument("--no-flip", action="store_true", help="augment without horizontal flips")
    p.add_argument("--no-side-cameras", action="store_true", help="ignore side cameras even where recorded")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    p.add_argument("--precision", choices=["auto", "fp32", "bf16"], default="auto",
                   help="training arithmetic: bf16 autocast (weights stay fp32) is 1.6x faster on CPUs with "
                        "AVX512-BF16; auto picks it where the CPU has it")
    p.add_argument("--resume", action="store_true", help="continue from --out/last.pt")
    p.add_argument("--dagger", type=int, default=0, metavar="ROUNDS", help="DAgger rounds after training")
    p.add_argument("--dagger-episodes", type=int, default=8, help="learner episodes per DAgger round")
    p.add_argument("--dagger-epochs", type=int, default=4, help="training epochs per DAgger round")
    p.add_argument("--dagger-seconds", type=float, default=60.0, help="length of each DAgger episode")
    add_loader_argument(p)
    add_device_argument(p, more="Several GPUs (or CPU processes): start with torchrun --nproc_per_node N "
                                "train.py pilotnet ... (DDP)")
