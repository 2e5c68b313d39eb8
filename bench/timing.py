"""Latency statistics shared by the benchmarks: run a callable many times, report p50 and p95 in ms."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Latency:
    p50_ms: float
    p95_ms: float
    mean_ms: float
    n: int

    def __str__(self) -> str:
        return f"p50 {self.p50_ms:.2f} ms, p95 {self.p95_ms:.2f} ms (n={self.n})"


def latency_of(samples_s: list[float] | np.ndarray) -> Latency:
    ms = np.asarray(samples_s, dtype=np.float64) * 1000.0
    return Latency(float(np.percentile(ms, 50)), float(np.percentile(ms, 95)), float(ms.mean()), int(ms.size))


def measure(fn: Callable[[], object], repeats: int = 200, warmup: int = 10) -> Latency:
    """Time ``fn()`` ``repeats`` times after ``warmup`` untimed calls."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t0)
    return latency_of(samples)


def machine_line() -> str:
    """Which machine a figure is from: CPU model, cores, vector extensions and the load average now.

    Why: the same code runs 1.5x apart on two 2-core machines (AVX-512 or not), and a shared machine's other
    jobs move every figure; a table row is only comparable with rows of the same machine class and load."""
    import os
    import platform

    model, flags = platform.processor() or "unknown CPU", set()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() == "model name" and model in ("unknown CPU", "", platform.machine()):
                    model = value.strip()
                elif key.strip() == "flags":
                    flags = set(value.split())
                    break
    except OSError:
        pass
    wanted = (("avx2", "AVX2"), ("avx512f", "AVX-512"), ("avx512_vnni", "AVX-512 VNNI"), ("avx_vnni", "AVX-VNNI"))
    vector = ", ".join(name for flag, name in wanted if flag in flags) or "none of AVX2 / AVX-512 / VNNI"
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    load = " ".join(f"{x:.2f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"
    return f"machine: {model}, {os.cpu_count()} cores ({cores} usable), {vector}; load average {load}"
