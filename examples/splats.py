"""Cages for Gaussian splats and radiance fields, on the bundled bar.

1. A synthetic splat scene: flat Gaussians (surfels) on the bar's surface, coloured along its
   length with a view-dependent tint (degree-1 spherical harmonics); written as a 3D Gaussian
   splatting PLY and read back.
2. The scene bent by the bar's cage (mean value coordinates): centres, covariances and colours
   deformed by ``torchcage.splats.DeformGaussians``; rendered before and after.
3. A radiance field trained at rest (here an analytic one: a striped density inside the bar) shown
   in the deformed space by mapping each ray sample back to rest space
   (``torchcage.splats.rest_points``) and volume rendering.

Writes ``splats.png`` (the three panels) and the deformed scene ``bar_splats_deformed.ply`` into
``--out``::

    python examples/splats.py --out docs/images
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

import torchcage
from torchcage.geometry import inside_cage
from torchcage.splats import DeformGaussians, GaussianScene, read_ply, rest_points, write_ply
from torchcage.splats.linalg import matrix_to_quaternion
from torchcage.splats.render import Camera, render
from torchcage.splats.sh import C0

D64 = torch.float64


def bar_surfels(n: int, seed: int = 0) -> GaussianScene:
    """``n`` flat Gaussians on the bar's surface, area-weighted, tangent to it."""
    v, f = torchcage.load_mesh(torchcage.data.path("bar.obj"))
    v = v.to(D64)
    p = v[f]
    cross = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    g = torch.Generator().manual_seed(seed)
    tri = torch.multinomial(cross.norm(dim=-1), n, replacement=True, generator=g)
    ab = torch.rand(n, 2, generator=g, dtype=D64)
    ab = torch.where(ab.sum(-1, keepdim=True) > 1, 1 - ab, ab)
    q = p[tri]
    means = q[:, 0] + ab[:, :1] * (q[:, 1] - q[:, 0]) + ab[:, 1:] * (q[:, 2] - q[:, 0])
    normal = torch.nn.functional.normalize(cross[tri], dim=-1)
    t1 = torch.nn.functional.normalize(torch.linalg.cross(normal, torch.randn(n, 3, generator=g, dtype=D64)), dim=-1)
    t2 = torch.linalg.cross(normal, t1)
    rot = torch.stack([t1, t2, normal], dim=-1)  # columns: local axes
    z = (means[:, 2] + 1.5) / 3.0  # 0..1 along the bar
    rgb = torch.stack([0.9 - 0.6 * z, 0.3 + 0.5 * torch.sin(3.14 * z), 0.2 + 0.7 * z], dim=-1)
    stripes = (torch.sin(12.0 * means[:, 2]) > 0).to(D64)[:, None]
    rgb = rgb * (0.75 + 0.25 * stripes)
    sh = torch.zeros(n, 4, 3, dtype=D64)
    sh[:, 0] = (rgb - 0.5) / C0
    sh[:, 1:, :] = 0.15 * torch.tensor([0.0, 1.0, 0.0], dtype=D64)[:, None]  # a tint that depends on the view
    return GaussianScene(
        means=means.float(),
        log_scales=torch.log(torch.tensor([0.035, 0.035, 0.004])).expand(n, 3).clone(),
        rotations=matrix_to_quaternion(rot).float(),
        opacity_logits=torch.full((n,), 3.0),
        sh=sh.float(),
    )


