"""How the native CPU kernels scale with threads: mean value, Green, QMVC and QGC coordinates.

Times each method on the QMVC data set's models (mesh vertices as points; MVC and GC on the cage
triangulated along ``q0-q2``, GC with ``exterior="none"``; QMVC at n = 4 and QGC at n = 2 on the triquad
cage) with one thread and with ``--threads`` threads, the thread counts alternated in the same
rounds. Wall-clock time (CPU time adds up over threads), best of ``--repeat``. *scaling* is the
one-thread time over the many-thread time (the issue's goal for two threads: at least 1.8x);
*max diff.* is the largest difference between the two results (each point's row is computed by
one thread whatever their number, so 0 is expected).

Usage::

    python benchmarks/threads.py [--models FireHydrant Beast] [--threads 2] [--repeat 5] [--data ../shared/data]
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Callable

import torch
from harness import model_parser, present_models

import torchcage
import torchcage.functional as F
from torchcage.backends import native


def wall_best(fn: Callable[[], object], counts: list[int], repeat: int) -> tuple[list[float], list[object]]:
    """The best wall-clock time of ``fn()`` with each thread count (alternated, ``repeat`` rounds)
    and its last result with each."""
    best, last = [float("inf")] * len(counts), [None] * len(counts)
    for _ in range(repeat):
        for i, k in enumerate(counts):
            torch.set_num_threads(k)
            t = time.perf_counter()
            last[i] = fn()
            best[i] = min(best[i], time.perf_counter() - t)
    return best, last


def flat(result: object) -> torch.Tensor:
    """One tensor of a method's result (Green's (phi, psi) joined)."""
    return torch.cat([r.flatten() for r in result]) if isinstance(result, tuple) else result.flatten()


def methods(points: torch.Tensor, cage: torchcage.Cage) -> dict[str, Callable[[], object]]:
    """The timed calls on one model."""
    tri = cage.triangulated()
    return {
        f"MVC, {tri.triangles.shape[0]} triangles": functools.partial(F.mean_value_coordinates, points, tri),
        f"GC, {tri.triangles.shape[0]} triangles": functools.partial(F.green_coordinates, points, tri, exterior="none"),
        "QMVC, n=4": functools.partial(F.quad_mean_value_coordinates, points, cage, n=4),
        "QGC, n=2": functools.partial(F.quad_green_coordinates, points, cage, n=2),
    }


def main() -> None:
    ap = model_parser(__doc__, repeat=5)
    ap.add_argument("--threads", type=int, default=min(2, os.cpu_count() or 1))
    args = ap.parse_args()
    counts = [1, args.threads]
    print(f"torch {torch.__version__}, float64, native library: {native.variant()}, {os.cpu_count()} CPUs")
    print(f"| model | method | 1 thread | {args.threads} threads | scaling | max diff. |")
    print("|---|---|---|---|---|---|")
    for model, points, cage in present_models(args.data, args.models):
        name = f"{model} ({points.shape[0]:,} pts)"
        for label, fn in methods(points, cage).items():
            fn()  # (warm-up: tables, libraries)
            (t1, tk), (r1, rk) = wall_best(fn, counts, args.repeat)
            diff = float((flat(r1) - flat(rk)).abs().max())
            print(f"| {name} | {label} | {t1 * 1e3:,.1f} ms | {tk * 1e3:,.1f} ms | {t1 / tk:.2f}x | {diff:.1e} |")
            name = ""


if __name__ == "__main__":
    main()
