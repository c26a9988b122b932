"""Picture: one vertex's mean value coordinate and its maximum entropy coordinate, side by side.

A U-shaped polygon; the chosen vertex is an inner corner of the right arm. Mean value coordinates
give it a negative weight in the left arm (blue): moving the vertex would push that arm the other
way. Maximum entropy coordinates with the MVC prior are nonnegative everywhere and keep the
prior's shape where it was positive.

Usage: ``python examples/maximum_entropy.py [out.png]``
"""

from __future__ import annotations

import sys

import torch
from PIL import Image

import torchcage
from torchcage import functional as F
from torchcage.geometry import inside_cage
from torchcage.viz import render_field_2d


def u_shape() -> torchcage.Cage:
    """A U-shaped polygon (counter-clockwise), arms 0.3 wide."""
    P = [(-1, -1), (1, -1), (1, 1), (0.7, 1), (0.7, -0.7), (-0.7, -0.7), (-0.7, 1), (-1, 1)]
    return torchcage.Cage(torch.tensor(P, dtype=torch.float64))


def main(out: str = "mec.png", size: int = 360) -> None:
    cage = u_shape()
    vertex = 4  # the right arm's inner corner (0.7, -0.7)
    lo, hi = [-1.15, -1.15], [1.15, 1.15]
    xs = torch.linspace(lo[0], hi[0], size, dtype=torch.float64)
    ys = torch.linspace(hi[1], lo[1], size, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1).reshape(-1, 2)
    inside = inside_cage(grid, cage)
    mvc = torch.zeros(grid.shape[0], dtype=torch.float64)
    mec = torch.zeros_like(mvc)
    mvc[inside] = F.mean_value_coordinates(grid[inside], cage)[:, vertex]
    mec[inside] = F.maximum_entropy_coordinates(grid[inside], cage, prior="mvc")[:, vertex]
    # (weights scaled by 20 so that the small negative lobe shows)
    a = render_field_2d(20 * mvc, cage, lo, hi, mask=inside, vertex=vertex, title="MVC x20 (blue: negative)")
    b = render_field_2d(20 * mec, cage, lo, hi, mask=inside, vertex=vertex, title="MEC, MVC prior, x20")
    image = Image.new("RGB", (2 * size + 8, size), (255, 255, 255))
    image.paste(a, (0, 0))
    image.paste(b, (size + 8, 0))
    image.save(out)
    print(f"wrote {out}: MVC min {float(mvc.min()):.3f}, MEC min {float(mec.min()):.2e}")


if __name__ == "__main__":
    main(*sys.argv[1:2])
