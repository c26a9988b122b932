"""Benchmark of learnable cages: B shapes with their own rest cages, mean value coordinates
forward and forward+backward (gradients with respect to the points and the rest cages).

The setting of Neural Cages: B = 8 shapes, N = 5,000 points each, a 42-vertex / 80-triangle
icosphere cage per shape (each jittered), points inside. torchcage (``F.mean_value_coordinates``
on a batched ``Cage``; the backward through its fused analytic pass) against a dense batched
implementation of the half-angle formula differentiated by plain autograd
(``baseline.dense_batched_mean_value_coordinates``), float32 and float64, every measurement in its
own child process (its peak memory its own). *err*: the largest coordinate difference to
torchcage's float64 values. With CUDA present, the same on the GPU.

Usage: ``python benchmarks/learnable.py [--batch 8] [--points 5000] [--repeat 3]``
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

import torchcage
from torchcage import functional as F
from torchcage.testing import icosphere

sys.path.insert(0, str(Path(__file__).resolve().parent))
from baseline import dense_batched_mean_value_coordinates
from harness import best_of, peak_mb, rss_mb, run_in_child


def problem(B: int, N: int, dtype: torch.dtype, device: str):
    ico = icosphere()
    g = torch.Generator().manual_seed(0)
    P = ico.vertices * (1 + 0.1 * torch.rand(B, 1, 1, generator=g, dtype=torch.float64))
    P = P + 0.02 * torch.randn(B, 42, 3, generator=g, dtype=torch.float64)
    x = torch.randn(B, N, 3, generator=g, dtype=torch.float64)
    x = x / x.norm(dim=-1, keepdim=True) * torch.rand(B, N, 1, generator=g, dtype=torch.float64) ** (1 / 3) * 0.85
    cot = torch.randn(B, N, 42, generator=g, dtype=torch.float64)
    return x.to(device, dtype), P.to(device, dtype), ico.triangles.to(device), cot.to(device, dtype)


def child(args: argparse.Namespace) -> None:
    dtype = getattr(torch, args.dtype)
    x, P, faces, cot = problem(args.batch, args.points, dtype, args.device)
    ref = F.mean_value_coordinates(x.double().cpu(), torchcage.Cage(P.double().cpu(), faces.cpu(), validate="topology"))

    def coords(xx, PP):
        if args.impl == "dense":
            return dense_batched_mean_value_coordinates(xx, PP, faces)
        return F.mean_value_coordinates(xx, torchcage.Cage(PP, faces, validate="topology"))

    def sync():
        if args.device == "cuda":
            torch.cuda.synchronize()

    def run():
        if args.task == "forward":
            with torch.no_grad():
                out = coords(x, P)
        else:
            xx, PP = x.clone().requires_grad_(), P.clone().requires_grad_()
            out = coords(xx, PP)
            (out * cot).sum().backward()
        sync()
        return out.detach()

    run()  # warm-up: lazy imports, native library load
    before = rss_mb()
    if args.device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    _, best, out = best_of(run, repeat=args.repeat)
    peak = torch.cuda.max_memory_allocated() / 2**20 if args.device == "cuda" else peak_mb() - before
    err = float((out.double().cpu() - ref).abs().max())
    print(json.dumps({"best": best, "peak": max(peak, 0.0), "err": err}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--points", type=int, default=5000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--impl", default="torchcage", help=argparse.SUPPRESS)
    ap.add_argument("--task", default="forward", help=argparse.SUPPRESS)
    ap.add_argument("--dtype", default="float32", help=argparse.SUPPRESS)
    ap.add_argument("--device", default="cpu", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args)
        return
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    print(f"B = {args.batch} shapes x N = {args.points} points, 42-vertex / 80-triangle cages, "
          f"{torch.get_num_threads()} threads, best of {args.repeat}")  # fmt: skip
    cols = ["device", "dtype", "task", "torchcage", "dense", "speed-up", "torchcage peak", "dense peak"]
    print("| " + " | ".join([*cols, "err torchcage", "err dense"]) + " |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for device in devices:
        for dtype in ("float32", "float64"):
            for task in ("forward", "forward+backward"):
                res = {}
                for impl in ("torchcage", "dense"):
                    common = ["--batch", str(args.batch), "--points", str(args.points), "--repeat", str(args.repeat)]
                    res[impl] = run_in_child(
                        __file__,
                        [*common, "--child", "--impl", impl, "--task", task.split("+")[-1] if task != "forward"
                         else "forward", "--dtype", dtype, "--device", device],
                    )  # fmt: skip
                a, b = res["torchcage"], res["dense"]
                print(
                    f"| {device} | {dtype} | {task} | {a['best'] * 1e3:,.0f} ms | {b['best'] * 1e3:,.0f} ms | "
                    f"{b['best'] / a['best']:.1f}x | {a['peak']:,.0f} MB | {b['peak']:,.0f} MB | "
                    f"{a['err']:.1e} | {b['err']:.1e} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
