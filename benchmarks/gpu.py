"""GPU benchmark: 3D mean value coordinates by the Triton kernel, the eager torch kernel and
``torch.compile`` of the torch kernel, float32 and float64, on FireHydrant (39,028 mesh vertices)
and Beast (28,388) and on 10^7 points in FireHydrant's cage; prints a table (median of repeats,
first-call latency, peak GPU memory) and the Triton kernel's largest difference from the eager
torch kernel (float64) in the same run.

Run it on a machine with a CUDA GPU and triton::

    python benchmarks/gpu.py --data ../shared/data

``--interpret`` runs a tiny smoke version on the CPU through Triton's interpreter (no timing
meaning; it checks that the script runs). Green coordinates (rows ``gc triton``, ``gc torch
eager``: the bare integrals) on the same points, with the speed-up. The MVC gradients and Hessians
(float64): the Triton derivative kernel against autograd of the torch kernel (rows ``d2 triton``,
``d2 torch``; 3D on the first 4096 points and on all, 2D on a 512 x 512 grid), and the gradient of a
loss through the autograd Function (``grad (backward)``). Quad mean value coordinates on the quad
cages (float64): the Triton kernel against the eager torch kernel on the first 4096 points
(``qmvc triton 4096``, ``qmvc torch 4096``), and the Triton kernel on all points.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import torch
from harness import add_data_argument, load_model

import torchcage
from torchcage import functional as F
from torchcage.families.green.dispatch import green_flat
from torchcage.families.mean_value.dispatch import coordinates_flat


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def _time(fn, device: str, repeats: int) -> tuple[float, float, float]:
    """(first call s, median s of ``repeats`` more, peak memory MB of one call)."""
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    _sync(device)
    t0 = time.perf_counter()
    fn()
    _sync(device)
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - t0)
    times.sort()
    peak = torch.cuda.max_memory_allocated() / 2**20 if device == "cuda" else float("nan")
    return first, times[len(times) // 2], peak


def _torch_kernel(x: torch.Tensor, cage: torchcage.Cage) -> torch.Tensor:
    """The eager torch kernel computing in the points' dtype (the public function would promote
    float32 to float64)."""
    return coordinates_flat(x, cage, backend="torch")


def _time_rows(name: str, dtype: str, runs: dict, device: str, repeats: int) -> dict[str, float]:
    """Time each of ``runs`` (method name -> callable), print a table row per method (or why it
    failed) and return the medians of those that ran."""
    med = {}
    for method, fn in runs.items():
        try:
            first, med[method], peak = _time(fn, device, repeats)
        except Exception as err:  # (a failure is a result too)
            print(f"{name:42s} {dtype:8s} {method:14s} failed: {type(err).__name__}: {err}")
            continue
        print(f"{name:42s} {dtype:8s} {method:14s} {first:9.4f} {med[method]:9.4f} {peak:9.1f}")
    return med


def _derivative_3d_rows(name: str, x: torch.Tensor, cage: torchcage.Cage, device: str, repeats: int, m: int) -> None:
    """3D mean value gradients and Hessians (float64, as every backend computes them): the Triton
    derivative kernel against autograd of the torch kernel on the first ``m`` points, with the
    speed-up and the largest difference (relative to each row's largest entry); the Triton kernel
    on all points; and the gradient of a loss through the autograd Function (backward: values and
    point derivatives from the Triton kernels on a GPU)."""
    xs = x[:m]
    w = torch.randn(cage.num_vertices, dtype=x.dtype, device=x.device)

    def backward() -> torch.Tensor:
        xr = x.detach().requires_grad_()
        (gx,) = torch.autograd.grad((F.mean_value_coordinates(xr, cage) @ w).sum(), xr)
        return gx

    runs = {
        f"d2 triton {m}": lambda: F.mean_value_derivatives(xs, cage, order=2, backend="triton"),
        f"d2 torch {m}": lambda: F.mean_value_derivatives(xs, cage, order=2, backend="torch"),
        "d2 triton all": lambda: F.mean_value_derivatives(x, cage, order=2, backend="triton"),
        "grad (backward)": backward,
    }
    med = _time_rows(name, "float64", runs, device, repeats)
    a, b = f"d2 triton {m}", f"d2 torch {m}"
    if a in med and b in med:
        (_, gt, ht), (_, ge, he) = runs[a](), runs[b]()
        err = max(
            float(((p - q).abs().flatten(1).amax(1) / q.abs().flatten(1).amax(1).clamp_min(1e-300)).max())
            for p, q in ((gt, ge), (ht, he))
        )
        print(f"{'':51s} d2 triton: {med[b] / med[a]:.1f}x autograd's speed, largest difference {err:.1e}")


def _green_rows(name: str, x: torch.Tensor, c: torchcage.Cage, dtype: torch.dtype, device: str, repeats: int) -> None:
    """Green coordinates (the bare integrals): the Triton kernel against the eager torch kernel,
    with the speed-up and the largest difference."""
    runs = {
        "gc triton": lambda: green_flat(x, c, backend="triton"),
        "gc torch eager": lambda: green_flat(x, c, backend="torch"),
    }
    med = _time_rows(name, str(dtype)[6:], runs, device, repeats)
    if len(med) == 2:
        t, e = (torch.cat(fn(), dim=1).double() for fn in runs.values())
        err = float(((t - e).abs() / e.abs().clamp_min(1)).max())
        speed = med["gc torch eager"] / med["gc triton"]
        print(f"{'':51s} gc triton: {speed:.1f}x the eager kernel's speed, largest difference {err:.1e}")


def _quad_rows(name: str, x: torch.Tensor, cage: torchcage.Cage, device: str, repeats: int, m: int) -> None:
    """Quad mean value coordinates (float64, as every backend computes them; the paper's ``n = 4``):
    the Triton kernel against the eager torch kernel on the first ``m`` points, with the speed-up
    and the largest difference, and the Triton kernel on all points."""
    xs = x[:m]
    runs = {
        f"qmvc triton {m}": lambda: F.quad_mean_value_coordinates(xs, cage, backend="triton"),
        f"qmvc torch {m}": lambda: F.quad_mean_value_coordinates(xs, cage, backend="torch"),
        "qmvc triton all": lambda: F.quad_mean_value_coordinates(x, cage, backend="triton"),
    }
    med = _time_rows(name, "float64", runs, device, repeats)
    a, b = f"qmvc triton {m}", f"qmvc torch {m}"
    if a in med and b in med:
        t, e = runs[a](), runs[b]()
        err = float(((t - e).abs() / e.abs().clamp_min(1)).max())
        print(f"{'':51s} qmvc triton: {med[b] / med[a]:.1f}x the eager kernel's speed, largest difference {err:.1e}")


def _derivative_2d_rows(device: str, repeats: int, side: int) -> None:
    """2D mean value gradients and Hessians (the image warps' derivatives) on a ``side x side`` grid
    over the bundled polygon: the Triton derivative kernel against autograd of the torch kernel
    (float64), with the speed-up and the largest difference (relative to each row's largest
    entry)."""
    cage = torchcage.load_cage(torchcage.data.path("blob2d.obj")).to(torch.float64).to(device)
    lo, hi = cage.vertices.amin(0), cage.vertices.amax(0)
    t = torch.linspace(0.02, 0.98, side, dtype=torch.float64, device=device)
    gx, gy = torch.meshgrid(lo[0] + (hi[0] - lo[0]) * t, lo[1] + (hi[1] - lo[1]) * t, indexing="xy")
    x = torch.stack([gx.reshape(-1), gy.reshape(-1)], dim=1)
    runs = {
        "d2 triton": lambda: F.mean_value_derivatives(x, cage, order=2, backend="triton"),
        "d2 torch": lambda: F.mean_value_derivatives(x, cage, order=2, backend="torch"),
    }
    name = f"2D derivatives, blob2d ({x.shape[0]:,} pts)"
    med = _time_rows(name, "float64", runs, device, repeats)
    if len(med) == 2:
        (_, gt, ht), (_, ge, he) = (fn() for fn in runs.values())
        err = max(
            float(((a - b).abs().flatten(1).amax(1) / b.abs().flatten(1).amax(1).clamp_min(1e-300)).max())
            for a, b in ((gt, ge), (ht, he))
        )
        speed = med["d2 torch"] / med["d2 triton"]
        print(f"{'':51s} d2 triton: {speed:.1f}x autograd's speed, largest difference {err:.1e}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_data_argument(ap)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--big", type=int, default=10**7, help="points of the large case")
    ap.add_argument("--interpret", action="store_true", help="a tiny smoke run on the CPU (TRITON_INTERPRET=1)")
    ap.add_argument("--no-compile", action="store_true", help="skip torch.compile")
    args = ap.parse_args(argv)
    if args.interpret:
        os.environ["TRITON_INTERPRET"] = "1"
        device, args.big, args.repeats = "cpu", 512, 1
    elif torch.cuda.is_available():
        device = "cuda"
    else:
        raise SystemExit("no CUDA device: run this on a GPU machine (or --interpret for a smoke run on the CPU)")
    cases, quad_cases = [], []
    for model in ("FireHydrant", "Beast"):
        loaded = load_model(args.data, model)
        if loaded is None:
            print(f"{model}: not in the data folder, skipped", file=sys.stderr)
            continue
        mesh, quad_cage = loaded
        cage = quad_cage.triangulated()
        if args.interpret:
            mesh = mesh[:256]
        cases.append((f"{model} ({mesh.shape[0]:,} pts, {cage.triangles.shape[0]} tri)", mesh, cage))
        quad_cases.append((f"{model} ({mesh.shape[0]:,} pts, {quad_cage.quads.shape[0]} quads)", mesh, quad_cage))
    if cases:
        _, mesh, cage = cases[0]
        lo, hi = mesh.min(dim=0).values, mesh.max(dim=0).values
        g = torch.Generator().manual_seed(0)
        big = lo + (hi - lo) * torch.rand(args.big, 3, generator=g, dtype=torch.float64)
        cases.append((f"{cases[0][0].split(' ')[0]} box ({args.big:,} pts)", big, cage))
    compiled = None if args.no_compile or args.interpret else torch.compile(_torch_kernel, dynamic=True)
    print(f"{'case':42s} {'dtype':8s} {'method':14s} {'first s':>9s} {'median s':>9s} {'peak MB':>9s}")
    for name, pts, cage in cases:
        for dtype in (torch.float32, torch.float64):
            x = pts.to(device, dtype)
            c = cage.to(device).to(dtype)
            runs = {"triton": lambda x=x, c=c, dt=dtype: F.mean_value_coordinates(x, c, backend="triton", dtype=dt)}
            if pts.shape[0] <= 10**6 or args.interpret:  # (the eager kernel on 10^7 points: minutes)
                runs["torch eager"] = lambda x=x, c=c: _torch_kernel(x, c)
                if compiled is not None:
                    runs["torch.compile"] = lambda x=x, c=c: compiled(x, c)
            base, tri = None, None
            for method, fn in runs.items():
                try:
                    first, med, peak = _time(fn, device, args.repeats)
                except Exception as err:  # (a compile failure is a result too)
                    print(f"{name:42s} {str(dtype)[6:]:8s} {method:14s} failed: {type(err).__name__}: {err}")
                    continue
                base = med if method == "torch eager" else base
                tri = med if method == "triton" else tri
                print(f"{name:42s} {str(dtype)[6:]:8s} {method:14s} {first:9.4f} {med:9.4f} {peak:9.1f}")
            if base is not None and tri is not None:
                t = F.mean_value_coordinates(x, c, backend="triton", dtype=dtype)
                e = _torch_kernel(x, c)
                err = float(((t.double() - e.double()).abs() / e.double().abs().clamp_min(1)).max())
                print(f"{'':51s} triton: {base / tri:.1f}x the eager kernel's speed, largest difference {err:.1e}")
            if pts.shape[0] <= 10**6 or args.interpret:
                _green_rows(name, x, c, dtype, device, args.repeats)
                if dtype == torch.float64 and (not args.interpret or name == cases[0][0]):  # (interpreted: minutes)
                    _derivative_3d_rows(name, x, c, device, args.repeats, 64 if args.interpret else 4096)
    for name, pts, cage in quad_cases[: 1 if args.interpret else None]:  # (interpreted: a minute per case)
        x = pts.to(device, torch.float64)
        _quad_rows(
            name, x[:64] if args.interpret else x, cage.to(device), device, args.repeats, 32 if args.interpret else 4096
        )
    _derivative_2d_rows(device, args.repeats, 16 if args.interpret else 512)
    return 0


if __name__ == "__main__":
    sys.exit(main())
