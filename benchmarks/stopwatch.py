"""Wall-clock timing shared by the benchmark scripts (``from stopwatch import best_s``).

A benchmark is run as ``python benchmarks/bench_x.py``, which puts this folder
on ``sys.path``.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np


def _runs_s(fn: Callable[[], object], repeats: int) -> np.ndarray:
    """(repeats,) wall-clock seconds of ``repeats`` calls of ``fn``."""
    if repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {repeats!r}")
    out = np.empty(repeats)
    for k in range(repeats):
        t0 = time.perf_counter()
        fn()
        out[k] = time.perf_counter() - t0
    return out


def best_s(fn: Callable[[], object], repeats: int) -> float:
    """Shortest of ``repeats`` timed calls, s (the least disturbed by the rest of the machine)."""
    return float(_runs_s(fn, repeats).min())


def median_s(fn: Callable[[], object], repeats: int) -> float:
    """Median of ``repeats`` timed calls, s (for calls that each see different data)."""
    return float(np.median(_runs_s(fn, repeats)))
