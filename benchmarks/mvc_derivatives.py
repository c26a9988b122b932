"""Benchmark of the analytic gradients and Hessians of mean value coordinates.

Two measurements, float64, all threads of this machine:

1. 10,000 points (the model's mesh vertices) and a cage of 300 triangles (Beast of the QMVC data
   set): torchcage's analytic kernel against automatic differentiation of the plain coordinate
   formula (``benchmarks/baseline.py: textbook_vector_form``) in the same run: forward mode
   (``torch.func.jvp``: one pass per direction and, nested, per pair of directions: 3 + 6 passes,
   the strongest baseline we know) and reverse-over-reverse (``vmap(hessian)`` over points). The
   AD baselines are timed on a subset of the points and scaled linearly. The
   accuracy column is the largest entry difference to torchcage's Hessians relative to their
   largest entry (the AD results lose digits near the faces' support planes).
2. Per point on an 8-vertex cage (the cube, 12 triangles), 100,000 points inside it; the issue's
   reference: a single-point C++ implementation measured at 150 us per point, target <= 3 us.

Usage: ``python benchmarks/mvc_derivatives.py [--data ../shared/data] [--points 10000] [--repeat 3]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from torch.func import hessian, jvp, vmap

import torchcage
from torchcage import functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))
from baseline import textbook_vector_form
from harness import add_data_argument, best_of, load_model, qmvc_root


def forward_mode(x: torch.Tensor, V: torch.Tensor, T: torch.Tensor, chunk: int = 500):
    """Gradients and Hessians by nested torch.func.jvp, one pass per direction / pair."""
    n, D = x.shape
    G = torch.empty(n, V.shape[0], D, dtype=x.dtype)
    H = torch.empty(n, V.shape[0], D, D, dtype=x.dtype)
    eye = torch.eye(D, dtype=x.dtype)

    def f(y):
        return textbook_vector_form(y, V, T)

    for s in range(0, n, chunk):
        xc = x[s : s + chunk]
        for c in range(D):
            dc = eye[c].expand_as(xc)
            G[s : s + chunk, :, c] = jvp(f, (xc,), (dc,))[1]
            for d in range(c, D):
                dd = eye[d].expand_as(xc)
                h = jvp(lambda y, dc=dc: jvp(f, (y,), (dc,))[1], (xc,), (dd,))[1]
                H[s : s + chunk, :, c, d] = h
                H[s : s + chunk, :, d, c] = h
    return G, H


def reverse_mode(x: torch.Tensor, V: torch.Tensor, T: torch.Tensor, chunk: int = 200):
    """Hessians by vmap(hessian) over points (jacfwd over jacrev per point)."""
    f1 = hessian(lambda y: textbook_vector_form(y[None], V, T)[0])
    return torch.cat([vmap(f1)(x[s : s + chunk]) for s in range(0, x.shape[0], chunk)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_data_argument(ap)
    ap.add_argument("--points", type=int, default=10000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--ad-points", type=int, default=1000, help="points timed for forward-mode AD (then scaled)")
    ap.add_argument("--rev-points", type=int, default=50, help="points timed for reverse-mode AD (then scaled)")
    args = ap.parse_args()
    qmvc_root(args.data)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, float64")
    x, quad_cage = load_model(args.data, "Beast")  # type: ignore[misc]
    cage, x = quad_cage.triangulated(), x[: args.points]
    V, T = cage.vertices.to(torch.float64), cage.triangles
    F.mean_value_derivatives(x[:8], cage)  # build the native library outside the timings
    _, t_ours, (_, G, H) = best_of(lambda: F.mean_value_derivatives(x, cage), args.repeat)
    _, t_grad, _ = best_of(lambda: F.mean_value_derivatives(x, cage, order=1), args.repeat)
    # AD costs grow linearly with the points: time a subset and scale to all points.
    xa, xr = x[: args.ad_points], x[: args.rev_points]
    _, t_fwd, (Gf, Hf) = best_of(lambda: forward_mode(xa, V, T), 1)
    t_fwd *= x.shape[0] / xa.shape[0]
    _, t_rev, Hr = best_of(lambda: reverse_mode(xr, V, T), 1)
    t_rev *= x.shape[0] / xr.shape[0]

    def rel(a, b):
        dims = tuple(range(1, a.ndim))
        return float(((a - b).abs().amax(dims) / b.abs().amax(dims)).max())

    print(f"\nBeast cage: {T.shape[0]} triangles, {V.shape[0]} vertices; {x.shape[0]} points; gradients + Hessians")
    head = f"{'method':<48} {'time':>8} {'vs torchcage':>13} {'max rel. diff. G / H':>22}"
    print(head + "\n" + "-" * len(head))
    rows = [
        ("torchcage analytic (gradients + Hessians)", t_ours, "-"),
        ("torchcage analytic (gradients only)", t_grad, "-"),
        (
            "AD forward mode, torch.func.jvp (3 + 6 passes)*",
            t_fwd,
            f"{rel(Gf, G[: xa.shape[0]]):.0e} / {rel(Hf, H[: xa.shape[0]]):.0e}",
        ),
        ("AD reverse, vmap(hessian) over points*", t_rev, f"- / {rel(Hr, H[: xr.shape[0]]):.0e}"),
    ]
    for name, t, acc in rows:
        print(f"{name:<48} {t:>7.2f}s {t / t_ours:>12.2f}x {acc:>22}")
    print(f"* timed on the first {xa.shape[0]} (forward) and {xr.shape[0]} (reverse) points, scaled to {x.shape[0]}")
    best = min(t_fwd, t_rev)
    print(f"best automatic differentiation / torchcage: {best / t_ours:.1f}x (target >= 5x)")

    cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
    g = torch.Generator().manual_seed(0)
    xc = (torch.rand(100_000, 3, generator=g, dtype=torch.float64) * 2 - 1) * 0.99
    _, t_cube, _ = best_of(lambda: F.mean_value_derivatives(xc, cube, chunk_size=100_000), args.repeat)
    per = t_cube / xc.shape[0] * 1e6
    print(f"\ncube (8 vertices, 12 triangles), {xc.shape[0]} points: {per:.2f} us per point "
          f"(gradients + Hessians); reference 150 us -> {150 / per:.0f}x faster (target >= 50x)")  # fmt: skip


if __name__ == "__main__":
    main()
