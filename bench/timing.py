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
