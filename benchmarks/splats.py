"""Splat benchmark: deforming 10^6 Gaussians per pose, and the inverse mapping per 10^5 samples.

Rows (one process, the bundled bar and its cage, float64):

- ``DeformGaussians`` set-up (coordinates and gradients at the centres) and one pose (centres,
  covariances, log-scales and rotations, degree-3 colours; the faster of two calls), mean value and
  Green coordinates, on ``--gaussians`` Gaussians (default 10^6): time and the peak resident memory
  above the start;
- the baseline a user would write without it, in the same run: the Jacobians by autograd
  (``torch.func.vmap(torch.func.jacrev(...))`` of the mean value map at the centres, per pose) on
  ``--baseline`` Gaussians (default 10^4), scaled per 10^6;
- ``rest_points`` on ``--samples`` deformed-space samples (default 10^5) inside the bent cage:
  time, the Newton iterations (median and largest) and the largest residual.

Usage::

    python benchmarks/splats.py [--gaussians 1000000] [--baseline 10000] [--samples 100000]
"""

from __future__ import annotations

import argparse
import sys
import time

import torch
from harness import peak_since, reset_peak

import torchcage
from torchcage import functional as F
from torchcage.geometry import inside_cage
from torchcage.splats import DeformGaussians, GaussianScene, rest_points

D64 = torch.float64


def _row(name: str, n: int, seconds: float, peak: float | str, note: str = "") -> None:
    per = seconds / n * 1e6
    peak_s = f"{peak:9.0f}" if isinstance(peak, float) else f"{peak:>9s}"
    print(f"{name:44s} {n:>10,d} {seconds:9.2f} {per:12.2f} {peak_s} {note}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaussians", type=int, default=10**6)
    ap.add_argument("--baseline", type=int, default=10**4)
    ap.add_argument("--samples", type=int, default=10**5)
    args = ap.parse_args(argv)
    cage = torchcage.load_cage(torchcage.data.path("bar_cage.obj"))
    pose = torchcage.load_cage(torchcage.data.path("bar_cage_deformed.obj")).vertices
    box = (-0.4, 0.4)
    scene = GaussianScene.random(args.gaussians, degree=3, box=box, dtype=D64)
    scene.means[:, 2] *= 3.5  # along the bar
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; bar cage (16 vertices, 28 triangles)")
    print(f"{'step':44s} {'count':>10s} {'seconds':>9s} {'s per 10^6':>12s} {'peak MB':>9s}")
    for method in ("mvc", "gc"):
        before = reset_peak()
        t0 = time.perf_counter()
        deform = DeformGaussians(cage, scene, method=method)
        t1 = time.perf_counter()
        _row(f"{method}: set-up (coordinates, gradients)", args.gaussians, t1 - t0, peak_since(before))
        times = []
        for _ in range(2):  # the first call also warms up (allocations, library initialisation)
            before = reset_peak()
            t1 = time.perf_counter()
            out = deform(pose)
            times.append(time.perf_counter() - t1)
            peak = peak_since(before)
            del out
        _row(f"{method}: one pose (all outputs)", args.gaussians, min(times), peak, f"(first call {times[0]:.2f} s)")
        del deform
    # baseline: autograd Jacobians of the mean value map, per pose
    tri = cage.triangulated()
    x = scene.means[: args.baseline]

    def mapped(p: torch.Tensor) -> torch.Tensor:
        return F.mean_value_coordinates(p[None], tri, backend="torch")[0] @ pose

    before = reset_peak()
    t0 = time.perf_counter()
    J = torch.func.vmap(torch.func.jacrev(mapped))(x)
    t1 = time.perf_counter()
    fields = ("means", "log_scales", "rotations", "opacity_logits", "sh")
    ref = DeformGaussians(cage, scene.replace(**{k: getattr(scene, k)[: args.baseline] for k in fields}))(pose)
    err = float((ref.jacobians - J).abs().max())
    _row("baseline: autograd Jacobians only (mvc)", args.baseline, t1 - t0, peak_since(before), f"(|dJ| {err:.1e})")
    # inverse mapping
    lo, hi = pose.amin(0), pose.amax(0)
    g = torch.Generator().manual_seed(0)
    y = lo + (hi - lo) * torch.rand(4 * args.samples, 3, generator=g, dtype=D64)
    y = y[inside_cage(y, torchcage.Cage(pose, cage.faces, validate=False))][: args.samples]
    before = reset_peak()
    t0 = time.perf_counter()
    res = rest_points(y, cage, pose, warn=False)
    t1 = time.perf_counter()
    it = res.iterations.double()
    note = (
        f"(iterations median {float(it.median()):.0f}, max {int(it.max())}; residual max "
        f"{float(res.residual.max()):.1e} of the size; {int((~res.converged).sum())} unconverged)"
    )
    _row("rest_points (mvc), samples inside the bent cage", y.shape[0], t1 - t0, peak_since(before), note)
    return 0


if __name__ == "__main__":
    sys.exit(main())
