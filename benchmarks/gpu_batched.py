"""GPU benchmark of batched rest cages: mean value coordinates of B cages with one topology as one
Triton launch, against the loop of single-cage calls and the dense batched torch formula; Green
coordinates (the exterior continued), 2D mean value coordinates of 32-gons and their gradients and
Hessians, the 3D gradients and Hessians, and quad mean value coordinates (the bundled bar's 14-quad
cage) likewise, batched launch against the loop.

The setting of ``learnable.py`` / ``batched.py`` (Neural Cages): B = 8 shapes, N = 5,000 points each,
a jittered 42-vertex / 80-triangle icosphere cage per shape, float32 inputs, on CUDA. Rows:

* *loop*: ``over_cage_batch`` calling ``F.mean_value_coordinates`` per element (what a batched cage
  cost before: one set of tables and one launch per cage);
* *batched*: ``F.mean_value_coordinates`` on the batched ``Cage`` (one set of tables for the batch,
  one Triton launch);
* *dense*: ``baseline.dense_batched_mean_value_coordinates`` (the half-angle formula on every
  (shape, point, face) triple at once, plain torch).

Each torchcage path twice: the default compute (float64, results cast to float32) and
``backend="triton", dtype=torch.float32`` (float32 compute). Each call builds the cage
(``validate="topology"``, as a training step does). The table gives the best of ``--repeat`` (after
a warm-up call that compiles the kernels), the speed-up against the loop, and the largest
difference from the float64 batched result. *forward+backward (graph)*: the learnable path (points
and rest cages require grad; a loss's backward), which is still one call per cage (no batched
backward yet), against the dense formula under autograd.

Single command, under a minute on an H200 (the kernels' first compilation included)::

    python benchmarks/gpu_batched.py [--batch 8] [--points 5000] [--repeat 5]

Without a CUDA device (or without triton) it prints why and exits 0.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from pathlib import Path

import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--points", type=int, default=5000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--interpret", action="store_true", help="a tiny smoke run on the CPU by Triton's interpreter")
    args = ap.parse_args()
    device = "cuda"
    if args.interpret:  # (no timing meaning: it checks that the script runs)
        os.environ["TRITON_INTERPRET"] = "1"
        device, args.batch, args.points, args.repeat = "cpu", 2, 40, 1
    elif not torch.cuda.is_available():
        print("gpu_batched.py: no CUDA device here; nothing to measure (run it on a machine with a GPU)")
        return
    try:
        import triton  # noqa: F401
    except ImportError:
        print("gpu_batched.py: triton is not installed (pip install torchcage[triton]); nothing to measure")
        return

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from baseline import dense_batched_mean_value_coordinates
    from learnable import problem

    import torchcage
    from torchcage import functional as F
    from torchcage._core.batch import over_cage_batch
    from torchcage._timing import best_of

    x, P, faces, _ = problem(args.batch, args.points, torch.float32, device)
    f64 = {"backend": "triton"}  # (what "auto" takes on CUDA; said, so that --interpret runs it too)
    f32 = {"backend": "triton", "dtype": torch.float32}

    def cage(PP: torch.Tensor) -> torchcage.Cage:
        return torchcage.Cage(PP, faces, validate="topology")

    forward: dict[str, Callable[[], torch.Tensor]] = {
        "loop (float64 compute)": lambda: over_cage_batch(F.mean_value_coordinates, x, cage(P), **f64),
        "batched (float64 compute)": lambda: F.mean_value_coordinates(x, cage(P), **f64),
        "loop (float32 compute)": lambda: over_cage_batch(F.mean_value_coordinates, x, cage(P), **f32),
        "batched (float32 compute)": lambda: F.mean_value_coordinates(x, cage(P), **f32),
        "dense torch formula": lambda: dense_batched_mean_value_coordinates(x, P, faces),
    }

    def timed(fn: Callable[[], torch.Tensor]) -> tuple[float, torch.Tensor]:
        def run() -> torch.Tensor:
            out = fn()
            if device == "cuda":
                torch.cuda.synchronize()
            return out

        run()  # warm-up: compiles the kernels (cached by Triton across runs)
        _, best, out = best_of(run, repeat=args.repeat)
        return best, out

    print(
        f"B = {args.batch} cages x N = {args.points} points, 42-vertex / 80-triangle cages (2D: 32-gons), "
        "float32 inputs, "
        f"{torch.cuda.get_device_name() if device == 'cuda' else 'CPU (interpreter)'}, best of {args.repeat}\n"
    )
    with torch.no_grad():
        results = {k: timed(fn) for k, fn in forward.items()}
    ref = results["batched (float64 compute)"][1].double()
    _table("forward", results, ref, ("loop (float64 compute)", "loop (float32 compute)"))

    def green(batched: bool) -> Callable[[], torch.Tensor]:
        def run() -> torch.Tensor:
            c = cage(P)
            phi, psi = (
                F.green_coordinates(x, c, **f64) if batched else over_cage_batch(F.green_coordinates, x, c, **f64)
            )
            return torch.cat([phi, psi], dim=-1)

        return run

    with torch.no_grad():
        results = {"loop (float64 compute)": timed(green(False)), "batched (float64 compute)": timed(green(True))}
    print()
    _table("Green forward", results, results["batched (float64 compute)"][1].double(), ("loop (float64 compute)",))

    from batched import polygon_problem

    x2, P2, edges = polygon_problem(args.batch, args.points, torch.float32)
    x2, P2, edges = x2.to(device), P2.to(device), torch.tensor(edges, device=device)
    polygons = torchcage.Cage(P2, edges)
    with torch.no_grad():
        results = {
            "loop (float64 compute)": timed(lambda: over_cage_batch(F.mean_value_coordinates, x2, polygons, **f64)),
            "batched (float64 compute)": timed(lambda: F.mean_value_coordinates(x2, polygons, **f64)),
        }
    print()
    ref2 = results["batched (float64 compute)"][1].double()
    _table("2D forward (32-gons)", results, ref2, ("loop (float64 compute)",))

    def derivatives(batched: bool, xx: torch.Tensor, cages: torchcage.Cage) -> Callable[[], torch.Tensor]:
        def run() -> torch.Tensor:
            fn = F.mean_value_derivatives
            call = fn if batched else lambda *a, **k: over_cage_batch(fn, *a, **k)
            lam, grad, hess = call(xx, cages, order=2, **f64)
            return torch.cat([lam[..., None], grad, hess.flatten(-2)], dim=-1).flatten(-2)

        return run

    results = {
        "loop (float64 compute)": timed(derivatives(False, x2, polygons)),
        "batched (float64 compute)": timed(derivatives(True, x2, polygons)),
    }
    print()
    ref3 = results["batched (float64 compute)"][1].double()
    _table("2D derivatives, order 2 (32-gons)", results, ref3, ("loop (float64 compute)",))
    results = {
        "loop (float64 compute)": timed(derivatives(False, x, cage(P))),
        "batched (float64 compute)": timed(derivatives(True, x, cage(P))),
    }
    print()
    ref3 = results["batched (float64 compute)"][1].double()
    _table("3D derivatives, order 2", results, ref3, ("loop (float64 compute)",))

    from batched import quad_problem

    xq, Pq, quad_faces = quad_problem(args.batch, args.points, torch.float32)
    quad_cages = torchcage.Cage(Pq.to(device), quad_faces)
    xq, opts = xq.to(device), {"n": 4, **f64}
    with torch.no_grad():
        results = {
            "loop (float64 compute)": timed(
                lambda: over_cage_batch(F.quad_mean_value_coordinates, xq, quad_cages, **opts)
            ),
            "batched (float64 compute)": timed(lambda: F.quad_mean_value_coordinates(xq, quad_cages, **opts)),
        }
    print()
    ref4 = results["batched (float64 compute)"][1].double()
    _table("quad mean value forward (bar cage, 14 quads, n = 4)", results, ref4, ("loop (float64 compute)",))

    cot = torch.randn(args.batch, args.points, 42, generator=torch.Generator().manual_seed(1)).to(device)

    def backward(coords: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]) -> Callable[[], torch.Tensor]:
        def run() -> torch.Tensor:
            xx, PP = x.clone().requires_grad_(), P.clone().requires_grad_()
            out = coords(xx, PP)
            (out * cot).sum().backward()
            return out.detach()

        return run

    graph = {
        "torchcage (one call per cage)": backward(lambda xx, PP: F.mean_value_coordinates(xx, cage(PP))),
        "dense torch formula": backward(lambda xx, PP: dense_batched_mean_value_coordinates(xx, PP, faces)),
    }
    results = {k: timed(fn) for k, fn in graph.items()}
    print()
    _table("forward+backward (graph)", results, ref, ("torchcage (one call per cage)",))


def _table(
    task: str, results: dict[str, tuple[float, torch.Tensor]], ref: torch.Tensor, bases: tuple[str, ...]
) -> None:
    """Print the rows; each speed-up is against the loop of the same compute dtype (the first base
    for rows without one)."""
    print(f"| {task} | time | speed-up | max diff to batched float64 |")
    print("|---|---|---|---|")
    for name, (t, out) in results.items():
        base = next((b for b in bases if b.split(" ", 1)[1] == name.split(" ", 1)[1]), bases[0])
        diff = float((out.double() - ref).abs().max())
        print(f"| {name} | {t * 1e3:.2f} ms | {results[base][0] / t:.2f}x | {diff:.1e} |")


if __name__ == "__main__":
    main()
