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

import torch
from PIL import Image

import torchcage
from torchcage import functional as F
from torchcage.geometry import inside_cage
from torchcage.viz import Panel, render_field_2d, render_panels


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
        panels.append(
            render_field_2d(
                w, cage, lo.tolist(), hi.tolist(), mask=inside, vertex=vertex, title=f"{name}, vertex {vertex}"
            )
        )
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
