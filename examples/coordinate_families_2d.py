"""Picture: one cage vertex's weight under five coordinate families on the same polygon, and the
deformation each gives when that vertex moves.

Mean value (closed form, can be negative), maximum entropy (MVC made positive), harmonic (solved
on a mesh of the interior, positive on a good mesh), bounded biharmonic weights (solved on the same
kind of mesh, in [0, 1], smooth) and local barycentric coordinates (positive and local). Top row:
the weight, red positive, blue negative (x10, so that small negative lobes show); grey outside the
polygon. Bottom row: a grid inside the polygon after the circled vertex moves right and up; each
point moves by the weighted displacements of the cage vertices, ``x + w @ (V' - V)`` (the same as
``w @ V'`` for the coordinates with linear precision; bounded biharmonic weights need it to keep
the rest pose).

Usage: ``python examples/coordinate_families_2d.py [out.png]``
"""

from __future__ import annotations

import sys

import torch
from PIL import Image, ImageDraw

import torchcage
from torchcage import functional as F
from torchcage.geometry import inside_cage
from torchcage.viz import render_field_2d


def _grid_lines(cage: torchcage.Cage, n: int = 24, samples: int = 200) -> list[torch.Tensor]:
    """Horizontal and vertical lines through the polygon's box, kept inside it: ``(k, 2)`` each."""
    lo, hi = cage.vertices.min(0).values, cage.vertices.max(0).values
    t = torch.linspace(0, 1, samples, dtype=torch.float64)
    lines = []
    for s in torch.linspace(0.02, 0.98, n, dtype=torch.float64):
        for axis in (0, 1):
            p = torch.empty(samples, 2, dtype=torch.float64)
            p[:, axis] = lo[axis] + (hi[axis] - lo[axis]) * t
            p[:, 1 - axis] = lo[1 - axis] + (hi[1 - axis] - lo[1 - axis]) * s
            lines.append(p)
    return lines


def _draw_deformation(lines, weights, rest, pose, lo, hi, size, title) -> Image.Image:
    """The deformed grid (polylines, split where a line leaves the polygon) and the posed cage."""
    img = Image.new("RGB", (size, size), (255, 255, 255))
    d = ImageDraw.Draw(img)

    def px(p):
        sx, sy = size / (hi[0] - lo[0]), size / (hi[1] - lo[1])
        return [((float(x) - lo[0]) * sx, (hi[1] - float(y)) * sy) for x, y in p]

    for (line, inside), w in zip(lines, weights, strict=True):
        moved = line + w @ (pose - rest)  # (the displacement form: x + w (V' - V))
        run = []
        for ok, q in zip(inside, moved, strict=True):
            if ok:
                run.append(q)
            elif run:
                if len(run) > 1:
                    d.line(px(run), fill=(70, 110, 170), width=1)
                run = []
        if len(run) > 1:
            d.line(px(run), fill=(70, 110, 170), width=1)
    ring = [*pose, pose[0]]
    d.line(px(ring), fill=(40, 40, 40), width=2)
    d.text((4, 2), title, fill=(0, 0, 0))
    return img


def main(out: str = "coordinate_families.png", size: int = 300) -> None:
    P = [(-1, -1), (1, -1), (1, 1), (0.7, 1), (0.7, -0.7), (-0.7, -0.7), (-0.7, 1), (-1, 1)]
    cage = torchcage.Cage(torch.tensor(P, dtype=torch.float64))
    vertex = 4  # the right arm's inner corner
    lo, hi = [-1.15, -1.15], [1.15, 1.15]
    xs = torch.linspace(lo[0], hi[0], size, dtype=torch.float64)
    ys = torch.linspace(hi[1], lo[1], size, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1).reshape(-1, 2)
    inside = inside_cage(grid, cage)
    lines = [(line, inside_cage(line, cage)) for line in _grid_lines(cage)]
    pts = torch.cat([line[ok] for line, ok in lines])
    solves = {
        "mean value": lambda x: F.mean_value_coordinates(x, cage),
        "maximum entropy": lambda x: F.maximum_entropy_coordinates(x, cage),
        "harmonic": lambda x: F.harmonic_coordinates(x, cage, target_cells=6000),
        "bounded biharmonic": lambda x: F.bounded_biharmonic_weights(x, cage, target_cells=6000),
        "local barycentric": lambda x: F.local_barycentric_coordinates(x, cage, target_cells=3000).to_dense(),
    }
    pose = cage.vertices.clone()
    pose[vertex] += torch.tensor([0.25, 0.45], dtype=torch.float64)
    image = Image.new("RGB", (len(solves) * (size + 8) - 8, 2 * size + 8), (255, 255, 255))
    for k, (name, weights_of) in enumerate(solves.items()):
        w = weights_of(torch.cat([grid[inside], pts]))
        f = torch.zeros(grid.shape[0], dtype=torch.float64)
        f[inside] = w[: int(inside.sum()), vertex]
        image.paste(render_field_2d(10 * f, cage, lo, hi, mask=inside, vertex=vertex, title=f"{name} (x10)"),
                    (k * (size + 8), 0))  # fmt: skip
        wl, parts = w[int(inside.sum()) :], []
        for line, ok in lines:  # every sample of the line: outside ones are skipped when drawing
            full = torch.zeros(line.shape[0], w.shape[1], dtype=torch.float64)
            full[ok], wl = wl[: int(ok.sum())], wl[int(ok.sum()) :]
            parts.append(full)
        panel = _draw_deformation(lines, parts, cage.vertices, pose, lo, hi, size, name)
        image.paste(panel, (k * (size + 8), size + 8))
        print(f"{name}: min {float(w[:, vertex].min()):.3f}, max {float(w[:, vertex].max()):.3f}")
    image.save(out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main(*sys.argv[1:2])
