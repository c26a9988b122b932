"""The comparison picture of Green coordinates for triquad cages (the QGC paper's Fig. 4 setting).

The bundled bar's quad cage is stretched to 1.6 times its length and its top twisted by 70
degrees. Left to right: rest; quad mean value coordinates (QMVC: symmetric, but the cross-section
thins where the cage stretches); Green coordinates on the triangulated cage (GC: quasi-conformal,
the bar thickens with the stretch, but the split diagonals show); Green coordinates for triquad
cages (QGC: quasi-conformal and free of the triangulation). The colour is the local surface
stretch (log2 of the faces' area ratio) relative to its median: blue is less stretched
than typical, red more; a uniform colour is an even deformation.

Writes ``qgc_comparison.png`` into the output folder.

Usage: ``python examples/quad_green.py [out_dir]``
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import torch

import torchcage
from torchcage.viz import Panel, render_panels


def main(out_dir: str = ".") -> None:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cage = torchcage.load_cage(torchcage.data.path("bar_cage.obj"))
    verts, faces = torchcage.load_mesh(torchcage.data.path("bar.obj"))
    verts = verts.to(torch.float64)
    v = cage.vertices
    lo, hi = v.min(0).values, v.max(0).values
    axis = int(torch.argmax(hi - lo))
    a, b = [k for k in range(3) if k != axis]
    centre = (lo + hi) / 2
    t = (v[:, axis] - lo[axis]) / (hi[axis] - lo[axis])  # 0 at the bottom, 1 at the top
    pose = v.clone()
    pose[:, axis] = lo[axis] + 1.6 * (v[:, axis] - lo[axis])
    ang = math.radians(70.0) * t
    da, db = v[:, a] - centre[a], v[:, b] - centre[b]
    pose[:, a] = centre[a] + torch.cos(ang) * da - torch.sin(ang) * db
    pose[:, b] = centre[b] + torch.sin(ang) * da + torch.cos(ang) * db

    def face_areas(x: torch.Tensor) -> torch.Tensor:
        p = x[faces]
        return torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1).norm(dim=-1)

    rest_area = face_areas(verts)
    panels = [Panel(verts, faces, v, cage.unique_edges(), "rest")]
    models = (
        ("QMVC (quads)", torchcage.QuadMeanValueCoordinates(cage, verts), cage),
        ("GC (triangulated)", torchcage.GreenCoordinates(cage.triangulated(), verts), cage.triangulated()),
        ("QGC (quads)", torchcage.QuadGreenCoordinates(cage, verts), cage),
    )
    for name, module, shown in models:
        x = module(pose).detach()
        ratio = torch.log2(face_areas(x) / rest_area)  # per face; vertices take the mean of their faces
        vc = torch.zeros(verts.shape[0], dtype=torch.float64)
        vc.index_add_(0, faces.reshape(-1), ratio.repeat_interleave(3))
        vc = vc / torch.bincount(faces.reshape(-1), minlength=verts.shape[0]).clamp_min(1)
        vc = vc - vc.median()  # relative to the typical stretch: how uneven the deformation is
        s = ((vc + 0.5) / 1.0).clamp(0, 1)[:, None]  # -0.5 .. 0.5 (log2) -> blue .. red
        colors = (1 - s) * torch.tensor([0.25, 0.45, 0.85], dtype=torch.float64) + s * torch.tensor([0.9, 0.3, 0.2])
        panels.append(Panel(x, faces, pose, shown.unique_edges(), name, vertex_colors=colors))
        print(f"{name}: surface area x{float(face_areas(x).sum() / rest_area.sum()):.2f}")
    render_panels(panels, size=320, azimuth=60.0, elevation=20.0).save(out / "qgc_comparison.png")
    print(f"wrote {out / 'qgc_comparison.png'}")


if __name__ == "__main__":
    main(*sys.argv[1:])
