r"""Harmonic coordinates (Joshi et al. 2007): the public front end.

The cage's interior is meshed (:mod:`torchcage.solvers.domain`), the harmonic extension of the
cage's basis functions is solved on that mesh (:mod:`torchcage.solvers.harmonic`), and the values
at the mesh vertices are interpolated linearly at the query points: a dense ``(N, V)`` tensor
(harmonic coordinates are positive across the whole interior, so nothing is sparse).
"""

from __future__ import annotations

import warnings
from typing import Any

import torch

from ..cage import Cage
from ..solvers.domain import Domain, domain_for
from ..solvers.harmonic import HarmonicResult, solve_harmonic
from ._common import as_inputs, check_points
from .local_barycentric import locate

__all__ = ["harmonic_coordinates", "interpolate_on_mesh", "solve_harmonic_coordinates"]


def solve_harmonic_coordinates(
    cage: Cage,
    *,
    target_cells: int = 20000,
    domain: tuple[torch.Tensor, torch.Tensor] | Domain | None = None,
    solver: str = "auto",
    **options: Any,
) -> HarmonicResult:
    """Mesh the cage's interior and solve for harmonic coordinates at the mesh vertices.

    Args:
        cage: a closed 2D polygon or 3D triquad cage (quads get bilinear boundary values).
        target_cells: about how many triangles / tetrahedra to mesh the interior with.
        domain: your own mesh instead, ``(vertices (Nv, D), cells (C, D + 1))`` whose boundary
            vertices lie on the cage (triangle cages and polygons), or a :class:`Domain`.
        solver: ``"auto"`` (cholespy's sparse Cholesky where installed, else scipy's sparse LU),
            ``"cholesky"``, ``"lu"`` or ``"cg"`` (torch conjugate gradients).
        **options: ``tol`` and ``max_iter`` of ``"cg"``.

    Returns:
        The :class:`~torchcage.solvers.harmonic.HarmonicResult` (weights at the mesh vertices,
        the solve's residual, the smallest weight).
    """
    dom = domain_for(cage, target_cells, domain, "harmonic coordinates")
    return solve_harmonic(dom, solver, **options)


def harmonic_coordinates(
    points: torch.Tensor,
    cage: Cage,
    *,
    solution: HarmonicResult | None = None,
    chunk_size: int = 1 << 16,
    **options: Any,
) -> torch.Tensor:
    """Harmonic coordinates of points inside a cage, ``(*, V)``.

    Smooth inside the cage, equal to the cage's basis functions on it (linear on edges and
    triangles, bilinear on quads, Lagrange at the vertices), partition of unity and linear
    precision exact (P1 elements reproduce linear functions), nonnegative where the mesh obeys the
    discrete maximum principle. Computing them means meshing the interior and a sparse solve:
    pass ``solution=`` (from :func:`solve_harmonic_coordinates`) to reuse one for more points.

    Args:
        points: ``(*, D)`` points inside the cage (points outside get the coordinates of the
            nearest point of the meshed interior, with a warning).
        cage: a closed 2D polygon or 3D triquad cage.
        solution: a previous solve for the same cage.
        chunk_size: points per chunk.
        **options: passed to :func:`solve_harmonic_coordinates` (``target_cells``, ``domain``,
            ``solver``, ...).

    Returns:
        ``(*, V)`` coordinates in the points' dtype and device; differentiable with respect to
        points that require grad (piecewise linear: constant gradients in each cell).

    Examples:
        >>> import torch, torchcage
        >>> from torchcage import functional as F
        >>> poly = torchcage.Cage(torch.tensor([[0.0, 0], [2, 0], [2, 1], [1, 1.5], [0, 1]], dtype=torch.float64))
        >>> x = torch.tensor([[0.5, 0.5], [1.5, 0.7]], dtype=torch.float64)
        >>> w = F.harmonic_coordinates(x, poly, target_cells=400)
        >>> torch.allclose(w @ poly.vertices, x), torch.allclose(w.sum(1), torch.ones(2, dtype=torch.float64))
        (True, True)
    """
    points, cage = as_inputs(points, cage)
    lead = points.shape[:-1]
    flat = check_points(points, cage)
    result = solution if solution is not None else solve_harmonic_coordinates(cage, **options)
    out = interpolate_on_mesh(flat, result.domain, result.weights, chunk_size)
    return out.to(dtype=flat.dtype, device=flat.device).reshape(*lead, out.shape[1])


def interpolate_on_mesh(flat: torch.Tensor, domain: Domain, weights: torch.Tensor, chunk_size: int) -> torch.Tensor:
    """Values ``weights (Nv, V)`` at the mesh vertices interpolated linearly at points ``flat (N, D)``
    through their containing cell, ``(N, V)`` float64 on the points' device; differentiable with
    respect to points that require grad. Points outside the mesh take the value of the nearest
    mesh point, with a warning."""
    x = flat.detach().to(torch.float64).cpu()
    V = weights.shape[1]
    grad = flat.requires_grad and torch.is_grad_enabled()
    parts = []
    outside = 0
    for s in range(0, x.shape[0], chunk_size):
        cell, bary, inside = locate(x[s : s + chunk_size], domain)
        outside += int((~inside).sum())
        corners = domain.cells[cell]  # (n, D + 1)
        if grad:  # the barycentric coordinates again, differentiable (linear in the point in its cell)
            bary = _differentiable_bary(flat[s : s + chunk_size], domain.vertices[corners], bary, inside)
        parts.append(torch.einsum("nk,nkv->nv", bary, weights[corners].to(bary)))
    if outside:
        warnings.warn(
            f"{outside} points lie outside the meshed interior of the cage; they got the coordinates of "
            "the nearest point of the mesh",
            stacklevel=3,
        )
    return torch.cat(parts) if parts else torch.zeros(0, V, dtype=torch.float64)


def _differentiable_bary(x: torch.Tensor, p: torch.Tensor, bary: torch.Tensor, inside: torch.Tensor) -> torch.Tensor:
    """Barycentric coordinates ``(n, D + 1)`` of points ``x`` ``(n, D)`` (with their graph) in
    cells with corners ``p`` ``(n, D + 1, D)``; points outside the mesh keep the clamped ``bary``
    (constant: the value of the nearest mesh point)."""
    p = p.to(device=x.device, dtype=torch.float64)
    E = (p[:, 1:] - p[:, :1]).transpose(1, 2)  # (n, D, D)
    b = torch.linalg.solve(E, (x.to(torch.float64) - p[:, 0])[..., None])[..., 0]
    full = torch.cat([1 - b.sum(-1, keepdim=True), b], dim=-1)
    return torch.where(inside.to(x.device)[:, None], full, bary.to(x.device))
