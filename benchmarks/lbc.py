"""Benchmark of local barycentric coordinates (LBC): meshing, the ADMM solve, and deformation with
the sparse weights against the dense mean value product.

Rows of the solve table: torchcage's defaults (automatic penalty scale, balanced W constraint,
gentle residual balancing), and in the same run the baseline the paper prescribes (fixed penalty
mu = 10 on the unit-diagonal scene, the W constraint unweighted), capped at ``--baseline-iters``
iterations. ``objective`` is the weighted total variation of the result (lower is better; both
results satisfy the constraints exactly).

Usage: ``python benchmarks/lbc.py [--data ../shared/data] [--large 60000] [--skip-large]``
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import best_of

import torchcage
from torchcage import functional as F
from torchcage.solvers.domain import mesh_domain
from torchcage.solvers.lbc import solve_lbc


def polygon(path: Path) -> torchcage.Cage:
    v = [[float(t) for t in line.split()[1:3]] for line in open(path) if line.startswith("v ")]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torchcage.Cage(torch.tensor(v, dtype=torch.float64))


def solve_row(name: str, cage: torchcage.Cage, cells: int, baseline_iters: int) -> None:
    t_mesh, _, d = best_of(lambda: mesh_domain(cage, cells), 1)
    t_solve, _, r = best_of(lambda: solve_lbc(d, cage.vertices), 1)
    conv = "yes" if r.converged else "no"
    print(f"{name:<16}{d.vertices.shape[0]:>7}{d.cells.shape[0]:>7} | {'torchcage':<14}{t_mesh:>7.2f}"
          f"{t_solve:>8.2f}{t_mesh + t_solve:>8.2f}{r.iterations:>7}{conv:>5}{r.objective:>12.5g}")  # fmt: skip
    if baseline_iters:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t_b, _, b = best_of(
                lambda: solve_lbc(d, cage.vertices, mu=10.0, adaptive=False, w_scale=0.0, max_iter=baseline_iters), 1
            )
        print(f"{'':<16}{'':>7}{'':>7} | {'paper, mu=10':<14}{t_mesh:>7.2f}{t_b:>8.2f}{t_mesh + t_b:>8.2f}"
              f"{b.iterations:>7}{'yes' if b.converged else 'no':>5}{b.objective:>12.5g}")  # fmt: skip


def deformation_rows(data: Path, repeat: int = 5) -> None:
    path = data / "qmvc" / "FireHydrant_Cage.obj"
    if not path.exists():
        print(f"(FireHydrant absent from {data}/qmvc: deformation rows skipped)")
        return
    cage = torchcage.load_cage(path)
    pts, _ = torchcage.load_mesh(data / "qmvc" / "FireHydrant.obj")
    pts = pts.to(torch.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t_lbc, _, lbc = best_of(lambda: torchcage.LocalBarycentricCoordinates(cage, pts, target_cells=6000), 1)
    t_mvc, _, mvc = best_of(lambda: torchcage.MeanValueCoordinates(cage.triangulated(), pts), 1)
    print(f"\nDeformation, FireHydrant: {pts.shape[0]} points, {cage.num_vertices} cage vertices "
          f"(coordinates: LBC {t_lbc:.1f} s, MVC {t_mvc:.2f} s)")  # fmt: skip
    nnz = lbc.weight_values.numel()
    mem_lbc = nnz * (8 + 4) + (pts.shape[0] + 1) * 4
    mem_mvc = mvc.weights.numel() * 8
    print(f"{'weights':<22}{'entries':>10}{'MB':>8} | {'1 pose ms':>10}{'16 poses ms':>12}")
    gen = torch.Generator().manual_seed(0)
    for name, module, entries, mem in (
        ("LBC (sparse CSR)", lbc, nnz, mem_lbc),
        ("MVC (dense)", mvc, mvc.weights.numel(), mem_mvc),
    ):
        times = []
        for batch in (1, 16):
            v = cage.vertices + 0.01 * torch.randn((batch, *cage.vertices.shape), dtype=torch.float64, generator=gen)
            times.append(best_of(lambda module=module, v=v: module(v), repeat, warmup=1)[1])
        print(f"{name:<22}{entries:>10}{mem / 2**20:>8.2f} | {1000 * times[0]:>10.2f}{1000 * times[1]:>12.2f}")
    _, P, Q = F.locality_statistics(lbc.weights)
    _, Pm, Qm = F.locality_statistics(mvc.weights)
    V = cage.num_vertices
    med_lbc = int((lbc.weights.to_dense() > 1e-3 / V).sum(1).median())
    med_mvc = int((mvc.weights.abs() > 1e-3 / V).sum(1).median())
    print(f"locality over the points: median influencing vertices (> 1e-3/V): LBC {med_lbc}, MVC {med_mvc}; "
          f"Q(10) = {float(Q[10]):.3f} (LBC) vs {float(Qm[10]):.3f} (MVC); P(1e-3) = "
          f"{float(P[torch.searchsorted(torch.logspace(-6, 0, 50), torch.tensor(1e-3))]):.3f} vs "
          f"{float(Pm[torch.searchsorted(torch.logspace(-6, 0, 50), torch.tensor(1e-3))]):.3f}")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--baseline-iters", type=int, default=3000)
    ap.add_argument("--large", type=int, default=60000, help="target cells of the large 3D case")
    ap.add_argument("--skip-large", action="store_true")
    args = ap.parse_args()
    data = Path(args.data)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, float64\n")
    header = (f"{'cage':<16}{'verts':>7}{'cells':>7} | {'solver':<14}{'mesh s':>7}{'solve s':>8}{'total s':>8}"
              f"{'iters':>7}{'conv':>5}{'objective':>12}")  # fmt: skip
    print(header)
    print("-" * len(header))
    cactus = data / "lbc2d" / "cactus-control-edgeset.obj"
    if cactus.exists():
        solve_row("cactus (2D, 27)", polygon(cactus), 3000, args.baseline_iters)
    cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
    solve_row("cube (3D, 8)", cube, 2400, args.baseline_iters)
    fh = data / "qmvc" / "FireHydrant_Cage.obj"
    if fh.exists():
        solve_row("FireHydrant (48)", torchcage.load_cage(fh), 3000, args.baseline_iters)
        if not args.skip_large:
            solve_row("FireHydrant (48)", torchcage.load_cage(fh), args.large, 0)
    print("\nverts: mesh vertices; total: meshing + solve; objective: weighted total variation (lower is better).")
    deformation_rows(data)


if __name__ == "__main__":
    main()
