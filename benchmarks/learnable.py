"""Benchmark of learnable cages: B shapes with their own rest cages, mean value coordinates
forward and forward+backward (gradients with respect to the points and the rest cages).

The setting of Neural Cages: B = 8 shapes, N = 5,000 points each, a 42-vertex / 80-triangle
icosphere cage per shape (each jittered), points inside. torchcage (``F.mean_value_coordinates``
on a batched ``Cage``; the backward through its fused analytic pass) against a dense batched
implementation of the half-angle formula differentiated by plain autograd
(``baseline.dense_batched_mean_value_coordinates``), float32 and float64, every measurement in its
own child process. *peak*: resident memory above the level after a warm-up call (freed memory
handed back and the kernel's high-water mark reset first, so that the warm-up's own peak does not
hide it). *err*: the largest coordinate difference to
torchcage's float64 values. With CUDA present, the same on the GPU.

``--green`` adds Green coordinates (``phi`` and ``psi``; gradients with respect to points and rest
cages): torchcage's ``GreenFunction`` (values by the native kernel, backward by the native reverse pass
``gc3d_vjp.c``) against plain autograd of the same torch kernel over all points at once, in the inputs'
dtype (what torchcage did before, except that it computed in float64).

Two last rows per device: float64 forward+backward with ``--near-fraction`` (10%) of the points on
the cage (half, inside faces) or within ``1e-4`` inside it (the others), then on its edges (half)
or within ``1e-6`` of them, and their ratios to the row without (issue 44: at most 1.5x).

Usage: ``python benchmarks/learnable.py [--batch 8] [--points 5000] [--repeat 3] [--near-fraction 0.1] [--green]``
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
from harness import best_of, peak_since, reset_peak, run_in_child

from torchcage.families.green.dispatch import green_flat


def problem(B: int, N: int, dtype: torch.dtype, device: str, near: float = 0.0, near_on: str = "faces"):
    """Cages ``(B, 42, 3)``, points ``(B, N, 3)`` inside, a cotangent; ``near``: the fraction of the
    points put on the cage (half of them, inside faces) or within ``1e-4`` inside it (the others);
    with ``near_on="edges"``, on the cage's edges (half of them) or within ``1e-6`` of them."""
    ico = icosphere()
    g = torch.Generator().manual_seed(0)
    P = ico.vertices * (1 + 0.1 * torch.rand(B, 1, 1, generator=g, dtype=torch.float64))
    P = P + 0.02 * torch.randn(B, 42, 3, generator=g, dtype=torch.float64)
    x = torch.randn(B, N, 3, generator=g, dtype=torch.float64)
    x = x / x.norm(dim=-1, keepdim=True) * torch.rand(B, N, 1, generator=g, dtype=torch.float64) ** (1 / 3) * 0.85
    k = int(near * N)
    if k:
        f = torch.randint(0, ico.triangles.shape[0], (B, k), generator=g)
        w = torch.rand(B, k, 3, generator=g, dtype=torch.float64)
        tri = P[torch.arange(B)[:, None, None], ico.triangles[f]]  # (B, k, 3, 3)
        n = torch.linalg.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :], dim=-1)
        depth = torch.rand(B, k, 1, generator=g, dtype=torch.float64) * 1e-4
        depth[:, : k // 2] = 0
        x[:, :k] = ((w / w.sum(-1, keepdim=True))[..., None] * tri).sum(-2) - depth * n / n.norm(dim=-1, keepdim=True)
        if near_on == "edges":  # along the face's first edge, then half of them moved by 1e-6 anywhere
            t = 0.05 + 0.9 * torch.rand(B, k, 1, generator=g, dtype=torch.float64)
            off = torch.nn.functional.normalize(torch.randn(B, k, 3, generator=g, dtype=torch.float64), dim=-1)
            off[:, : k // 2] = 0
            x[:, :k] = (1 - t) * tri[..., 0, :] + t * tri[..., 1, :] + 1e-6 * off
    cot = torch.randn(B, N, 42, generator=g, dtype=torch.float64)
    return x.to(device, dtype), P.to(device, dtype), ico.triangles.to(device), cot.to(device, dtype)


def _coordinates(impl: str, x: torch.Tensor, P: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """``(B, N, K)``: mean value coordinates (``K = V``) or Green's ``[phi, psi]`` (``K = V + T``)."""
    if impl == "dense":
        return dense_batched_mean_value_coordinates(x, P, faces)
    if impl == "gc-autograd":  # plain autograd of the torch kernel, every point in one graph
        parts = [
            green_flat(x[b], torchcage.Cage(P[b], faces, validate=False), None, False, "torch") for b in range(len(x))
        ]
        return torch.stack([torch.cat(part, dim=-1) for part in parts])
    cage = torchcage.Cage(P, faces, validate="topology")
    if impl == "gc":
        return torch.cat(F.green_coordinates(x, cage), dim=-1)
    return F.mean_value_coordinates(x, cage)


def child(args: argparse.Namespace) -> None:
    dtype = getattr(torch, args.dtype)
    x, P, faces, _ = problem(args.batch, args.points, dtype, args.device, args.near, args.near_on)
    green = args.impl.startswith("gc")
    ref = _coordinates("gc" if green else "torchcage", x.double().cpu(), P.double().cpu(), faces.cpu())
    cot = torch.randn(ref.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64).to(args.device, dtype)

    def sync():
        if args.device == "cuda":
            torch.cuda.synchronize()

    def run():
        if args.task == "forward":
            with torch.no_grad():
                out = _coordinates(args.impl, x, P, faces)
        else:
            xx, PP = x.clone().requires_grad_(), P.clone().requires_grad_()
            out = _coordinates(args.impl, xx, PP, faces)
            (out * cot).sum().backward()
        sync()
        return out.detach()

    run()  # warm-up: lazy imports, native library load
    before = reset_peak()
    if args.device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    _, best, out = best_of(run, repeat=args.repeat)
    peak = torch.cuda.max_memory_allocated() / 2**20 if args.device == "cuda" else peak_since(before)
    err = float((out.double().cpu() - ref).abs().max())
    print(json.dumps({"best": best, "peak": max(peak, 0.0), "err": err}))


def _table(args: argparse.Namespace, device: str, ours: str, theirs: str) -> None:
    cols = ["device", "dtype", "task", ours, theirs, "speed-up", f"{ours} peak", f"{theirs} peak"]
    print("| " + " | ".join([*cols, f"err {ours}", f"err {theirs}"]) + " |")
    print("|" + "---|" * (len(cols) + 2))
    common = ["--batch", str(args.batch), "--points", str(args.points), "--repeat", str(args.repeat), "--child"]
    for dtype in ("float32", "float64"):
        for task in ("forward", "backward"):
            res = {
                impl: run_in_child(
                    __file__, [*common, "--impl", impl, "--task", task, "--dtype", dtype, "--device", device]
                )
                for impl in (ours, theirs)
            }
            a, b = res[ours], res[theirs]
            name = "forward" if task == "forward" else "forward+backward"
            print(
                f"| {device} | {dtype} | {name} | {a['best'] * 1e3:,.0f} ms | {b['best'] * 1e3:,.0f} ms | "
                f"{b['best'] / a['best']:.1f}x | {a['peak']:,.0f} MB | {b['peak']:,.0f} MB | "
                f"{a['err']:.1e} | {b['err']:.1e} |",
                flush=True,
            )
    if ours == "torchcage":
        # Points on the cage or within 1e-4 of it (issue 44): torchcage only (the dense formula is
        # not defined on the cage); "speed-up" here is the ratio to the row above (no such points).
        nf = str(args.near_fraction)
        for on, where in (("faces", "on or near the cage"), ("edges", "on or within 1e-6 of its edges")):
            near = run_in_child(
                __file__,
                [*common, "--impl", ours, "--task", "backward", "--dtype", "float64", "--device", device,
                 "--near", nf, "--near-on", on],
            )  # fmt: skip
            print(
                f"| {device} | float64 | forward+backward, {args.near_fraction:.0%} of points {where} | "
                f"{near['best'] * 1e3:,.0f} ms | | {near['best'] / a['best']:.2f}x the plain row | "
                f"{near['peak']:,.0f} MB | | {near['err']:.1e} | |",
                flush=True,
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--points", type=int, default=5000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--green", action="store_true", help="also Green coordinates against plain autograd")
    ap.add_argument(
        "--near-fraction", type=float, default=0.1, help="points on or near the cage in the extra row (0.1)"
    )
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--near", type=float, default=0.0, help=argparse.SUPPRESS)
    ap.add_argument("--near-on", default="faces", choices=["faces", "edges"], help=argparse.SUPPRESS)
    ap.add_argument("--impl", default="torchcage", help=argparse.SUPPRESS)
    ap.add_argument("--task", default="forward", help=argparse.SUPPRESS)
    ap.add_argument("--dtype", default="float32", help=argparse.SUPPRESS)
    ap.add_argument("--device", default="cpu", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args)
        return
    print(f"B = {args.batch} shapes x N = {args.points} points, 42-vertex / 80-triangle cages, "
          f"{torch.get_num_threads()} threads, best of {args.repeat}")  # fmt: skip
    for device in ["cpu"] + (["cuda"] if torch.cuda.is_available() else []):
        print(f"\nmean value coordinates ({device}): torchcage vs the dense batched formula")
        _table(args, device, "torchcage", "dense")
        if args.green:
            print(f"\nGreen coordinates ({device}): torchcage vs plain autograd of its torch kernel")
            _table(args, device, "gc", "gc-autograd")


if __name__ == "__main__":
    main()
