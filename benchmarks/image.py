"""Benchmark of 2D cage image warping (torchcage.image): a 512x512 RGB image, a 30-vertex cage,
batches of 8 poses, float32 images and vertices (the stored coordinates are float64).

Rows: the one-off precomputation of ``CageWarp`` (forward mapping), the warp per pose with and
without a backward pass, the backward mapping (coordinates per pose), and, as the baseline in the
same run, kornia's ``remap`` alone with a prebuilt map (the floor any cage warp pays to sample).

Usage: ``python benchmarks/image.py [--size 512] [--batch 8] [--repeat 5]``
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import best_of


def cage_polygon(size: int, n: int = 30) -> torch.Tensor:
    k = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n
    r = 0.35 * size * (1 + 0.15 * torch.sin(3 * k))
    return torch.stack([size / 2 + r * torch.cos(k), size / 2 + r * torch.sin(k)], dim=1)


def best(fn, repeat: int) -> float:
    return best_of(fn, repeat)[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--methods", nargs="*", default=["mvc", "gc", "lbc"])
    args = ap.parse_args()
    from kornia.geometry.transform import remap

    from torchcage.backends import native as _native
    from torchcage.image import CageWarp, pixel_centres

    S, B = args.size, args.batch
    _native.library()  # build or load outside the timings
    gen = torch.Generator().manual_seed(0)
    cage = cage_polygon(S)
    poses = (cage[None] + 0.03 * S * torch.randn((B, *cage.shape), dtype=torch.float64, generator=gen)).float()
    img = torch.rand(B, 3, S, S, generator=gen)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; {S}x{S} RGB, {cage.shape[0]}-vertex cage, "
          f"batch of {B} poses, float32\n")  # fmt: skip
    header = f"{'method':<7}{'step':<38}{'total ms':>10}{'ms / pose':>11}"
    print(header)
    print("-" * len(header))

    grid = pixel_centres(S, S, dtype=torch.float32).reshape(1, S, S, 2).expand(B, -1, -1, -1) + 0.25
    t = best(lambda: remap(img, grid[..., 0], grid[..., 1], align_corners=True), args.repeat)
    print(f"{'-':<7}{'baseline: kornia remap, prebuilt map':<38}{1000 * t:>10.1f}{1000 * t / B:>11.1f}")
    for method in args.methods:
        pre, _, warp = best_of(lambda method=method: CageWarp(cage, S, S, method=method), 1)
        print(f"{method:<7}{'precompute (forward mapping, once)':<38}{1000 * pre:>10.1f}{'':>11}")
        t = best(lambda warp=warp: warp(img, poses), args.repeat)
        print(f"{method:<7}{'forward mapping: warp':<38}{1000 * t:>10.1f}{1000 * t / B:>11.1f}")

        def with_grad(warp=warp) -> None:
            v = poses.clone().requires_grad_()
            warp(img, v).square().mean().backward()

        t = best(with_grad, max(1, args.repeat // 2))
        print(f"{method:<7}{'forward mapping: warp + backward pass':<38}{1000 * t:>10.1f}{1000 * t / B:>11.1f}")
        if method == "lbc":  # forward mapping only
            continue
        back = CageWarp(cage, S, S, method=method, mapping="backward")
        t = best(lambda back=back: back(img[:2], poses[:2].double()), 1)
        print(f"{method:<7}{'backward mapping: warp (coords per pose)':<38}{1000 * t:>10.1f}{1000 * t / 2:>11.1f}")
    print("\nms / pose: total divided by the poses in the batch; the backward mapping is timed on 2 poses")
    print("(float64: its coordinates are recomputed for every pose with the native kernel).")


if __name__ == "__main__":
    main()
