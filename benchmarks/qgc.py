"""Benchmark of Green coordinates for triquad cages (QGC) on the data set of the QMVC paper.

For each model (mesh vertices as points, triquad cage; native kernels, float64): Green coordinates
on the triangulated cage (GC) and quad mean value coordinates (QMVC, n = 4) as baselines in the same
run, then QGC for the requested n, with its cost relative to QMVC (the issue's target: at most 3x)
and the linear precision of the result on the points inside the cage (sum(phi) = 1).

The timings are the best of ``--repeat`` rounds, each round timing every column once in turn, so
that a slow spell of this shared machine does not fall on one column only.

Usage: ``python benchmarks/qgc.py [--data ../shared/data] [--models FireHydrant Beast] [--n 1 2] [--repeat 3]``
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import add_data_argument, best_of, load_model, qmvc_root

from torchcage import functional as F


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_data_argument(ap)
    ap.add_argument("--models", nargs="*", default=["FireHydrant", "Beast"])
    ap.add_argument("--n", nargs="*", type=int, default=[1, 2])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    qmvc_root(args.data)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, float64, native kernels")
    head = f"{'model':<12} {'points':>7} | {'GC tri.':>7} {'QMVC n=4':>8} |"
    head += "".join(f" {'QGC n=' + str(n):>9} {'/QMVC':>6}" for n in args.n) + " | lin. prec."
    print(head)
    print("-" * len(head))
    for model in args.models:
        x, cage = load_model(args.data, model)  # type: ignore[misc]
        F.quad_green_coordinates(x[:8], cage)  # build the native library outside the timings
        tri = cage.triangulated()
        jobs = {
            "gc": functools.partial(F.green_coordinates, x, tri),
            "qmvc": functools.partial(F.quad_mean_value_coordinates, x, cage),
        }
        jobs.update({n: functools.partial(F.quad_green_coordinates, x, cage, n) for n in args.n})
        best, out = {}, {}
        for key, fn in jobs.items():
            _, best[key], out[key] = best_of(fn, args.repeat)
        t_q = best["qmvc"]
        row = f"{model:<12} {x.shape[0]:>7} | {best['gc']:>6.2f}s {t_q:>7.2f}s |"
        lin = 0.0
        N = torch.cat(
            [
                cage.triangle_normals()[: cage.triangles.shape[0]].to(torch.float64),
                cage.quad_corner_normals().reshape(-1, 3),
            ]
        )
        for n in args.n:
            phi, psi = out[n]
            row += f" {best[n]:>8.2f}s {best[n] / t_q:>5.1f}x"
            inside = (phi.sum(1) - 1).abs() < 1e-6
            err = (phi @ cage.vertices.to(torch.float64) + psi @ N - x)[inside].abs().max() / cage.scale
            lin = max(lin, float(err))
        print(row + f" | {lin:.1e}")


if __name__ == "__main__":
    main()
