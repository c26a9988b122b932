"""Benchmark runner: mean value coordinates on the QMVC data set, against a naive baseline.

Prints one table: for each model, the mesh vertices as points and the triangulated cage; the first
call (in a fresh process), the best of ``--repeat`` calls, points per second and peak memory, for
torchcage's default (native) and torch backends and for the naive eager baseline, each measured in
its own child process in the same run. ``--large N`` also measures peak memory for N
random points (10 million by default off) to show that it is bounded by the chunk size.

Usage:
    python benchmarks/run.py [--data ../shared/data] [--repeat 5] [--large 10000000]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from baseline import naive_mean_value_coordinates
from harness import MODELS, add_data_argument, best_of, load_model, peak_mb, rss_mb, run_in_child

import torchcage
from torchcage import functional as F


def load(data: str, model: str) -> tuple[torch.Tensor, torchcage.Cage] | None:
    """A model's mesh vertices and its triangulated cage, or ``None`` if absent."""
    loaded = load_model(data, model)
    return None if loaded is None else (loaded[0], loaded[1].triangulated())


def run_one(data: str, model: str, backend: str, repeat: int) -> dict:
    """Measure one (model, backend) in this process; meant to run in a fresh child process so that
    the peak resident memory (``ru_maxrss``) belongs to this measurement alone."""
    x, cage = load(data, model)  # type: ignore[misc]
    if backend == "naive":

        def fn() -> torch.Tensor:
            return naive_mean_value_coordinates(x, cage.vertices, cage.triangles)
    elif backend == "gc":

        def fn() -> tuple[torch.Tensor, torch.Tensor]:
            return F.green_coordinates(x, cage)
    else:

        def fn() -> torch.Tensor:
            return F.mean_value_coordinates(x, cage, backend=backend)

    base = rss_mb()
    first, _, w = best_of(fn, 1)
    peak = peak_mb() - base
    if backend == "gc":  # Green coordinates hold inside only: measure there (sum of phi = 1)
        phi, psi = w
        inside = (phi.sum(1) - 1).abs() < 1e-6
        fit = phi[inside] @ cage.vertices + psi[inside] @ cage.triangle_normals()
        err = (fit - x[inside]).abs().max().item() / cage.scale
        del phi, psi
    else:
        err = (w @ cage.vertices - x).abs().max().item() / cage.scale
    del w
    best = min(first, best_of(fn, repeat)[1]) if repeat else first
    return {"points": x.shape[0], "tris": cage.triangles.shape[0], "first": first, "best": best, "peak": peak,
            "err": err}  # fmt: skip


def measure(data: str, model: str, backend: str, repeat: int) -> dict:
    return run_in_child(__file__, ["--one", model, backend, "--data", data, "--repeat", str(repeat)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_argument(ap)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--models", nargs="*", default=MODELS)
    ap.add_argument("--no-baseline", action="store_true", help="skip the naive baseline (slow, memory hungry)")
    ap.add_argument("--no-green", action="store_true", help="skip the Green coordinates rows")
    ap.add_argument("--large", type=int, default=0, help="also run this many random points (memory check)")
    ap.add_argument("--one", nargs=2, metavar=("MODEL", "BACKEND"), help=argparse.SUPPRESS)
    ap.add_argument("--large-one", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(run_one(args.data, args.one[0], args.one[1], args.repeat)))
        return
    if args.large_one:
        print(json.dumps(run_large(int(args.large_one[0]), args.large_one[1], args.large_one[2])))
        return

    from torchcage.backends import native as _native

    t = time.perf_counter()
    native = _native.available()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, float64; native kernel: "
          f"{'yes' if native else 'no'} (load/build {1000 * (time.perf_counter() - t):.0f} ms)\n")  # fmt: skip
    header = (f"{'model':<12}{'points':>8}{'tris':>6} | {'backend':<8}{'first ms':>10}{'best ms':>9}"
              f"{'Mpts/s':>8}{'peak MB':>9}{'max |err|':>11}")  # fmt: skip
    print(header)
    print("-" * len(header))
    for model in args.models:
        if load(args.data, model) is None:
            print(f"{model:<12}  (absent from {args.data}/qmvc: skipped)")
            continue
        backends = (["native"] if native else []) + ["torch"] + ([] if args.no_baseline else ["naive"])
        backends += [] if args.no_green else ["gc"]
        for name in backends:
            r = measure(args.data, model, name, args.repeat if name != "naive" else 1)
            rate = r["points"] / r["best"] / 1e6
            print(f"{model:<12}{r['points']:>8}{r['tris']:>6} | {name:<8}{1000 * r['first']:>10.1f}"
                  f"{1000 * r['best']:>9.1f}{rate:>8.2f}{r['peak']:>9.1f}{r['err']:>11.1e}")  # fmt: skip
        print()
    print("first: first call in a fresh process (includes loading the native library);")
    print("best: best of the repeated calls; peak MB: peak resident memory of the process above its level")
    print("before the first call; max |err|: linear precision, max |W V - X| / cage size (for green: the")
    print("identity phi V + psi n = X at the points inside the cage). native/torch/naive: mean value")
    print("coordinates; green: Green coordinates (default backend: native where available).")
    if args.large:
        out_mb = args.large * 16 * 8 / 2**20
        print(f"\n{args.large} random points in the bar cage (16 vertices): the output alone is {out_mb:.0f} MB")
        for backend in (["native"] if native else []) + ["torch"]:
            for chunk in ("default", "4096"):
                r = run_in_child(__file__, ["--large-one", str(args.large), backend, chunk])
                print(f"  {backend:<7} chunk {chunk:>7}: {r['time']:7.2f} s, peak {r['peak']:7.0f} MB "
                      f"({r['peak'] - out_mb:+.0f} MB beyond the output)")  # fmt: skip


def run_large(n: int, backend: str, chunk: str) -> dict:
    """Peak memory of ``n`` random points in the bundled bar cage, in this (fresh) process."""
    cage = torchcage.load_cage(torchcage.data.path("bar_cage.obj")).triangulated()
    x = torch.rand(n, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) - 0.5
    base = rss_mb()
    size = None if chunk == "default" else int(chunk)
    dt, _, _ = best_of(lambda: F.mean_value_coordinates(x, cage, backend=backend, chunk_size=size), 1)
    return {"time": dt, "peak": peak_mb() - base}


if __name__ == "__main__":
    main()
