"""The bounded biharmonic weights module."""

from __future__ import annotations

from typing import Any

import torch

from torchcage._core.module import DenseWeightsModule, detached, module_points
from torchcage.cage import Cage
from torchcage.families.biharmonic.api import bounded_biharmonic_weights, solve_bounded_biharmonic_weights
from torchcage.solvers.biharmonic import BBWResult

__all__ = ["BoundedBiharmonicWeights"]


class BoundedBiharmonicWeights(DenseWeightsModule):
    """Deform points inside a cage with bounded biharmonic weights (Jacobson et al. 2011).

    The weights are solved once on a mesh of the cage's interior (one box-constrained quadratic
    program per cage vertex, ADMM with one sparse factorisation, a certified objective gap) and
    interpolated at ``points``; they are stored as the dense buffer ``weights`` ``(N, V)`` and
    ``forward`` is one matrix product, differentiable with respect to the deformed vertices.

    The weights are nonnegative, bounded by one and a partition of unity, but they have no linear
    precision: ``weights @ rest_vertices`` is not ``points``. So by default the module moves each
    point by the weighted **displacements** of the cage vertices, ``x + weights @ (V' - V)``, which
    is linear blend skinning with the cage vertices as translating handles (Jacobson et al. 2011):
    the rest cage gives back the points exactly and translations are reproduced. With
    ``displacements=False`` it returns ``weights @ V'``. The solve's report (gaps, iterations,
    time) is kept in ``self.solution`` (not saved).

    Args:
        cage: a closed 2D polygon or 3D triquad cage.
        points: ``(N, D)`` points inside the cage.
        solution: reuse a solve of the same cage (checked against it: another cage raises a
            ``CageError``).
        dtype: dtype of the stored weights (float64 by default).
        displacements: deform by the cage vertices' displacements (the default; keeps the rest pose
            exact), or by their positions (``weights @ V'``).
        **options: passed to :func:`torchcage.functional.solve_bounded_biharmonic_weights`
            (``target_cells``, ``domain``, ``tol``, ``progress``).

    Shape:
        - Input: ``(*, V, D)`` deformed cage vertices.
        - Output: ``(*, N, D)`` deformed points.

    Examples:
        >>> import torch, torchcage
        >>> cage = torchcage.Cage(torch.tensor([[0.0, 0], [2, 0], [2, 2], [0, 2]], dtype=torch.float64))
        >>> pts = torch.tensor([[0.5, 0.5], [1.0, 1.5]], dtype=torch.float64)
        >>> bbw = torchcage.BoundedBiharmonicWeights(cage, pts, target_cells=200)
        >>> torch.allclose(bbw(cage.vertices), pts), torch.allclose(bbw(cage.vertices + 1), pts + 1)
        (True, True)
    """

    def __init__(
        self,
        cage: Cage,
        points: torch.Tensor,
        *,
        solution: BBWResult | None = None,
        dtype: torch.dtype = torch.float64,
        displacements: bool = True,
        **options: Any,
    ) -> None:
        pts = module_points(points, cage)
        cage = detached(cage)
        if solution is None:
            solution = solve_bounded_biharmonic_weights(cage, **options)
        w = bounded_biharmonic_weights(pts.to(torch.float64), cage, solution=solution)  # (float64 whatever x's)
        super().__init__(cage, pts)
        self.solution = solution
        self.displacements = bool(displacements)
        self.register_buffer("weights", w.to(dtype))
        # x - weights @ V (float64): added to weights @ V' it gives x + weights @ (V' - V)
        offset = pts.to(torch.float64) - w @ cage.vertices.to(torch.float64) if displacements else None
        self.register_buffer("offset", None if offset is None else offset.to(dtype))

    def forward(self, vertices: torch.Tensor) -> torch.Tensor:
        """Deformed points ``(*, N, D)`` for deformed cage vertices ``(*, V, D)``."""
        moved = super().forward(vertices)
        return moved if self.offset is None else moved + self.offset.to(moved.dtype)

    def extra_repr(self) -> str:
        s = self.solution
        return (
            super().extra_repr()
            + f", mesh_vertices={s.domain.vertices.shape[0]}, gap={float(s.gap.max()):.2g}, "
            + f"displacements={self.displacements}"
        )
