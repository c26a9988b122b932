"""Benchmark of quad mean value coordinates (QMVC) on the data set of the QMVC paper.

For each model: the mesh vertices as points, the triquad cage; QMVC (native kernel, float64) for
n = 1, 2, 4, 8 and, as the baseline in the same run, mean value coordinates of the triangulated
cage (the cheapest alternative, which QMVC costs a multiple of); linear precision of each result.
The paper's targets on this machine (issue): FireHydrant n = 4 <= 2.0 s, Beast <= 4.0 s (a
single-thread C++ implementation measured here: 7.9 s and 16.3 s).

Usage: ``python benchmarks/qmvc.py [--data ../shared/data] [--models FireHydrant Beast] [--repeat 2]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import add_data_argument, best_of, load_model, qmvc_root

from torchcage import functional as F


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_data_argument(ap)
    ap.add_argument("--models", nargs="*", default=["FireHydrant", "Beast", "Ogre", "Bench"])
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    qmvc_root(args.data)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, float64, native kernel")
    head = f"{'model':<12} {'points':>7} {'quads':>5} {'tris':>4} | {'MVC tri.':>8} |"
    head += "".join(f" {'n=' + str(n):>7}" for n in (1, 2, 4, 8)) + " | lin. prec. (n=4)"
    print(head)
    print("-" * len(head))
    for model in args.models:
        x, cage = load_model(args.data, model)  # type: ignore[misc]
        F.quad_mean_value_coordinates(x[:8], cage)  # build the native library outside the timings
        _, t_mvc, _ = best_of(lambda x=x, c=cage: F.mean_value_coordinates(x, c.triangulated()), args.repeat)
        row = f"{model:<12} {x.shape[0]:>7} {cage.quads.shape[0]:>5} {cage.triangles.shape[0]:>4} | {t_mvc:>7.2f}s |"
        lin = float("nan")
        for n in (1, 2, 4, 8):
            _, t, w = best_of(lambda n=n, x=x, c=cage: F.quad_mean_value_coordinates(x, c, n), args.repeat)
            row += f" {t:>6.2f}s"
            if n == 4:
                lin = float((w @ cage.vertices.to(torch.float64) - x).abs().max()) / cage.scale
        print(row + f" | {lin:.1e}")


if __name__ == "__main__":
    main()
