"""Benchmark of batched rest cages: one native call for the whole batch against a loop of
single-cage calls, mean value coordinates forward (no graph, CPU).

The setting of ``learnable.py`` (Neural Cages): B = 8 shapes, N = 5,000 points each, a 42-vertex /
80-triangle icosphere cage per shape (each jittered), points inside. *loop*: ``over_cage_batch``
calling ``F.mean_value_coordinates`` per element (what a batched cage did before the batched
kernel: per element its tables, its checks and one native call); *batched*:
``F.mean_value_coordinates`` on the batched ``Cage`` (one set of tables for the batch, one native
call). Each call builds the cage (``validate="topology"``, as a training step does), so the
geometric check runs every time. *kernel*: the time inside the native calls (the C function
itself, argument checks excluded), *set-up*: the rest, and its share of the total. Both run in one
process, interleaved, best of ``--repeat``.

Usage: ``python benchmarks/batched.py [--batch 8] [--points 5000] [--repeat 10]``
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

import torchcage
from torchcage import _native
from torchcage._native import abi
from torchcage.functional import mean_value_coordinates
from torchcage.functional._batch import over_cage_batch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from learnable import problem

KERNEL = [0.0]


def _timed_call(lib, name: str, **arguments: object) -> None:
    """``_native.call`` with the C function's own time added to ``KERNEL``."""
    arguments.setdefault("nthreads", torch.get_num_threads())
    args = abi.check_arguments(name, arguments)
    t = time.perf_counter()
    getattr(lib, name)(*args)
    KERNEL[0] += time.perf_counter() - t


def _impls(x: torch.Tensor, P: torch.Tensor, faces: torch.Tensor) -> dict[str, Callable[[], torch.Tensor]]:
    def loop() -> torch.Tensor:
        return over_cage_batch(mean_value_coordinates, x, torchcage.Cage(P, faces, validate="topology"))

    def batched() -> torch.Tensor:
        return mean_value_coordinates(x, torchcage.Cage(P, faces, validate="topology"))

    return {"loop": loop, "batched": batched}


def _best(impls: dict[str, Callable[[], torch.Tensor]], repeat: int) -> dict[str, tuple[float, float]]:
    """``{name: (best seconds, kernel seconds of that call)}``, the implementations interleaved."""
    best = {k: (float("inf"), 0.0) for k in impls}
    with torch.no_grad():
        for _ in range(repeat):
            for name, fn in impls.items():
                KERNEL[0] = 0.0
                t = time.perf_counter()
                fn()
                dt = time.perf_counter() - t
                if dt < best[name][0]:
                    best[name] = (dt, KERNEL[0])
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--points", type=int, default=5000)
    ap.add_argument("--repeat", type=int, default=10)
    args = ap.parse_args()
    _native.call = _timed_call  # every glue module calls it through the module attribute
    print(
        f"B = {args.batch} cages x N = {args.points} points, 42-vertex / 80-triangle cages, CPU, "
        f"{torch.get_num_threads()} threads, best of {args.repeat}\n"
    )
    print("| dtype | path | forward | kernel | set-up | set-up share | speed-up |")
    print("|---|---|---|---|---|---|---|")
    for dtype in (torch.float32, torch.float64):
        name = str(dtype).removeprefix("torch.")
        impls = _impls(*problem(args.batch, args.points, dtype, "cpu")[:3])
        with torch.no_grad():
            outs = {k: fn() for k, fn in impls.items()}  # (warm-up: lazy imports, the native library)
        best = _best(impls, args.repeat)
        for impl, (total, kernel) in best.items():
            print(
                f"| {name} | {impl} | {total * 1e3:.1f} ms | {kernel * 1e3:.1f} ms | {(total - kernel) * 1e3:.1f} ms | "
                f"{(total - kernel) / total:.0%} | {best['loop'][0] / total:.2f}x |",
                flush=True,
            )
        diff = float((outs["loop"] - outs["batched"]).abs().max())
        print(f"| {name} | largest difference, loop - batched | {diff:.1e} | | | | |")


if __name__ == "__main__":
    main()
