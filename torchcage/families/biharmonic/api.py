r"""Bounded biharmonic weights (Jacobson et al. 2011): the public front end.

The cage's interior is meshed (:mod:`torchcage.solvers.domain`, the mesh of harmonic and local
barycentric coordinates), the weights are solved at the mesh vertices
(:mod:`torchcage.solvers.biharmonic`) and interpolated linearly at the query points: a dense
``(N, V)`` tensor.
"""

from __future__ import annotations

from typing import Any

import torch

from torchcage._core.common import as_inputs, check_points, refuse_transforms
from torchcage.cage import Cage
from torchcage.families.harmonic.api import check_mesh_solution, interpolate_on_mesh, refuse_options_with_solution
from torchcage.solvers.biharmonic import BBWResult, solve_bbw
from torchcage.solvers.domain import Domain, domain_for

__all__ = ["bounded_biharmonic_weights", "solve_bounded_biharmonic_weights"]


def solve_bounded_biharmonic_weights(
    cage: Cage,
    *,
    target_cells: int = 20000,
    domain: tuple[torch.Tensor, torch.Tensor] | Domain | None = None,
    **options: Any,
) -> BBWResult:
    """Mesh the cage's interior and solve for bounded biharmonic weights at the mesh vertices.

    Args:
        cage: a closed 2D polygon or 3D triquad cage (quads get bilinear boundary values).
        target_cells: about how many triangles / tetrahedra to mesh the interior with.
        domain: your own mesh instead, ``(vertices (Nv, D), cells (C, D + 1))`` whose boundary
            vertices lie on the cage (triangle cages and polygons), or a :class:`Domain`.
        **options: passed to :func:`torchcage.solvers.biharmonic.solve_bbw` (``tol``, the certified
            relative objective gap, default 1e-5; ``max_iter``; ``solver``; ``progress``).

    Returns:
        The :class:`~torchcage.solvers.biharmonic.BBWResult` (weights at the mesh vertices, the
        certified gaps, iterations, time).

    Examples:
        >>> import torch, torchcage
        >>> from torchcage import functional as F
        >>> poly = torchcage.Cage(torch.tensor([[0.0, 0], [2, 0], [2, 1], [1, 1.5], [0, 1]], dtype=torch.float64))
        >>> sol = F.solve_bounded_biharmonic_weights(poly, target_cells=400)
        >>> sol.converged, bool(sol.weights.min() >= 0)
        (True, True)
    """
    dom = domain_for(cage, target_cells, domain, "bounded biharmonic weights")
    return solve_bbw(dom, **options)


def bounded_biharmonic_weights(
    points: torch.Tensor,
    cage: Cage,
    *,
    solution: BBWResult | None = None,
    chunk_size: int = 1 << 16,
    **options: Any,
) -> torch.Tensor:
    """Bounded biharmonic weights of points inside a cage, ``(*, V)``.

    Each cage vertex's weight minimises the biharmonic energy with the cage's basis functions as
    boundary values (barycentric on triangles, bilinear on quads, Lagrange at the vertices) and
    ``0 <= w <= 1``; the weights are then divided by their sum (Jacobson et al. 2011). So they are
    smooth, nonnegative, bounded by one and a partition of unity, but, unlike harmonic
    coordinates, **without linear precision** (``w @ V`` is not ``x``): deform with the cage
    vertices' displacements, ``x + w @ (V' - V)``, as
    :class:`~torchcage.BoundedBiharmonicWeights` does. Pass ``solution=`` (from
    :func:`solve_bounded_biharmonic_weights`) to reuse a solve for more points.

    Args:
        points: ``(*, D)`` points inside the cage (points outside get the weights of the nearest
            point of the meshed interior, with a warning).
        cage: a closed 2D polygon or 3D triquad cage.
        solution: a previous solve for the same cage (checked: a solution of another cage, by
            dimension, vertex count, faces or rest vertices, raises a ``CageError``).
        chunk_size: points per chunk.
        **options: passed to :func:`solve_bounded_biharmonic_weights` (``target_cells``,
            ``domain``, ``tol``, ...).

    Returns:
        ``(*, V)`` weights in the points' dtype and device; differentiable with respect to points
        that require grad (piecewise linear: constant gradients in each cell).

    Examples:
        >>> import torch, torchcage
        >>> from torchcage import functional as F
        >>> poly = torchcage.Cage(torch.tensor([[0.0, 0], [2, 0], [2, 1], [1, 1.5], [0, 1]], dtype=torch.float64))
        >>> w = F.bounded_biharmonic_weights(torch.tensor([[0.5, 0.5], [1.5, 0.7]], dtype=torch.float64), poly,
        ...                                  target_cells=400)
        >>> bool(w.min() >= 0), torch.allclose(w.sum(1), torch.ones(2, dtype=torch.float64))
        (True, True)
    """
    points, cage = as_inputs(points, cage)
    refuse_transforms(points, cage, "bounded_biharmonic_weights")
    lead = points.shape[:-1]
    flat = check_points(points, cage)
    if solution is not None:
        refuse_options_with_solution(options, "bounded_biharmonic_weights")
        check_mesh_solution(solution, cage, "bounded biharmonic weights")
    result = solution if solution is not None else solve_bounded_biharmonic_weights(cage, **options)
    out = interpolate_on_mesh(flat, result.domain, result.weights, chunk_size, cage)
    return out.to(dtype=flat.dtype, device=flat.device).reshape(*lead, out.shape[1])
