"""Benchmark of Green coordinate gradients (``F.green_derivatives``) on a data-set cage.

10,000 points inside the Beast cage (300 triangles): the closed-form gradients against, in the
same run, the MVC gradients (``F.mean_value_derivatives(order=1)``, native) and reverse-mode
autograd of the Green torch kernel (one backward pass per coordinate, on 20 of the points and
scaled), the way to get them before. Best of ``--repeat``.

Usage: ``python benchmarks/green_derivatives.py [--data ../shared/data] [--model Beast] [--points 10000]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import add_data_argument, qmvc_root

import torchcage
from torchcage import functional as F
from torchcage.functional.green_derivatives import _autograd_rows
from torchcage.geometry import inside_cage


def _best(f, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - t)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_data_argument(ap)
    ap.add_argument("--model", default="Beast")
    ap.add_argument("--points", type=int, default=10000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    cage = torchcage.load_cage(qmvc_root(args.data) / f"{args.model}_Cage.obj").to(torch.float64).triangulated()
    g = torch.Generator().manual_seed(0)
    v = cage.vertices
    lo, hi = v.min(0).values, v.max(0).values
    x = lo + (hi - lo) * torch.rand(20 * args.points, 3, generator=g, dtype=torch.float64)
    x = x[inside_cage(x, cage)][: args.points]
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; {args.model}: {cage.triangles.shape[0]} "
          f"triangles, {x.shape[0]} points inside")  # fmt: skip
    t_gc = _best(lambda: F.green_derivatives(x, cage), args.repeat)
    t_mvc = _best(lambda: F.mean_value_derivatives(x, cage, order=1), args.repeat)
    m = 20
    t_ad = _best(lambda: _autograd_rows(x[:m], cage, "extend"), 1) * x.shape[0] / m
    print(f"{'method':<44} {'seconds':>8} {'vs MVC':>7}")
    for name, t in (
        ("green_derivatives (closed form, torch)", t_gc),
        ("mean_value_derivatives order=1 (native)", t_mvc),
        ("autograd of the Green kernel (scaled)", t_ad),
    ):
        print(f"{name:<44} {t:>8.2f} {t / t_mvc:>6.1f}x")


if __name__ == "__main__":
    main()
