"""Generate the small data bundled in ``torchcage/data`` (run once; the outputs are committed).

- ``bar.obj``: a ridged, bulging bar made from a subdivided icosahedron (2,562 vertices).
- ``bar_cage.obj``: a 16-vertex, 14-quad box cage around it; ``bar_cage_deformed.obj``: the cage
  bent and twisted.
- ``blob2d.obj``: a 2D polygon cage (12 vertices, counter-clockwise).

Usage: ``python examples/make_demo_data.py``
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

import torchcage
from torchcage.testing import icosphere as _icosphere

OUT = Path(__file__).resolve().parents[1] / "torchcage" / "data"


def icosphere(level: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit geodesic sphere ``(vertices, triangles)``: :func:`torchcage.testing.icosphere`."""
    sphere = _icosphere(level)
    return sphere.vertices, sphere.triangles


def bar() -> tuple[torch.Tensor, torch.Tensor]:
    u, f = icosphere(4)
    z = 1.5 * u[:, 2]
    phi = torch.atan2(u[:, 1], u[:, 0])
    radius = (0.36 + 0.07 * torch.sin(2.2 * math.pi * z / 1.5)) * (1 + 0.08 * torch.cos(8 * phi))
    return torch.stack([u[:, 0] * radius, u[:, 1] * radius, z], dim=1), f


def cage() -> torchcage.Cage:
    zs = [-1.65, -0.55, 0.55, 1.65]
    ring = [[-0.6, -0.6], [0.6, -0.6], [0.6, 0.6], [-0.6, 0.6]]
    v = [[x, y, z] for z in zs for x, y in ring]
    quads = []
    for k in range(3):
        for i in range(4):
            j = (i + 1) % 4
            quads.append([4 * k + i, 4 * k + j, 4 * (k + 1) + j, 4 * (k + 1) + i])
    quads += [[0, 3, 2, 1], [12, 13, 14, 15]]
    return torchcage.Cage(torch.tensor(v, dtype=torch.float64), quads)


def deformed(c: torchcage.Cage) -> torch.Tensor:
    """Bend the bar towards +x and twist it: each ring is rotated about z and y and shifted."""
    v = c.vertices.clone()
    for k, (shift, twist, tilt) in enumerate([(0.0, 0.0, 0.0), (0.12, 0.15, 0.15), (0.55, 0.45, 0.45),
                                               (1.2, 0.8, 0.75)]):  # fmt: skip
        ring = v[4 * k : 4 * k + 4]
        centre = ring.mean(0)
        local = ring - centre
        cz, sz = math.cos(twist), math.sin(twist)
        rz = torch.tensor([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]], dtype=torch.float64)
        cy, sy = math.cos(tilt), math.sin(tilt)
        ry = torch.tensor([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]], dtype=torch.float64)
        v[4 * k : 4 * k + 4] = local @ (ry @ rz).T + centre + torch.tensor([shift, 0, -0.25 * shift]).double()
    return v


def blob2d() -> torchcage.Cage:
    ang = torch.arange(12, dtype=torch.float64) * 2 * math.pi / 12
    r = 1.0 + 0.35 * torch.cos(3 * ang) + 0.1 * torch.sin(5 * ang)
    return torchcage.Cage(torch.stack([r * torch.cos(ang), 0.8 * r * torch.sin(ang)], dim=1))


def main() -> None:
    v, f = bar()
    c = cage()
    inside = torchcage.functional.mean_value_coordinates(v, c.triangulated()).min().item()
    print(f"bar: {v.shape[0]} vertices, {f.shape[0]} faces; min coordinate {inside:.3f}")
    torchcage.save_mesh(OUT / "bar.obj", v, f)
    torchcage.save_cage(OUT / "bar_cage.obj", c)
    torchcage.save_cage(OUT / "bar_cage_deformed.obj", c, deformed(c))
    torchcage.save_cage(OUT / "blob2d.obj", blob2d())
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
