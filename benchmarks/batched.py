"""Benchmark of batched rest cages: one native call for the whole batch against a loop of
single-cage calls, mean value and Green coordinates forward (no graph, CPU), and forward and
backward (``mvc-grad``, ``gc-grad``: the gradients of a loss with respect to the points and the rest
cages, as a training step takes them), and quad mean value coordinates forward (``qmvc``: the
bundled bar's 14-quad cage, jittered per shape, n = 4), quad Green coordinates forward (``qgc``: the
same cages, n = 2) and the mean value derivatives (``mvcd``:
values, gradients and Hessians, ``order=2``); in 2D, mean value coordinates (``mvc2d``) and their
derivatives (``mvcd2d``) and Green coordinates (``gc2d``: the torch kernel, vectorised over the
batch) of 32-vertex polygons (jittered circles, per shape).

The setting of ``learnable.py`` (Neural Cages): B = 8 shapes, N = 5,000 points each, a 42-vertex /
80-triangle icosphere cage per shape (each jittered), points inside. *loop*: ``over_cage_batch``
calling ``F.mean_value_coordinates`` (``F.green_coordinates``) per element (per element its
tables, its checks and one native call); *batched*: the same function on the batched ``Cage`` (one
set of tables for the batch, one native call; with ``-grad``, one more for the backward pass).
*time*: the forward call, or for ``-grad`` the forward call and the backward pass. With
``--baseline REV`` (default ``HEAD``; ``none`` to skip), also the loop of the library at git
revision ``REV`` (exported to a temporary folder; what a batched cage
cost before this benchmark's revision, the single-cage path's own set-up included). Each call
builds the cage (``validate="topology"``, as a training step does), so the geometric check runs
every time. *kernel*: the time inside the native calls (the C function itself, argument checks
excluded); *set-up*: the rest, and its share of the total. Each tree runs in its own process, its
implementations interleaved, best of ``--repeat``; *speed-up* is against the first row of the
method and dtype.

Usage: ``python benchmarks/batched.py [--batch 8] [--points 5000] [--repeat 10] [--baseline REV]
[--methods mvc gc mvc-grad gc-grad qmvc qgc mvcd mvc2d mvcd2d gc2d]``
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
KERNEL = [0.0]


def _child(args: argparse.Namespace) -> None:
    """Time ``args.impl`` (comma-separated) of the torchcage on ``PYTHONPATH``; print JSON."""
    # (an editable install's import hook would serve modules of the checkout to a baseline tree)
    sys.meta_path[:] = [f for f in sys.meta_path if not type(f).__module__.startswith("__editable__")]
    import torch

    import torchcage
    from torchcage.functional import green_coordinates, mean_value_coordinates

    try:  # (the layout since the families' folders; a baseline revision may predate it)
        from torchcage._core.batch import over_cage_batch
        from torchcage.backends import native as _native
        from torchcage.backends.native import abi
    except ImportError:
        from torchcage._native import abi  # type: ignore[no-redef]
        from torchcage.functional._batch import over_cage_batch  # type: ignore[no-redef]

        from torchcage import _native  # type: ignore[no-redef]

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from learnable import problem

    def timed_call(lib, name: str, **arguments: object) -> None:  # _native.call, the C function timed
        arguments.setdefault("nthreads", torch.get_num_threads())
        c_args = abi.check_arguments(name, arguments)
        t = time.perf_counter()
        getattr(lib, name)(*c_args)
        KERNEL[0] += time.perf_counter() - t

    _native.call = timed_call  # every glue module calls it through the module attribute
    if args.method in ("qmvc", "qgc"):
        x, P, faces = quad_problem(args.batch, args.points, getattr(torch, args.dtype))
    elif args.method.endswith("2d"):
        x, P, faces = polygon_problem(args.batch, args.points, getattr(torch, args.dtype))
    else:
        x, P, faces, _ = problem(args.batch, args.points, getattr(torch, args.dtype), "cpu")
    green = args.method.startswith("gc")  # (gc, gc-grad, gc2d)
    fn = green_coordinates if green else mean_value_coordinates
    if args.method == "qmvc":
        fn = torchcage.functional.quad_mean_value_coordinates
    if args.method == "qgc":
        fn = torchcage.functional.quad_green_coordinates
    if args.method in ("mvcd", "mvcd2d"):  # values, gradients and Hessians

        def fn(x: torch.Tensor, cage: torchcage.Cage) -> tuple[torch.Tensor, ...]:
            return torchcage.functional.mean_value_derivatives(x, cage, order=2)  # type: ignore[return-value]

    width = P.shape[-2] + (len(faces) if green else 0)  # (Green: phi and psi, joined)
    cot = torch.randn(args.batch, args.points, width, generator=torch.Generator().manual_seed(1)).to(x.dtype)

    def joined(out: torch.Tensor | tuple[torch.Tensor, ...]) -> torch.Tensor:  # (Green's phi and psi, for the diff)
        if isinstance(out, torch.Tensor):
            return out
        if args.method in ("mvcd", "mvcd2d"):  # (values, gradients, Hessians: flattened)
            return torch.cat([o.reshape(-1) for o in out])
        return torch.cat(out, dim=-1)

    def call(batched: bool) -> torch.Tensor | tuple[torch.Tensor, ...]:
        if not args.method.endswith("-grad"):
            cage = torchcage.Cage(P, faces, validate="topology")
            return fn(x, cage) if batched else over_cage_batch(fn, x, cage)
        # a training step's part: the values and the gradients of a loss with respect to the
        # points and the rest cages (returned, joined, for the diff)
        xx, PP = x.clone().requires_grad_(), P.clone().requires_grad_()
        cage = torchcage.Cage(PP, faces, validate="topology")
        lam = joined(fn(xx, cage) if batched else over_cage_batch(fn, xx, cage))
        (lam * cot).sum().backward()
        assert xx.grad is not None and PP.grad is not None
        return torch.cat([xx.grad.reshape(-1), PP.grad.reshape(-1)])

    impls: dict[str, Callable[[], torch.Tensor | tuple[torch.Tensor, ...]]] = {
        "loop": lambda: call(False),
        "batched": lambda: call(True),
    }
    names = args.impl.split(",")
    best = {k: (float("inf"), 0.0) for k in names}
    with torch.no_grad() if not args.method.endswith("-grad") else contextlib.nullcontext():
        outs = {k: impls[k]() for k in names}  # (warm-up: lazy imports, the native library)
        for _ in range(args.repeat):
            for k in names:
                KERNEL[0] = 0.0
                t = time.perf_counter()
                impls[k]()
                dt = time.perf_counter() - t
                if dt < best[k][0]:
                    best[k] = (dt, KERNEL[0])
    ref = joined(outs[names[0]])
    diff = {k: float((joined(outs[k]) - ref).abs().max()) for k in names}
    print(json.dumps({"best": best, "diff": diff, "threads": torch.get_num_threads()}))


def quad_problem(B: int, N: int, dtype: Any) -> tuple[Any, Any, list[list[int]]]:
    """Quad mean value coordinates' problem: ``B`` jittered copies ``(B, 16, 3)`` of the bundled
    bar's 14-quad cage, ``N`` points inside each ``(B, N, 3)``, and the quads."""
    import torch

    import torchcage

    bar = torchcage.load_cage(torchcage.data.path("bar_cage.obj"))
    g = torch.Generator().manual_seed(0)
    V = bar.vertices.to(torch.float64)
    P = V * (1 + 0.1 * torch.rand(B, 1, 1, generator=g, dtype=torch.float64))
    P = P + 0.02 * torch.randn(B, *V.shape, generator=g, dtype=torch.float64)
    x = (torch.rand(B, N, 3, generator=g, dtype=torch.float64) - 0.5) * 1.6 * V.amax(0)
    return x.to(dtype), P.to(dtype), bar.quads.tolist()


