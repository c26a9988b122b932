"""What Green coordinates' exterior continuation costs: ``exterior="extend"`` (the default) against
``exterior="none"`` (the bare integrals), on the QMVC data set's models.

Mesh vertices are the points (some lie outside the cages: Beast's 616 of 28,388), the cages
triangulated along ``q0-q2``. One thread, CPU time, best of ``--repeat`` rounds in which the two
calls alternate. *continuation* is the difference of the two, the time of
:func:`torchcage.families.green.exterior.extend_outside`; *per outside point* divides it by their
number.

Usage::

    python benchmarks/exterior.py [--models FireHydrant Beast] [--repeat 7] [--data ../shared/data]
"""

from __future__ import annotations

import functools
import os
import warnings

import torch
from harness import cpu_best, model_parser, present_models

import torchcage.functional as F
from torchcage.backends import native


def main() -> None:
    args = model_parser(__doc__, repeat=7).parse_args()
    torch.set_num_threads(1)
    os.environ["OMP_NUM_THREADS"] = "1"
    warnings.simplefilter("ignore")  # (points outside the cage: the continuation is what is timed)
    print(f"torch {torch.__version__}, float64, one thread, native library: {native.variant()}")
    print("| model | outside points | exterior='none' | exterior='extend' | continuation | per outside point |")
    print("|---|---|---|---|---|---|")
    for model, points, cage in present_models(args.data, args.models):
        tri = cage.triangulated()
        phi, _ = F.green_coordinates(points, tri, exterior="none")
        outside = int((phi.sum(dim=1) < 0.5).sum())
        del phi
        calls = [
            functools.partial(F.green_coordinates, points, tri, exterior="none"),
            functools.partial(F.green_coordinates, points, tri),
        ]
        for fn in calls:
            fn()  # (warm-up: tables, libraries)
        bare, extended = cpu_best(calls, args.repeat)
        cont = extended - bare
        per = f"{cont / outside * 1e6:,.1f} µs" if outside else "-"
        print(
            f"| {model} ({points.shape[0]:,} pts) | {outside:,} | {bare * 1e3:,.1f} ms | {extended * 1e3:,.1f} ms | "
            f"{cont * 1e3:,.1f} ms | {per} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
