"""The one timer of torchcage's benchmarks and of ``torchcage bench``."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

__all__ = ["best_of"]

T = TypeVar("T")


def best_of(fn: Callable[[], T], repeat: int = 3, warmup: int = 0) -> tuple[float, float, T]:
    """Time ``fn()``: ``(first, best, result)``, the first timed call's seconds, the best of
    ``repeat`` calls (the first included) and the last call's result, after ``warmup`` untimed calls.

    Examples:
        >>> first, best, out = best_of(lambda: sum(range(1000)), repeat=3)
        >>> best <= first and out == 499500
        True
    """
    if repeat < 1:
        raise ValueError(f"repeat must be at least 1, got {repeat}")
    for _ in range(warmup):
        fn()
    first = best = float("inf")
    out: T
    for i in range(repeat):
        t = time.perf_counter()
        out = fn()
        dt = time.perf_counter() - t
        first = dt if i == 0 else first
        best = min(best, dt)
    return first, best, out