def field(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """An analytic radiance field at rest: density ``(M,)`` inside a rounded bar, colour ``(M, 3)``
    striped along it."""
    r = torch.sqrt(x[:, 0] ** 2 + x[:, 1] ** 2)
    edge = torch.minimum(0.42 - r, 1.45 - x[:, 2].abs())  # > 0 inside the rounded bar
    density = 25.0 * torch.sigmoid(60.0 * edge)
    s = 0.5 + 0.5 * torch.sin(10.0 * x[:, 2])
    colour = torch.stack([0.2 + 0.7 * s, 0.35 + 0.3 * (1 - s), 0.85 - 0.5 * s], dim=-1)
    return density, colour


def render_field(cage: torchcage.Cage, pose: torch.Tensor, camera: Camera, samples: int) -> torch.Tensor:
    """Volume rendering of :func:`field` in the space deformed by ``pose``: each ray sample inside the
    deformed cage is mapped back to rest space (samples outside have no density)."""
    H, W = camera.height, camera.width
    v, u = torch.meshgrid(torch.arange(H, dtype=D64) + 0.5, torch.arange(W, dtype=D64) + 0.5, indexing="ij")
    d_cam = torch.stack([(u - W / 2) / camera.focal, (v - H / 2) / camera.focal, torch.ones_like(u)], dim=-1)
    dirs = torch.nn.functional.normalize(d_cam.reshape(-1, 3) @ camera.rotation, dim=-1)  # world
    lo, hi = pose.amin(0), pose.amax(0)
    centre, radius = (lo + hi) / 2, float((hi - lo).norm()) / 2
    dist = float((centre - camera.eye).norm())
    t = torch.linspace(dist - radius, dist + radius, samples, dtype=D64)
    pts = camera.eye + dirs[:, None, :] * t[None, :, None]  # (R, S, 3)
    flat = pts.reshape(-1, 3)
    deformed = torchcage.Cage(pose, cage.faces, validate=False)
    inside = inside_cage(flat, deformed)
    density = torch.zeros(flat.shape[0], dtype=D64)
    colour = torch.zeros(flat.shape[0], 3, dtype=D64)
    back = rest_points(flat[inside], cage, pose, warn=False)
    dens, col = field(back.points)
    density[inside], colour[inside] = dens * back.converged, col
    density, colour = density.reshape(-1, samples), colour.reshape(-1, samples, 3)
    alpha = 1 - torch.exp(-density * float(t[1] - t[0]))
    T = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], dim=1), dim=1)
    w = alpha * T
    img = (w[..., None] * colour).sum(1) + (1 - w.sum(1, keepdim=True))  # white background
    return img.reshape(H, W, 3).clamp(0, 1)


def _panel(img: torch.Tensor, title: str) -> Image.Image:
    im = Image.fromarray((img.numpy() * 255).astype(np.uint8))
    ImageDraw.Draw(im).text((8, 6), title, fill=(20, 20, 20))
    return im


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="splats_out", help="output folder (default splats_out)")
    ap.add_argument("--gaussians", type=int, default=6000, help="surfels on the bar (default 6000)")
    ap.add_argument("--samples", type=int, default=64, help="samples per ray of the radiance field (default 64)")
    ap.add_argument("--image-scale", type=float, default=1.0, help="picture size factor (default 1: 300 x 360 panels)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    cage = torchcage.load_cage(torchcage.data.path("bar_cage.obj"))
    pose = torchcage.load_cage(torchcage.data.path("bar_cage_deformed.obj")).vertices
    scene = bar_surfels(args.gaussians)
    write_ply(out / "bar_splats.ply", scene)
    scene = read_ply(out / "bar_splats.ply")

    t0 = time.perf_counter()
    deform = DeformGaussians(cage, scene)
    t1 = time.perf_counter()
    bent = deform(pose)
    t2 = time.perf_counter()
    write_ply(out / "bar_splats_deformed.ply", deform.scene(pose))
    print(f"{scene.num_gaussians} Gaussians: coordinates and Jacobians {t1 - t0:.2f} s, one pose {t2 - t1:.3f} s")

    w, h = max(8, round(300 * args.image_scale)), max(8, round(360 * args.image_scale))
    camera = Camera(eye=(4.2, -5.2, 1.6), target=(0.5, 0.0, 0.15), up=(0, 0, 1), fov=38, width=w, height=h)
    rest_img = render(scene.means, scene.covariances(), scene.sh, scene.opacity_logits, camera)
    bent_img = render(bent.means, bent.covariances, bent.sh, scene.opacity_logits, camera)
    t3 = time.perf_counter()
    field_img = render_field(cage, pose, camera, args.samples)
    rays = f"{camera.width}x{camera.height} rays x {args.samples} samples"
    print(f"radiance field: {rays}, {time.perf_counter() - t3:.1f} s")

    panels = [
        _panel(rest_img, "splats at rest"),
        _panel(bent_img, "bent by the cage (mean value coordinates)"),
        _panel(field_img, "radiance field through the inverse map"),
    ]
    sheet = Image.new("RGB", (sum(p.width for p in panels), panels[0].height), "white")
    x = 0
    for p in panels:
        sheet.paste(p, (x, 0))
        x += p.width
    sheet.save(out / "splats.png")
    print(f"wrote {out / 'splats.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
