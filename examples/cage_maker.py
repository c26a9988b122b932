"""Cages made by ``torchcage.make_cage`` for the bundled bar and for procedurally made shapes that
hand-made pipelines struggle with: a mesh with holes in two parts, a point cloud, an open box with
an inner wall. Writes ``cagegen.png`` (one panel per cage, each shape scaled to the same size) and
prints each cage's measures.

Usage: ``python examples/cage_maker.py [--out docs/images]`` (needs ``pip install 'torchcage[cage]'``).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import torch

import torchcage
from torchcage.cagegen import measure_cage
from torchcage.viz import CAGE_EDGE_COLOR, MESH_COLOR, Panel, render_panels


def uv_sphere(n: int, radius: float, centre: tuple[float, float, float], hole_every: int = 0):
    """A UV sphere ``(n + 1) x 2n``; every ``hole_every``-th face removed (an open mesh)."""
    t, p = torch.meshgrid(
        torch.linspace(0, math.pi, n + 1, dtype=torch.float64),
        torch.arange(2 * n, dtype=torch.float64) * (math.pi / n),
        indexing="ij",
    )
    v = radius * torch.stack([t.sin() * p.cos(), t.sin() * p.sin(), t.cos()], -1).reshape(-1, 3)
    v = v + torch.tensor(centre, dtype=torch.float64)
    idx = torch.arange((n + 1) * 2 * n).reshape(n + 1, 2 * n)
    a, b, c, d = idx[:-1], idx[:-1].roll(-1, 1), idx[1:], idx[1:].roll(-1, 1)
    f = torch.cat([torch.stack([a, c, d], -1).reshape(-1, 3), torch.stack([a, d, b], -1).reshape(-1, 3)])
    area = torch.linalg.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]).norm(dim=1)
    keep = area > 1e-12
    if hole_every:
        keep &= torch.arange(f.shape[0]) % hole_every != 0
    return v, f[keep]


def two_parts():
    """A sphere with scattered holes and a second, smaller sphere beside it."""
    v1, f1 = uv_sphere(24, 1.0, (0.0, 0.0, 0.0), hole_every=37)
    v2, f2 = uv_sphere(12, 0.45, (1.9, 0.0, 0.5))
    return torch.cat([v1, v2]), torch.cat([f1, f2 + v1.shape[0]])


def torus_cloud(n: int = 6000):
    """Points on a torus (no faces)."""
    g = torch.Generator().manual_seed(0)
    u, w = 2 * math.pi * torch.rand(2, n, generator=g, dtype=torch.float64)
    r = 1.0 + 0.35 * w.cos()
    return torch.stack([r * u.cos(), r * u.sin(), 0.35 * w.sin()], -1), None


def open_box_with_wall(k: int = 8):
    """A box without its top, and an inner wall across it (faces inside the shape)."""
    s = torch.linspace(-1, 1, k + 1, dtype=torch.float64)
    grid_u, grid_v = torch.meshgrid(s, s, indexing="ij")
    idx = torch.arange((k + 1) ** 2).reshape(k + 1, k + 1)
    quads = torch.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    tri = torch.cat([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    one = torch.ones_like(grid_u)
    sheets = [  # (x, y, z) of five box sides (no top) and the inner wall x = 0.2
        (grid_u, grid_v, -one),
        (-one, grid_u, grid_v),
        (one, grid_u, grid_v),
        (grid_u, -one, grid_v),
        (grid_u, one, grid_v),
        (0.2 * one, grid_u * 0.9, grid_v * 0.9),
    ]
    vs, fs = [], []
    for x, y, z in sheets:
        fs.append(tri + sum(p.shape[0] for p in vs))
        vs.append(torch.stack([x, y, z], -1).reshape(-1, 3) * torch.tensor([1.4, 0.8, 0.6], dtype=torch.float64))
    return torch.cat(vs), torch.cat(fs)


def normalised(v: torch.Tensor, *others: torch.Tensor) -> list[torch.Tensor]:
    """Shift and scale so that ``v`` has a unit bounding-box diagonal centred at the origin."""
    lo, hi = v.amin(0), v.amax(0)
    centre, size = (lo + hi) / 2, float((hi - lo).norm())
    return [(x - centre) / size for x in (v, *others)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/images")
    args = ap.parse_args()
    bar = torchcage.load_mesh(torchcage.data.path("bar.obj"))
    shapes = [
        ("bundled bar", *bar, 40, "triangle"),
        ("bundled bar", *bar, 40, "quad"),
        ("open, two parts", *two_parts(), 80, "quad"),
        ("point cloud (torus)", *torus_cloud(), 80, "triangle"),
        ("open box, inner wall", *open_box_with_wall(), 40, "quad"),
    ]
    panels = []
    print(f"{'shape':<22}{'kind':<10}{'V':>4}{'quads':>7}{'outside':>9}{'crossings':>11}{'mean':>8}{'max':>8}{'s':>6}")
    for name, v, f, target, kind in shapes:
        t = time.perf_counter()
        cage = torchcage.make_cage(v, f, target_vertices=target, kind=kind)
        seconds = time.perf_counter() - t
        r = measure_cage(cage, v, f)
        print(f"{name:<22}{kind:<10}{r.vertices:>4}{r.quad_fraction:>7.2f}{r.outside:>9}{r.self_intersections:>11}"
              f"{r.mean_distance:>8.4f}{r.max_distance:>8.4f}{seconds:>6.1f}")  # fmt: skip
        nv, ncv = normalised(v, cage.vertices)
        if f is None:  # a point cloud: tiny triangles at the points, to be seen
            e = 0.004
            offsets = torch.tensor([[e, 0, 0], [0, e, 0], [0, 0, e]], dtype=torch.float64)
            f = torch.arange(3 * nv.shape[0]).reshape(-1, 3)
            nv = (nv[:, None, :] + offsets).reshape(-1, 3)
        quads = f" ({r.quads} quads)" if r.quads else ""
        panels.append(Panel(nv, f, ncv, cage.unique_edges(), title=f"{name}: {kind}, {r.vertices} vertices{quads}"))
    image = render_panels(panels[:3], size=420, azimuth=35, elevation=25)
    image2 = render_panels(
        panels[3:], size=420, azimuth=35, elevation=35, legend=[("shape", MESH_COLOR), ("made cage", CAGE_EDGE_COLOR)]
    )
    from PIL import Image

    sheet = Image.new("RGB", (image.width, image.height + image2.height), "white")
    sheet.paste(image, (0, 0))
    sheet.paste(image2, ((image.width - image2.width) // 2, image.height))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sheet.save(out / "cagegen.png")
    print(f"wrote {out / 'cagegen.png'}")


if __name__ == "__main__":
    main()
