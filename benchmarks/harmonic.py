"""Benchmark of harmonic coordinates and bounded biharmonic weights: meshing, assembly and solve on
a data-set cage, and the harmonic coordinates' convergence under mesh refinement.

Part 1: the FireHydrant cage (or ``--model``) meshed with about 20,000 vertices; the time to mesh,
then to assemble and solve with cholespy's sparse Cholesky, scipy's sparse LU (each factored once,
all cage vertices as right-hand sides) and torch's conjugate gradients, in the same run; the solve's
residual, partition of unity and linear precision at the mesh vertices, and the negative weights
(the discrete maximum principle on a Delaunay mesh of the interior).

Part 2: bounded biharmonic weights on the same mesh: the default solve (certified relative gap
1e-5), a tight one (1e-8), and, as the baseline in the same run, the same ADMM with the penalty
``rho = diag Q`` (the usual Jacobi choice) for as many iterations as the default took: its
certified gap. Times include assembly, both factorisations and the penalty estimate; add the
meshing time for setup + solve.

Part 3: a convex pentagon and the cube, meshed ever finer: the RMS and max change of the
coordinates at fixed inside points between successive meshes (P1 elements: ``h^2``, a factor 4 per
4x the cells in 2D).

Usage: ``python benchmarks/harmonic.py [--data ../shared/data] [--model FireHydrant] [--cells 80000]``
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import add_data_argument, qmvc_root

import torchcage
from torchcage import functional as F
from torchcage.geometry import inside_cage
from torchcage.solvers.biharmonic import solve_bbw
from torchcage.solvers.domain import mesh_domain
from torchcage.solvers.harmonic import solve_harmonic


def _inside(cage: torchcage.Cage, n: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    v = cage.vertices.to(torch.float64)
    lo, hi = v.min(0).values, v.max(0).values
    x = lo + (hi - lo) * torch.rand(8 * n, cage.dim, generator=g, dtype=torch.float64)
    return x[inside_cage(x, cage)][:n]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_data_argument(ap)
    ap.add_argument("--model", default="FireHydrant")
    ap.add_argument("--cells", type=int, default=80000, help="target cells of the data-set mesh")
    args = ap.parse_args()
    cage = torchcage.load_cage(qmvc_root(args.data) / f"{args.model}_Cage.obj").to(torch.float64)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, float64")
    t0 = time.perf_counter()
    dom = mesh_domain(cage, args.cells)
    t_mesh = time.perf_counter() - t0
    print(f"{args.model}: {dom.vertices.shape[0]} mesh vertices, {dom.cells.shape[0]} cells, meshed in {t_mesh:.2f} s")
    head = f"{'solver':<6} {'solve s':>8} {'total s':>8} {'residual':>9} {'PU':>8} {'LP':>8} {'min w':>9} {'neg.':>6}"
    print(head)
    print("-" * len(head))
    for solver in ("cholesky", "lu", "cg"):
        r = solve_harmonic(dom, solver)
        W = r.weights
        pu = float((W.sum(1) - 1).abs().max())
        lp = float((W @ cage.vertices - dom.vertices).abs().max() / cage.scale)
        print(
            f"{solver:<6} {r.seconds:>8.2f} {t_mesh + r.seconds:>8.2f} {r.residual:>9.1e} {pu:>8.1e} {lp:>8.1e} "
            f"{r.min_weight:>9.2e} {r.negative_vertices:>6d}"
        )
    m, V = dom.interior.shape[0], cage.num_vertices
    print(f"\nbounded biharmonic weights ({m} interior vertices x {V} cage vertices)")
    cols = ("solve", "iterations", "largest gap", "solve s", "setup+solve s", "sum defect")
    head = f"{cols[0]:<22} " + " ".join(f"{c:>{w}}" for c, w in zip(cols[1:], (10, 12, 8, 14, 10), strict=True))
    print(head)
    print("-" * len(head))
    runs = {"default (tol 1e-5)": {}, "tight (tol 1e-8)": {"tol": 1e-8}}
    for name, opts in runs.items():
        r = solve_bbw(dom, **opts)
        print(
            f"{name:<22} {r.iterations:>10d} {float(r.gap.max()):>12.1e} {r.seconds:>8.2f} "
            f"{t_mesh + r.seconds:>14.2f} {r.partition_defect:>10.2f}"
        )
        if name.startswith("default"):
            base_iters = r.iterations
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # (the baseline does not converge: that is the point)
        r = solve_bbw(dom, rho=1.0, max_iter=base_iters, check_every=base_iters)
    line = f"{'baseline rho = diag Q':<22} {r.iterations:>10d} {float(r.gap.max()):>12.1e} {r.seconds:>8.2f}"
    print(line + "  (no solve stops early: one check at the end)")
    print("\nconvergence under refinement (change at fixed inside points between successive meshes)")
    cases = {
        "pentagon": (torchcage.Cage(torch.tensor([[0.0, 0], [2, 0], [2, 1], [1, 1.5], [0, 1]], dtype=torch.float64)),
                     (250, 1000, 4000, 16000, 64000)),
        "cube": (torchcage.load_cage(torchcage.data.path("cube.obj")).to(torch.float64), (1000, 4000, 16000, 64000)),
    }  # fmt: skip
    for name, (c, sizes) in cases.items():
        x = _inside(c, 300)
        prev = None
        for n in sizes:
            sol = F.solve_harmonic_coordinates(c, target_cells=n)
            w = F.harmonic_coordinates(x, c, solution=sol)
            if prev is not None:
                d = w - prev
                print(
                    f"  {name:<9} cells {n:>6} (vertices {sol.domain.vertices.shape[0]:>6}): "
                    f"RMS change {float(d.square().mean().sqrt()):.2e}, max {float(d.abs().max()):.2e}, "
                    f"min weight {sol.min_weight:.1e}"
                )
            prev = w


if __name__ == "__main__":
    main()