def polygon_problem(B: int, N: int, dtype: Any) -> tuple[Any, Any, list[list[int]]]:
    """2D problem: ``B`` jittered 32-gons around the unit circle ``(B, 32, 2)``, ``N`` points
    inside each ``(B, N, 2)`` (within radius 0.8), and the edges."""
    import math

    import torch

    V = 32
    g = torch.Generator().manual_seed(0)
    angle = torch.arange(V, dtype=torch.float64) * (2 * math.pi / V)
    radius = 1 + 0.2 * torch.rand(B, V, generator=g, dtype=torch.float64)
    P = radius[..., None] * torch.stack([angle.cos(), angle.sin()], dim=-1)
    r = 0.8 * torch.rand(B, N, 1, generator=g, dtype=torch.float64).sqrt()
    a = 2 * math.pi * torch.rand(B, N, generator=g, dtype=torch.float64)
    x = r * torch.stack([a.cos(), a.sin()], dim=-1)
    return x.to(dtype), P.to(dtype), [[i, (i + 1) % V] for i in range(V)]


def _run(tree: Path, args: argparse.Namespace, dtype: str, impl: str, method: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    cmd = [sys.executable, __file__, "--child", "--impl", impl, "--dtype", dtype, "--method", method]
    cmd += ["--batch", str(args.batch), "--points", str(args.points), "--repeat", str(args.repeat)]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--points", type=int, default=5000)
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--baseline", default="HEAD", help="git revision whose loop is timed too ('none': skip)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--impl", default="loop,batched", help=argparse.SUPPRESS)
    ap.add_argument("--dtype", default="float32", help=argparse.SUPPRESS)
    methods = ["mvc", "gc", "mvc-grad", "gc-grad", "qmvc", "qgc", "mvcd", "mvc2d", "mvcd2d", "gc2d"]
    ap.add_argument("--method", default="mvc", choices=methods, help=argparse.SUPPRESS)
    ap.add_argument("--methods", nargs="+", default=methods, choices=methods)
    args = ap.parse_args()
    if args.child:
        _child(args)
        return
    with tempfile.TemporaryDirectory() as tmp:
        base = None
        if args.baseline != "none":
            rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", args.baseline], capture_output=True,
                                 text=True, check=True).stdout.strip()  # fmt: skip
            archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "torchcage"], capture_output=True,
                                     check=True).stdout  # fmt: skip
            subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
            base = (f"loop at {rev}", Path(tmp))
        rows = []
        for method in args.methods:
            for dtype in ("float32", "float64"):
                runs = []
                if base is not None:
                    r = _run(base[1], args, dtype, "loop", method)
                    runs.append((base[0], *r["best"]["loop"]))
                r = _run(ROOT, args, dtype, "loop,batched", method)
                runs += [("loop", *r["best"]["loop"]), ("batched", *r["best"]["batched"])]
                rows.append((f"{method} {dtype}", runs, r["diff"]["batched"], r["threads"]))
    print(
        f"B = {args.batch} cages x N = {args.points} points, 42-vertex / 80-triangle cages (qmvc, qgc: 16-vertex / "
        f"14-quad, n = 4 and 2; mvc2d, mvcd2d, gc2d: 32-gons), CPU, "
        f"{rows[0][3]} threads, best of {args.repeat}\n"
    )
    print("| method, dtype | path | time | kernel | set-up | set-up share | speed-up |")
    print("|---|---|---|---|---|---|---|")
    for dtype, runs, diff, _ in rows:
        first = runs[0][1]
        for name, total, kernel in runs:
            if kernel == 0:  # (a baseline revision whose native calls the timer does not see)
                print(f"| {dtype} | {name} | {total * 1e3:.1f} ms | - | - | - | {first / total:.2f}x |")
                continue
            setup = total - kernel
            print(
                f"| {dtype} | {name} | {total * 1e3:.1f} ms | {kernel * 1e3:.1f} ms | {setup * 1e3:.1f} ms | "
                f"{setup / total:.0%} | {first / total:.2f}x |"
            )
        print(f"| {dtype} | largest difference, batched - loop | {diff:.1e} | | | | |")


if __name__ == "__main__":
    main()
