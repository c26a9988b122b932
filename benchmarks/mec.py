"""Benchmark of maximum entropy coordinates on the data set of the QMVC paper.

For each model: the mesh vertices inside the cage as points (a model without a mesh samples its
cage), the triquad cage, and maximum entropy coordinates with the QMVC prior (n = 4) and the
uniform prior. Prints the time of the prior (QMVC, the baseline in the same run) and of the
Newton solve, the distribution of Newton steps (median, 99th percentile, maximum, points not
converged), how many points had a negative prior weight, and the worst partition of unity, linear
precision (over the size) and smallest weight.

Usage: ``python benchmarks/mec.py [--data ../shared/data] [--models FireHydrant Beast] [--limit 20000]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import MODELS, add_data_argument, qmvc_root

import torchcage
from torchcage import functional as F
from torchcage.geometry import inside_cage


def _points(data: str, model: str, limit: int) -> tuple[torch.Tensor, torchcage.Cage]:
    root = qmvc_root(data)
    cage = torchcage.load_cage(root / f"{model}_Cage.obj").to(torch.float64)
    mesh = root / f"{model}.obj"
    if mesh.exists():
        x = torchcage.load_mesh(mesh)[0].to(torch.float64)
    else:  # (Cactus: no mesh in the data set)
        g = torch.Generator().manual_seed(0)
        lo, hi = cage.vertices.min(0).values, cage.vertices.max(0).values
        x = lo + (hi - lo) * torch.rand(4 * (limit or 25000), 3, generator=g, dtype=torch.float64)
    x = x[inside_cage(x, cage)]
    return (x[:limit] if limit else x[:25000] if not mesh.exists() else x), cage


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_data_argument(ap)
    ap.add_argument("--models", nargs="*", default=MODELS)
    ap.add_argument("--limit", type=int, default=0, help="at most this many points per model (0: all)")
    args = ap.parse_args()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, float64")
    head = (
        f"{'model':<12} {'prior':<8} {'points':>7} {'neg.':>6} | {'QMVC s':>7} {'MEC s':>7} | "
        f"{'steps med':>9} {'p99':>4} {'max':>4} {'unconv':>6} | {'PU':>8} {'LP':>8} {'min w':>9}"
    )
    print(head)
    print("-" * len(head))
    for model in args.models:
        x, cage = _points(args.data, model, args.limit)
        t0 = time.perf_counter()
        q = F.quad_mean_value_coordinates(x, cage)
        t_prior = time.perf_counter() - t0
        neg = int((q.min(dim=1).values < 0).sum())
        for prior in ("qmvc", "uniform"):
            t0 = time.perf_counter()
            r = F.maximum_entropy_coordinates(x, cage, prior=q if prior == "qmvc" else "uniform", return_info=True)
            t_mec = time.perf_counter() - t0
            w = r.weights
            it = r.iterations.double()
            pu = float((w.sum(1) - 1).abs().max())
            lp = float((w @ cage.vertices - x).norm(dim=1).max() / cage.scale)
            print(
                f"{model:<12} {prior:<8} {x.shape[0]:>7} {neg:>6} | {t_prior:>7.2f} {t_mec:>7.2f} | "
                f"{float(it.median()):>9.0f} {float(it.quantile(0.99)):>4.0f} {int(it.max()):>4d} "
                f"{int((~r.converged).sum()):>6d} | {pu:>8.1e} {lp:>8.1e} {float(w.min()):>9.1e}",
                flush=True,
            )


if __name__ == "__main__":
    main()
