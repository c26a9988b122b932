"""Picture: one cage vertex's weight under four coordinate families on the same polygon.

Mean value (closed form, can be negative), maximum entropy (MVC made positive), harmonic (solved
on a mesh of the interior, positive on a good mesh) and local barycentric coordinates (solved on
the same kind of mesh, positive and local). Red positive, blue negative (x10, so that small
negative lobes show); grey outside the polygon.

Usage: ``python examples/coordinate_families_2d.py [out.png]``
"""

from __future__ import annotations

import sys

import torch
from PIL import Image

import torchcage
from torchcage import functional as F
from torchcage.geometry import inside_cage
from torchcage.viz import render_field_2d


def main(out: str = "coordinate_families.png", size: int = 300) -> None:
    P = [(-1, -1), (1, -1), (1, 1), (0.7, 1), (0.7, -0.7), (-0.7, -0.7), (-0.7, 1), (-1, 1)]
    cage = torchcage.Cage(torch.tensor(P, dtype=torch.float64))
    vertex = 4  # the right arm's inner corner
    lo, hi = [-1.15, -1.15], [1.15, 1.15]
    xs = torch.linspace(lo[0], hi[0], size, dtype=torch.float64)
    ys = torch.linspace(hi[1], lo[1], size, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1).reshape(-1, 2)
    inside = inside_cage(grid, cage)
    x = grid[inside]
    fields = {
        "mean value": F.mean_value_coordinates(x, cage),
        "maximum entropy": F.maximum_entropy_coordinates(x, cage),
        "harmonic": F.harmonic_coordinates(x, cage, target_cells=6000),
        "local barycentric": F.local_barycentric_coordinates(x, cage, target_cells=3000).to_dense(),
    }
    panels = []
    for name, w in fields.items():
        f = torch.zeros(grid.shape[0], dtype=torch.float64)
        f[inside] = w[:, vertex]
        panels.append(render_field_2d(10 * f, cage, lo, hi, mask=inside, vertex=vertex, title=f"{name} (x10)"))
        print(f"{name}: min {float(w[:, vertex].min()):.3f}, max {float(w[:, vertex].max()):.3f}")
    image = Image.new("RGB", (4 * size + 24, size), (255, 255, 255))
    for k, p in enumerate(panels):
        image.paste(p, (k * (size + 8), 0))
    image.save(out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main(*sys.argv[1:2])
