"""Picture of one 2D mean value coordinate function over the bundled polygon cage.

Mean value coordinates are defined everywhere, inside and outside the cage: the picture shows
the coordinate of one vertex on a 400x400 grid (red positive, blue negative, white zero, bands
every 0.1), with the polygon and the vertex marked, a title, and a colour scale beside it.

Usage: ``python examples/coordinate_field_2d.py [out.png]`` (default: docs/images/mvc2d.png)
"""

from __future__ import annotations

import sys
from types import SimpleNamespace

import torch
from PIL import Image, ImageDraw

import torchcage
from torchcage import functional as F
from torchcage.viz import _font, render_field_2d

#: Height of the title strip and width of the colour-scale strip, pixels.
TITLE_HEIGHT, SCALE_WIDTH, BAR_WIDTH = 34, 86, 22


def colour_scale(height: int, lo: float = -1.0, hi: float = 1.0) -> Image.Image:
    """The colour scale of :func:`torchcage.viz.render_field_2d` from ``hi`` (top) to ``lo``
    (bottom), ``BAR_WIDTH x height``, drawn by that function itself (so that it cannot drift
    from the picture's colours)."""
    ramp = torch.linspace(hi, lo, height, dtype=torch.float64)[:, None].expand(height, height)
    nothing = SimpleNamespace(vertices=torch.zeros(0, 2), edges=torch.zeros(0, 2, dtype=torch.long))
    return render_field_2d(ramp, nothing, (0.0, 0.0), (1.0, 1.0)).crop((0, 0, BAR_WIDTH, height))


def framed(field: Image.Image, title: str, lo: float = -1.0, hi: float = 1.0) -> Image.Image:
    """``field`` with ``title`` above it and a labelled colour scale (``lo`` .. ``hi``) on its right."""
    w, h = field.size
    canvas = Image.new("RGB", (w + SCALE_WIDTH, h + TITLE_HEIGHT), (255, 255, 255))
    canvas.paste(field, (0, TITLE_HEIGHT))
    draw = ImageDraw.Draw(canvas)
    draw.text((8, 8), title, fill=(0, 0, 0), font=_font(16))
    x0, y0 = w + 12, TITLE_HEIGHT
    canvas.paste(colour_scale(h, lo, hi), (x0, y0))
    draw.rectangle([x0, y0, x0 + BAR_WIDTH - 1, y0 + h - 1], outline=(0, 0, 0))
    small = _font(13)
    for k in range(5):
        value = hi - k * (hi - lo) / 4
        y = y0 + round(k * (h - 1) / 4)
        draw.line([(x0 + BAR_WIDTH, y), (x0 + BAR_WIDTH + 4, y)], fill=(0, 0, 0))
        draw.text((x0 + BAR_WIDTH + 7, min(max(y - 7, y0), y0 + h - 15)), f"{value:+.1f}", fill=(0, 0, 0), font=small)
    return canvas


def main(out: str = "docs/images/mvc2d.png", vertex: int = 0, size: int = 400) -> None:
    cage = torchcage.load_cage(torchcage.data.path("blob2d.obj"))
    v = cage.vertices
    lo, hi = v.min(0).values - 0.4, v.max(0).values + 0.4
    xs = torch.linspace(float(lo[0]), float(hi[0]), size, dtype=torch.float64)
    ys = torch.linspace(float(hi[1]), float(lo[1]), size, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)  # (size, size, 2), rows top to bottom
    w = F.mean_value_coordinates(grid, cage)[..., vertex]
    field = render_field_2d(w, cage, lo.tolist(), hi.tolist(), vertex=vertex)
    title = f"mean value coordinate of vertex {vertex} (circled): range {float(w.min()):.2f}..{float(w.max()):.2f}"
    framed(field, title).save(out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main(*sys.argv[1:2])
