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


def interruptions(seconds: float = 2.0, threshold_s: float = 10e-6) -> tuple[float, float]:
    """How often this machine takes the CPU away from a running Python thread: a tight loop reads
    the clock for ``seconds`` and counts the gaps longer than ``threshold_s`` between two reads
    (interrupts, the hypervisor, other threads). Returns (gaps per second, median gap in s).

    A piece of code of duration d then loses the CPU in about ``rate * d`` of its runs, each time
    for about the median gap: a floor under its tail that the code itself cannot remove."""
    clock = time.perf_counter_ns
    limit = int(threshold_s * 1e9)
    gaps: list[int] = []
    end = clock() + int(seconds * 1e9)
    last = clock()
    while last < end:
        now = clock()
        if now - last > limit:
            gaps.append(now - last)
        last = now
    return len(gaps) / seconds, float(np.median(gaps)) * 1e-9 if gaps else 0.0
