"""Green deformation: coordinates and a deformed cage to deformed points, with Lipman's stretch
factors (the modules' ``forward`` and :func:`torchcage.deform`)."""

from __future__ import annotations

import torch

from torchcage.families.green.stretch import stretched_normals, stretched_triangle_normals

__all__ = ["green_deformation"]


def green_deformation(
    phi: torch.Tensor, psi: torch.Tensor, rest: torch.Tensor, deformed: torch.Tensor, faces: torch.Tensor
) -> torch.Tensor:
    """``phi @ V' + psi @ (s n')``: Green deformation with Lipman's stretch factors (3D; the edge
    stretch ``|a'| / |a|`` in 2D), differentiable with respect to everything.

    Args:
        phi: ``(*B, N, V)``; psi: ``(*B, N, T)`` (``T`` triangles, or edges in 2D).
        rest: ``(*B, V, D)`` rest vertices; deformed: ``(*, *B, V, D)``.
        faces: ``(T, 3)`` triangles, or ``(E, 2)`` edges in 2D.

    Returns:
        ``(*, *B, N, D)`` deformed points.
    """
    dt = deformed.dtype
    if deformed.shape[-1] == 2:
        sn = stretched_normals(rest, deformed, faces)
    else:
        sn = stretched_triangle_normals(rest, deformed, faces)
    return torch.matmul(phi.to(dt), deformed) + torch.matmul(psi.to(dt), sn)
