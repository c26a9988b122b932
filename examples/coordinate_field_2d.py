"""Picture of one 2D mean value coordinate function over the bundled polygon cage.

Mean value coordinates are defined everywhere, inside and outside the cage: the picture shows
the coordinate of one vertex on a 400x400 grid (red positive, blue negative), with the polygon
and the vertex marked.

Usage: ``python examples/coordinate_field_2d.py [out.png]``
"""

from __future__ import annotations

import sys

import numpy as np
import torch
from PIL import Image, ImageDraw

import torchcage
from torchcage import functional as F


def main(out: str = "mvc2d.png", vertex: int = 0, size: int = 400) -> None:
    cage = torchcage.load_cage(torchcage.data.path("blob2d.obj"))
    v = cage.vertices
    lo, hi = v.min(0).values - 0.4, v.max(0).values + 0.4
    xs = torch.linspace(float(lo[0]), float(hi[0]), size, dtype=torch.float64)
    ys = torch.linspace(float(hi[1]), float(lo[1]), size, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)  # (size, size, 2), rows top to bottom
    w = F.mean_value_coordinates(grid, cage)[..., vertex].numpy()
    t = np.clip(w, -1, 1)
    rgb = np.stack([1 - np.clip(-t, 0, 1), 1 - np.abs(t), 1 - np.clip(t, 0, 1)], -1)
    bands = (np.floor(w * 10) % 2 == 0)[..., None]  # iso-bands every 0.1
    image = Image.fromarray((255 * rgb * np.where(bands, 1.0, 0.93)).astype(np.uint8))
    draw = ImageDraw.Draw(image)

    def px(p: torch.Tensor) -> tuple[float, float]:
        return (
            float((p[0] - lo[0]) / (hi[0] - lo[0]) * (size - 1)),
            float((hi[1] - p[1]) / (hi[1] - lo[1]) * (size - 1)),
        )

    for a, b in cage.edges.tolist():
        draw.line([px(v[a]), px(v[b])], fill=(20, 20, 20), width=2)
    x, y = px(v[vertex])
    draw.ellipse([x - 6, y - 6, x + 6, y + 6], outline=(0, 0, 0), width=3)
    image.save(out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main(*sys.argv[1:2])
