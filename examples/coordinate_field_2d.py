"""Picture of one 2D mean value coordinate function over the bundled polygon cage.

Mean value coordinates are defined everywhere, inside and outside the cage: the picture shows
the coordinate of one vertex on a 400x400 grid (red positive, blue negative), with the polygon
and the vertex marked.

Usage: ``python examples/coordinate_field_2d.py [out.png]``
"""

from __future__ import annotations

import sys

import torch

import torchcage
from torchcage import functional as F
from torchcage.viz import render_field_2d


def main(out: str = "mvc2d.png", vertex: int = 0, size: int = 400) -> None:
    cage = torchcage.load_cage(torchcage.data.path("blob2d.obj"))
    v = cage.vertices
    lo, hi = v.min(0).values - 0.4, v.max(0).values + 0.4
    xs = torch.linspace(float(lo[0]), float(hi[0]), size, dtype=torch.float64)
    ys = torch.linspace(float(hi[1]), float(lo[1]), size, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)  # (size, size, 2), rows top to bottom
    w = F.mean_value_coordinates(grid, cage)[..., vertex]
    image = render_field_2d(w, cage, lo.tolist(), hi.tolist(), vertex=vertex)
    image.save(out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main(*sys.argv[1:2])
