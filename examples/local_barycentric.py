"""Pictures of local barycentric coordinates (LBC).

Writes into the output folder:

- ``lbc2d.png``: one coordinate function over the bundled 2D polygon, with mean value coordinates
  beside it (red positive, blue negative, white zero: LBC are non-negative and vanish away from
  their vertex, MVC spread over the whole shape and change sign);
- ``lbc3d.png``: the bundled bar deformed by moving the four cage vertices at one end: with LBC
  the far half stays exactly still, with MVC everything moves a little (colour: displacement).

Usage: ``python examples/local_barycentric.py [out_dir]``
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

import torchcage
from torchcage import functional as F
from torchcage.geometry import inside_cage
from torchcage.viz import Panel, render_panels


def field_panel(w: np.ndarray, inside: np.ndarray, size: int) -> Image.Image:
    t = np.clip(w, -1, 1)
    rgb = np.stack([1 - np.clip(-t, 0, 1), 1 - np.abs(t), 1 - np.clip(t, 0, 1)], -1)
    bands = (np.floor(w * 10) % 2 == 0)[..., None]
    rgb = rgb * np.where(bands, 1.0, 0.93)
    rgb[~inside] = 0.85
    return Image.fromarray((255 * rgb.reshape(size, size, 3)).astype(np.uint8))


def picture_2d(out: Path, vertex: int = 2, size: int = 360) -> None:
    cage = torchcage.load_cage(torchcage.data.path("blob2d.obj"))
    v = cage.vertices
    lo, hi = v.min(0).values - 0.05, v.max(0).values + 0.05
    xs = torch.linspace(float(lo[0]), float(hi[0]), size, dtype=torch.float64)
    ys = torch.linspace(float(hi[1]), float(lo[1]), size, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)
    inside = inside_cage(grid, cage)
    lbc = torch.zeros(grid.shape[0], dtype=torch.float64)
    mvc = torch.zeros(grid.shape[0], dtype=torch.float64)
    lbc[inside] = F.local_barycentric_coordinates(grid[inside], cage, target_cells=6000).to_dense()[:, vertex]
    mvc[inside] = F.mean_value_coordinates(grid[inside], cage)[:, vertex]
    panels = []
    for name, w in (("local barycentric", lbc), ("mean value", mvc)):
        img = field_panel(w.numpy(), inside.numpy(), size)
        draw = ImageDraw.Draw(img)

        def px(p: torch.Tensor) -> tuple[float, float]:
            return (
                float((p[0] - lo[0]) / (hi[0] - lo[0]) * (size - 1)),
                float((hi[1] - p[1]) / (hi[1] - lo[1]) * (size - 1)),
            )

        for a, b in cage.edges.tolist():
            draw.line([px(v[a]), px(v[b])], fill=(20, 20, 20), width=2)
        x, y = px(v[vertex])
        draw.ellipse([x - 6, y - 6, x + 6, y + 6], outline=(0, 0, 0), width=3)
        draw.text((6, 4), f"{name}, vertex {vertex}", fill=(0, 0, 0))
        panels.append(img)
    row = Image.new("RGB", (2 * size + 8, size), "white")
    row.paste(panels[0], (0, 0))
    row.paste(panels[1], (size + 8, 0))
    row.save(out / "lbc2d.png")
    print(f"wrote {out / 'lbc2d.png'}")


def picture_3d(out: Path) -> None:
    cage = torchcage.load_cage(torchcage.data.path("bar_cage.obj"))
    verts, faces = torchcage.load_mesh(torchcage.data.path("bar.obj"))
    verts = verts.to(torch.float64)
    axis = int(torch.argmax(cage.vertices.max(0).values - cage.vertices.min(0).values))
    end = cage.vertices[:, axis] >= cage.vertices[:, axis].max() - 1e-9
    moved = cage.vertices.clone()
    moved[end] += torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64).index_fill(0, torch.tensor([(axis + 1) % 3]), 0.6)
    lbc = torchcage.LocalBarycentricCoordinates(cage, verts, target_cells=4000)
    mvc = torchcage.MeanValueCoordinates(cage.triangulated(), verts)
    edges = cage.unique_edges()
    panels = [Panel(verts, faces, cage.vertices, edges, "rest")]
    for name, module in (("local barycentric", lbc), ("mean value", mvc)):
        x = module(moved).detach()
        d = (x - verts).norm(dim=1)
        still = float((d < 1e-9).double().mean())
        t = (d / 0.6).clamp(0, 1)[:, None]
        colors = (1 - t) * torch.tensor([0.55, 0.65, 0.8], dtype=torch.float64) + t * torch.tensor([0.9, 0.3, 0.2])
        colors[d < 1e-9] = torch.tensor([0.3, 0.75, 0.4], dtype=torch.float64)
        panels.append(
            Panel(x, faces, moved, edges, f"{name}: {100 * still:.0f}% of vertices exactly still", vertex_colors=colors)
        )
    render_panels(panels, size=360).save(out / "lbc3d.png")
    print(f"wrote {out / 'lbc3d.png'}")


def main(out_dir: str = ".") -> None:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    picture_2d(out)
    picture_3d(out)


if __name__ == "__main__":
    main(*sys.argv[1:])
