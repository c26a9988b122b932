"""Large outputs on transparent huge pages: what the advice of ``torchcage/_core/alloc.py`` saves.

Times, on one thread, the first fill of a fresh float64 table (the page faults a kernel pays when
it writes its output) with ``torch.empty`` and with ``empty_output`` (advised ``MADV_HUGEPAGE``),
against a fill of a reused table, at the output sizes of mean value and Green coordinates on the
QMVC data set's models; then mean value and Green coordinates (native kernels, ``exterior="none"``)
with the advice on and off (``advise_huge_pages`` replaced by a no-op), alternated in the same
rounds. CPU time, best of ``--repeat``.

Usage::

    python benchmarks/alloc.py [--models FireHydrant Beast] [--repeat 7] [--data ../shared/data]
"""

from __future__ import annotations

import os

if __name__ == "__main__":
    os.environ["OMP_NUM_THREADS"] = "1"  # before torch and the native kernels load

import functools
from collections.abc import Callable

import torch
from harness import cpu_best, model_parser, present_models

import torchcage.functional as F
from torchcage._core import alloc


def fill(make: Callable[[], torch.Tensor]) -> Callable[[], None]:
    """A fresh table from ``make()``, written once in full."""

    def run() -> None:
        make().fill_(1.0)

    return run


def row(n: int, cols: int, call: Callable[[], object], repeat: int) -> list[float]:
    """The best CPU times of: a fresh ``(n, cols)`` table filled (4 KiB pages, then advised), a
    reused one filled, ``call()`` with the advice off, and with it on (alternated)."""
    real = alloc.advise_huge_pages
    reused = torch.empty(n, cols, dtype=torch.float64)
    call()  # (warm-up: tables, libraries)

    def off() -> object:
        alloc.advise_huge_pages = lambda t: False
        try:
            return call()
        finally:
            alloc.advise_huge_pages = real

    return cpu_best(
        [
            fill(lambda: torch.empty(n, cols, dtype=torch.float64)),
            fill(lambda: alloc.empty_output(n, cols, dtype=torch.float64)),
            lambda: reused.fill_(1.0),
            off,
            call,
        ],
        repeat,
    )


def main() -> None:
    args = model_parser(__doc__, repeat=7).parse_args()
    torch.set_num_threads(1)
    print(f"torch {torch.__version__}, one thread, float64; huge-page advice available: {alloc._madvise is not None}")
    print("| model | table | MB | fresh, 4 KiB pages | fresh, advised | reused | call, advice off | call, advice on |")
    print("|---|---|---|---|---|---|---|---|")
    for model, points, cage in present_models(args.data, args.models):
        tri = cage.triangulated()
        n, V, T = points.shape[0], tri.num_vertices, tri.triangles.shape[0]
        calls = {
            "MVC": (V, functools.partial(F.mean_value_coordinates, points, tri)),
            "GC": (V + T, functools.partial(F.green_coordinates, points, tri, exterior="none")),
        }
        for name, (cols, call) in calls.items():
            t_plain, t_adv, t_reuse, t_off, t_on = row(n, cols, call, args.repeat)
            mb = n * cols * 8 / 1e6
            print(
                f"| {model} | {name} {n:,} x {cols} | {mb:.0f} | {t_plain * 1e3:.1f} ms | {t_adv * 1e3:.1f} ms "
                f"| {t_reuse * 1e3:.1f} ms | {t_off * 1e3:.1f} ms | {t_on * 1e3:.1f} ms |"
            )


if __name__ == "__main__":
    main()
