"""Benchmark of Green coordinate derivatives (``F.green_derivatives``) on a data-set cage.

10,000 points inside the Beast cage (300 triangles), gradients (order 1) and gradients with
Hessians (order 2): the closed form (native kernel; the torch kernel on ``--torch-points`` of the
points, scaled) against, in the same run, the MVC derivatives of the same order
(``F.mean_value_derivatives``, native) and autograd of the Green torch kernel (``D + 1`` backward
passes for the gradients, ``(D + 1)^2`` with the Hessians, on 200 of the points and scaled).
Best of ``--repeat``.

Usage: ``python benchmarks/green_derivatives.py [--data ../shared/data] [--model Beast] [--points 10000]
[--torch-points 2000]``
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
from torchcage.families.green.derivatives_flat import autograd_rows
from torchcage.families.green.dispatch import green_flat
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
    ap.add_argument("--torch-points", type=int, default=2000)
    args = ap.parse_args()
    cage = torchcage.load_cage(qmvc_root(args.data) / f"{args.model}_Cage.obj").to(torch.float64).triangulated()
    g = torch.Generator().manual_seed(0)
    v = cage.vertices
    lo, hi = v.min(0).values, v.max(0).values
    x = lo + (hi - lo) * torch.rand(20 * args.points, 3, generator=g, dtype=torch.float64)
    x = x[inside_cage(x, cage)][: args.points]
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; {args.model}: {cage.triangles.shape[0]} "
          f"triangles, {x.shape[0]} points inside")  # fmt: skip
    m, mt = min(200, x.shape[0]), min(args.torch_points, x.shape[0])
    scale, scale_t = x.shape[0] / m, x.shape[0] / mt
    rows = []
    for order in (1, 2):
        t_mvc = _best(lambda o=order: F.mean_value_derivatives(x, cage, order=o), args.repeat)
        t_gc = _best(lambda o=order: F.green_derivatives(x, cage, order=o), args.repeat)
        t_gt = _best(lambda o=order: F.green_derivatives(x[:mt], cage, order=o, backend="torch"), 1) * scale_t
        t_ad = _best(lambda o=order: autograd_rows(x[:m], o, lambda y: green_flat(y, cage, backend="torch")), 1) * scale
        rows += [
            (order, "green_derivatives (closed form, native)", t_gc, t_mvc),
            (order, "green_derivatives (closed form, torch, scaled)", t_gt, t_mvc),
            (order, "mean_value_derivatives (native)", t_mvc, t_mvc),
            (order, "autograd of the Green torch kernel (scaled)", t_ad, t_mvc),
        ]
    print(f"{'order':>5} {'method':<48} {'seconds':>8} {'vs MVC':>7}")
    for order, name, t, ref in rows:
        print(f"{order:>5} {name:<48} {t:>8.2f} {t / ref:>6.1f}x")


if __name__ == "__main__":
    main()
