"""Pictures of 2D cage image warping: a procedural image warped by each method with the cage drawn
over it, and a small optimisation that fits a cage pose to a target warp.

Writes ``image_warp.png`` (rest, then one panel per method) and ``image_fit.png`` (target, start,
fitted pose, loss curve) into the output folder.

Usage: ``python examples/image_warp.py [out_dir]``
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

from torchcage.image import CageWarp

SIZE = 256


def procedural_image(size: int = SIZE) -> torch.Tensor:
    """A checkerboard with a disc and a bar on it, ``(1, 3, size, size)`` in [0, 1]."""
    y, x = torch.meshgrid(
        torch.arange(size, dtype=torch.float64), torch.arange(size, dtype=torch.float64), indexing="ij"
    )
    checker = ((torch.div(x, 16, rounding_mode="floor") + torch.div(y, 16, rounding_mode="floor")) % 2) * 0.35 + 0.55
    img = torch.stack([checker, checker, checker])
    disc = ((x - 0.55 * size) ** 2 + (y - 0.45 * size) ** 2) < (0.16 * size) ** 2
    bar = ((x - 0.3 * size).abs() < 0.05 * size) & ((y - 0.55 * size).abs() < 0.25 * size)
    img[:, disc] = torch.tensor([0.85, 0.3, 0.2], dtype=torch.float64)[:, None]
    img[:, bar] = torch.tensor([0.2, 0.45, 0.8], dtype=torch.float64)[:, None]
    return img[None]


def rest_cage(size: int = SIZE, n: int = 10) -> torch.Tensor:
    k = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n
    r = 0.38 * size * (1 + 0.08 * torch.cos(2 * k))
    return torch.stack([0.5 * size + r * torch.cos(k), 0.5 * size + r * torch.sin(k)], dim=1)


def pose(cage: torch.Tensor) -> torch.Tensor:
    """Pull two vertices outwards, push one in, and twist the whole cage a little."""
    moved = cage.clone()
    c = cage.mean(dim=0)
    moved[0] += torch.tensor([28.0, -10.0], dtype=torch.float64)
    moved[3] += torch.tensor([-20.0, -26.0], dtype=torch.float64)
    moved[6] += 0.3 * (c - moved[6])
    d = moved - c
    a = 0.15 * d[:, 1] / cage[:, 1].std()
    return c + torch.stack(
        [d[:, 0] * torch.cos(a) - d[:, 1] * torch.sin(a), d[:, 0] * torch.sin(a) + d[:, 1] * torch.cos(a)], 1
    )


def to_pil(img: torch.Tensor, cage: torch.Tensor | None = None, title: str = "") -> Image.Image:
    arr = (img[0].permute(1, 2, 0).clamp(0, 1).detach().numpy() * 255).astype(np.uint8)
    pil = Image.fromarray(arr).convert("RGB")
    draw = ImageDraw.Draw(pil)
    if cage is not None:
        pts = [tuple(p) for p in cage.detach().tolist()]
        draw.line([*pts, pts[0]], fill=(20, 20, 20), width=2)
        for p in pts:
            draw.ellipse([p[0] - 3, p[1] - 3, p[0] + 3, p[1] + 3], fill=(250, 200, 0), outline=(0, 0, 0))
    if title:
        draw.rectangle([0, 0, 7 * len(title) + 8, 16], fill=(255, 255, 255))
        draw.text((4, 2), title, fill=(0, 0, 0))
    return pil


def row(panels: list[Image.Image]) -> Image.Image:
    out = Image.new("RGB", (sum(p.width for p in panels) + 6 * (len(panels) - 1), panels[0].height), "white")
    x = 0
    for p in panels:
        out.paste(p, (x, 0))
        x += p.width + 6
    return out


def warps(out_dir: Path, methods: list[tuple[str, str]]) -> None:
    img, cage = procedural_image(), rest_cage()
    moved = pose(cage)
    panels = [to_pil(img, cage, "rest")]
    for method, label in methods:
        warped = CageWarp(cage, SIZE, SIZE, method=method)(img, moved)
        panels.append(to_pil(warped, moved, label))
    row(panels).save(out_dir / "image_warp.png")
    print(f"wrote {out_dir / 'image_warp.png'}")


def fit(out_dir: Path, schedule: tuple[tuple[float, int], ...] = ((8.0, 40), (4.0, 40), (1.0, 60))) -> list[float]:
    """Recover a cage pose from its warped image by gradient descent through the warp, coarse to
    fine: the image loss is taken on blurred images, the blur shrinking in stages (a textured
    image's loss is far from convex in the vertices otherwise)."""
    from kornia.filters import gaussian_blur2d

    img, cage = procedural_image(), rest_cage()
    warp = CageWarp(cage, SIZE, SIZE)
    target_pose = pose(cage)
    target = warp(img, target_pose).detach()
    verts = cage.clone().requires_grad_()
    opt = torch.optim.Adam([verts], lr=1.0)
    losses = []
    for sigma, steps in schedule:
        k = 4 * int(sigma) + 1

        def blur(x: torch.Tensor, k: int = k, sigma: float = sigma) -> torch.Tensor:
            return gaussian_blur2d(x, (k, k), (sigma, sigma))

        blurred_target = blur(target)
        for _ in range(steps):
            opt.zero_grad()
            loss = (blur(warp(img, verts)) - blurred_target).square().mean()
            loss.backward()
            opt.step()
            losses.append(loss.item())
    steps = len(losses)
    fitted = warp(img, verts).detach()
    curve = Image.new("RGB", (SIZE, SIZE), "white")
    draw = ImageDraw.Draw(curve)
    logl = np.log10(np.maximum(losses, 1e-12))
    lo, hi = logl.min(), logl.max()
    pts = [
        (10 + i * (SIZE - 20) / (steps - 1), 20 + (hi - v) / max(hi - lo, 1e-9) * (SIZE - 40))
        for i, v in enumerate(logl)
    ]
    draw.line(pts, fill=(200, 40, 40), width=2)
    draw.text((10, 4), f"log10 loss (blur 8, 4, 1 px): {logl[0]:.2f} -> {logl[-1]:.2f}", fill=(0, 0, 0))
    err = float((verts.detach() - target_pose).norm(dim=1).max())
    draw.text((10, SIZE - 16), f"max vertex error {err:.2f} px", fill=(0, 0, 0))
    start = warp(img, cage).detach()
    row([to_pil(target, target_pose, "target"), to_pil(start, cage, "start"), to_pil(fitted, verts, "fitted"),
         curve]).save(out_dir / "image_fit.png")  # fmt: skip
    print(f"wrote {out_dir / 'image_fit.png'}: loss {losses[0]:.4g} -> {losses[-1]:.4g}, max vertex error {err:.3f} px")
    return losses


def main(out_dir: str = ".") -> None:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    warps(out, [("mvc", "mean value"), ("lbc", "local barycentric"), ("gc", "Green")])
    fit(out)


if __name__ == "__main__":
    main(*sys.argv[1:])
