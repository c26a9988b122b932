"""The harmonic coordinates module."""

from __future__ import annotations

from typing import Any

import torch

from torchcage._core.module import DenseWeightsModule, detached, module_points
from torchcage.cage import Cage
from torchcage.families.harmonic.api import harmonic_coordinates, solve_harmonic_coordinates
from torchcage.solvers.harmonic import HarmonicResult

__all__ = ["HarmonicCoordinates"]


class HarmonicCoordinates(DenseWeightsModule):
    """Deform points inside a cage with harmonic coordinates (Joshi et al. 2007).

    The coordinates are solved once on a mesh of the cage's interior (P1 finite elements, one sparse
    factorisation for all cage vertices) and interpolated at ``points``; they are stored as the
    dense buffer ``weights`` ``(N, V)`` (harmonic coordinates are positive across the interior:
    nothing to sparsify) and ``forward`` is one matrix product, differentiable with respect to the
    deformed vertices. The solve's report (residual, smallest weight, time) is kept in
    ``self.solution`` (not saved).

    Args:
        cage: a closed 2D polygon or 3D triquad cage.
        points: ``(N, D)`` points inside the cage.
        solution: reuse a solve of the same cage (checked against it: another cage raises a
            ``CageError``).
        dtype: dtype of the stored weights (float64 by default).
        **options: passed to :func:`torchcage.functional.solve_harmonic_coordinates`
            (``target_cells``, ``domain``, ``solver``).

    Shape:
        - Input: ``(*, V, D)`` deformed cage vertices.
        - Output: ``(*, N, D)`` deformed points.

    Examples:
        >>> import torch, torchcage
        >>> cage = torchcage.Cage(torch.tensor([[0.0, 0], [2, 0], [2, 2], [0, 2]], dtype=torch.float64))
        >>> pts = torch.tensor([[0.5, 0.5], [1.0, 1.5]], dtype=torch.float64)
        >>> hc = torchcage.HarmonicCoordinates(cage, pts, target_cells=200)
        >>> torch.allclose(hc(cage.vertices * 2 + 1), pts * 2 + 1)
        True
    """

    def __init__(
        self,
        cage: Cage,
        points: torch.Tensor,
        *,
        solution: HarmonicResult | None = None,
        dtype: torch.dtype = torch.float64,
        **options: Any,
    ) -> None:
        pts = module_points(points, cage)
        cage = detached(cage)
        if solution is None:
            solution = solve_harmonic_coordinates(cage, **options)
        w = harmonic_coordinates(pts, cage, solution=solution).to(dtype)
        super().__init__(cage, pts)
        self.solution = solution
        self.register_buffer("weights", w)

    def extra_repr(self) -> str:
        s = self.solution
        return super().extra_repr() + f", mesh_vertices={s.domain.vertices.shape[0]}, min_weight={s.min_weight:.2g}"
