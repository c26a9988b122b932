"""Picture: the local rotation and stretch of a Green deformation, from its exact Jacobian.

The bundled bar, bent by its deformed cage. At every mesh vertex the Jacobian ``J`` of the
deformation (:meth:`torchcage.GreenCoordinates.jacobian`, closed-form gradients of the
coordinates) is split by its singular values ``s1 >= s2 >= s3`` and polar rotation. Panels: the
rotation angle; the Green deformation's anisotropy ``s1 / s3`` (1 for a conformal map: Green
coordinates are quasi-conformal); and the same anisotropy for mean value coordinates on the same
cage and pose, on the same colour scale.

Usage: ``python examples/green_jacobian.py [out.png]`` (default: docs/images/green_jacobian.png).
Needs matplotlib (its colour maps): ``pip install 'torchcage[examples]'``.
"""

from __future__ import annotations

import sys

try:
    import matplotlib
except ModuleNotFoundError as err:  # an optional dependency: say which extra brings it
    sys.exit(
        f"examples/green_jacobian.py needs {err.name}, which is not installed: pip install 'torchcage[examples]' "
        "(or pip install matplotlib)"
    )
import torch

import torchcage
from torchcage.viz import Panel, render_panels

f64 = torch.float64


def _colours(values: torch.Tensor, lo: float, hi: float, cmap: str) -> torch.Tensor:
    """``(N, 3)`` RGB of ``values`` on ``[lo, hi]``."""
    t = ((values - lo) / max(hi - lo, 1e-12)).clamp(0, 1)
    return torch.as_tensor(matplotlib.colormaps[cmap](t.numpy())[:, :3])


def main(out: str = "docs/images/green_jacobian.png", size: int = 420) -> None:
    verts, faces = torchcage.load_mesh(torchcage.data.path("bar.obj"))
    quads = torchcage.load_cage(torchcage.data.path("bar_cage.obj"))
    cage, edges = quads.triangulated().to(f64), quads.unique_edges()
    posed = torchcage.load_cage(torchcage.data.path("bar_cage_deformed.obj")).vertices.to(f64)
    verts = verts.to(f64)
    gc = torchcage.GreenCoordinates(cage, verts, store_derivatives=1)
    mvc = torchcage.MeanValueCoordinates(cage, verts, store_derivatives=1)
    J_gc, J_mvc = gc.jacobian(posed), mvc.jacobian(posed)
    U, S, Vh = torch.linalg.svd(J_gc)
    angle = torch.rad2deg(torch.arccos(((torch.einsum("nii->n", U @ Vh) - 1) / 2).clamp(-1, 1)))
    aniso_gc = S[:, 0] / S[:, 2]
    S_mvc = torch.linalg.svdvals(J_mvc)
    aniso_mvc = S_mvc[:, 0] / S_mvc[:, 2]
    hi = float(torch.quantile(torch.cat([aniso_gc, aniso_mvc]), 0.99))
    panels = [
        Panel(gc(posed), faces, posed, edges, title=f"GC rotation 0..{float(angle.max()):.0f} deg",
              vertex_colors=_colours(angle, 0, float(angle.max()), "viridis")),
        Panel(gc(posed), faces, posed, edges, title=f"GC s1/s3: median {float(aniso_gc.median()):.2f}",
              vertex_colors=_colours(aniso_gc, 1, hi, "magma_r")),
        Panel(mvc(posed), faces, posed, edges, title=f"MVC s1/s3: median {float(aniso_mvc.median()):.2f}",
              vertex_colors=_colours(aniso_mvc, 1, hi, "magma_r")),
    ]  # fmt: skip
    render_panels(panels, size=size, azimuth=20, elevation=25).save(out)
    print(
        f"wrote {out}: GC rotation max {float(angle.max()):.1f} deg, anisotropy s1/s3 GC median "
        f"{float(aniso_gc.median()):.3f} max {float(aniso_gc.max()):.3f}, MVC median {float(aniso_mvc.median()):.3f} "
        f"max {float(aniso_mvc.max()):.3f}"
    )


if __name__ == "__main__":
    main(*sys.argv[1:2])
