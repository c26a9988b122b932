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

from torchcage._core.common import as_inputs, check_points, has_tangent, refuse_transforms
from torchcage.cage import Cage
from torchcage.errors import CageError
from torchcage.solvers.domain import Domain, check_solution, domain_for
from torchcage.solvers.harmonic import HarmonicResult, solve_harmonic
from torchcage.solvers.locate import locate_points, outside_points

__all__ = [
    "check_mesh_solution",
    "harmonic_coordinates",
    "interpolate_on_mesh",
    "refuse_options_with_solution",
    "solve_harmonic_coordinates",
]


def refuse_options_with_solution(options: dict[str, Any], what: str) -> None:
    """Raise ``TypeError`` for options given with ``solution=``: they are the solve's, and nothing
    is solved then (they were dropped unread: ``dtype=``, ``target_cells=``, a misspelt name)."""
    if options:
        raise TypeError(
            f"{what} with solution= solves nothing: the options {', '.join(sorted(options))} would be ignored; "
            "drop them, or solve again with them instead of passing solution="
        )


def check_mesh_solution(solution: Any, cage: Cage, what: str) -> None:
    """Raise a :class:`~torchcage.errors.CageError` (or ``TypeError``) when ``solution`` (a
    harmonic, biharmonic or LBC result: ``domain`` and ``weights (Nv, V)``) was not computed for
    ``cage``: another dimension, number of vertices, faces, or rest vertices
    (:func:`torchcage.solvers.domain.check_solution`)."""
    domain, weights = getattr(solution, "domain", None), getattr(solution, "weights", None)
    if not isinstance(domain, Domain) or not isinstance(weights, torch.Tensor):
        raise TypeError(
            f"solution must be the result of a {what} solve (with .domain and .weights), got {type(solution).__name__}"
        )
    if weights.ndim != 2 or weights.shape[0] != domain.vertices.shape[0]:
        raise CageError(
            f"the {what} solution's weights {tuple(weights.shape)} do not match its mesh of "
            f"{domain.vertices.shape[0]} vertices; pass a solution returned by the solver, unchanged"
        )
    check_solution(domain, cage, what, columns=weights.shape[1])


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
        solution: a previous solve for the same cage (checked: a solution of another cage, by
            dimension, vertex count, faces or rest vertices, raises a ``CageError``).
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
    refuse_transforms(points, cage, "harmonic_coordinates")
    lead = points.shape[:-1]
    flat = check_points(points, cage)
    if solution is not None:
        refuse_options_with_solution(options, "harmonic_coordinates")
        check_mesh_solution(solution, cage, "harmonic coordinates")
    result = solution if solution is not None else solve_harmonic_coordinates(cage, **options)
    out = interpolate_on_mesh(flat, result.domain, result.weights, chunk_size, cage)
    return out.to(dtype=flat.dtype, device=flat.device).reshape(*lead, out.shape[1])


def interpolate_on_mesh(
    flat: torch.Tensor, domain: Domain, weights: torch.Tensor, chunk_size: int, cage: Cage | None = None
) -> torch.Tensor:
    """Values ``weights (Nv, V)`` at the mesh vertices interpolated linearly at points ``flat (N, D)``
    through their containing cell (exact point location: :mod:`torchcage.solvers.locate`),
    ``(N, V)`` float64 on the points' device; differentiable with respect to points that require
    grad. Points outside the mesh take the value of the nearest mesh point, with a warning for
    those outside the cage (``cage``; without it, for all of them) beyond the rounding of their
    dtype."""
    x = flat.detach().to(torch.float64).cpu()
    V = weights.shape[1]
    grad = (flat.requires_grad and torch.is_grad_enabled()) or has_tangent(flat)  # (reverse or forward mode)
    parts = []
    outside, farthest = 0, 0.0
    for s in range(0, x.shape[0], chunk_size):
        xs = x[s : s + chunk_size]
        cell, bary, inside, distance = locate_points(xs, domain)
        warn = outside_points(xs, inside, distance, domain, cage, flat.dtype)
        if bool(warn.any()):
            outside += int(warn.sum())
            farthest = max(farthest, float(distance[warn].max()))
        corners = domain.cells[cell]  # (n, D + 1)
        if grad:  # the barycentric coordinates again, differentiable (linear in the point in its cell)
            bary = _differentiable_bary(flat[s : s + chunk_size], domain.vertices[corners], bary, inside)
        parts.append(torch.einsum("nk,nkv->nv", bary, weights[corners].to(bary)))
    if outside:
        v = domain.vertices
        size = float((v.amax(dim=0) - v.amin(dim=0)).norm())
        warnings.warn(
            f"{outside} points lie outside the meshed interior of the cage (up to {farthest:.3g} away, "
            f"{farthest / size:.2g} of its size); they got the coordinates of the nearest point of the mesh",
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
