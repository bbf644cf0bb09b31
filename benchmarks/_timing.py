"""Shared timing helpers for the benchmark scripts: median and p99 of repeated calls."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np


def time_calls(fn: Callable[[], object], repeats: int, warmup: int = 20) -> np.ndarray:
    """Wall-clock seconds of ``repeats`` calls of ``fn`` after ``warmup`` untimed calls."""
    for _ in range(warmup):
        fn()
    out = np.empty(repeats)
    clock = time.perf_counter
    for k in range(repeats):
        t0 = clock()
        fn()
        out[k] = clock() - t0
    return out


def summary(label: str, seconds: np.ndarray, per: int = 1, unit: float = 1e-6, unit_name: str = "µs") -> tuple[float, float]:
    """Print and return (median, p99) of ``seconds / per`` in ``unit``."""
    med, p99 = np.median(seconds) / per / unit, np.percentile(seconds, 99) / per / unit
    print(f"{label:<58s} median {med:10.2f} {unit_name}   p99 {p99:10.2f} {unit_name}")
    return med, p99
