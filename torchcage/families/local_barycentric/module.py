"""The local barycentric coordinates module: sparse weights, deformation by sparse products."""

from __future__ import annotations

import warnings
from typing import Any

import torch

from torchcage._core.module import CageModule, module_points
from torchcage.cage import Cage
from torchcage.families.local_barycentric.api import local_barycentric_coordinates, solve_local_barycentric
from torchcage.solvers.lbc import LBCResult

__all__ = ["LocalBarycentricCoordinates"]


class LocalBarycentricCoordinates(CageModule):
    """Deform points inside a cage with local barycentric coordinates (sparse weights).

    The weights are computed once (meshing and an ADMM solve, seconds) and stored as the buffers
    ``weight_crow (N + 1,)``, ``weight_col (nnz,)`` (int32) and ``weight_values (nnz,)`` of a sparse
    CSR ``(N, V)`` matrix, saved in the ``state_dict``: 12 bytes per entry instead of 8 per entry of
    a dense matrix. ``forward`` is one sparse product (all poses of a batch at once), differentiable
    with respect to the deformed vertices (measured on FireHydrant, 39k points, 48 cage vertices:
    as fast as the dense mean value product for one pose, 2.6x faster for 16, half the memory).
    The solve's report (iterations, residuals, convergence, objective) is kept in
    ``self.solution`` (not saved).

    Args:
        cage: a closed 2D polygon or 3D triquad cage.
        points: ``(N, D)`` points inside the cage.
        threshold: entries below it are dropped (default ``1e-3 / V``), rows corrected.
        solution: reuse a solve of the same cage (checked against it: another cage raises a
            ``CageError``).
        **options: passed to :func:`torchcage.functional.solve_local_barycentric`
            (``target_cells``, ``domain``, ``weighting``, ``progress``, solver options).

    Shape:
        - Input: ``(*, V, D)`` deformed cage vertices.
        - Output: ``(*, N, D)`` deformed points.

    Examples:
        >>> import torch, torchcage
        >>> cage = torchcage.Cage(torch.tensor([[0.0, 0], [2, 0], [2, 2], [0, 2]], dtype=torch.float64))
        >>> pts = torch.tensor([[0.5, 0.5], [1.0, 1.5]], dtype=torch.float64)
        >>> lbc = torchcage.LocalBarycentricCoordinates(cage, pts, target_cells=200)
        >>> torch.allclose(lbc(cage.vertices * 2 + 1), pts * 2 + 1)
        True
    """

    weight_crow: torch.Tensor
    weight_col: torch.Tensor
    weight_values: torch.Tensor

    def __init__(
        self,
        cage: Cage,
        points: torch.Tensor,
        *,
        threshold: float | None = None,
        solution: LBCResult | None = None,
        **options: Any,
    ) -> None:
        pts = module_points(points, cage)
        if solution is None:
            solution = solve_local_barycentric(cage, **options)
        W = local_barycentric_coordinates(pts, cage, threshold=threshold, solution=solution)
        super().__init__(cage, pts)
        self.solution = solution
        csr = W.to(torch.float64).to_sparse_csr()
        self.register_buffer("weight_crow", csr.crow_indices().to(torch.int32))
        self.register_buffer("weight_col", csr.col_indices().to(torch.int32))
        self.register_buffer("weight_values", csr.values().clone())

    def _csr(self, dtype: torch.dtype) -> torch.Tensor:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
            return torch.sparse_csr_tensor(
                self.weight_crow,
                self.weight_col,
                self.weight_values.to(dtype),
                (self.num_points, self.num_vertices),
                check_invariants=False,
            )

    @property
    def weights(self) -> torch.Tensor:
        """The sparse CSR ``(N, V)`` weight matrix."""
        return self._csr(self.weight_values.dtype)

    def forward(self, vertices: torch.Tensor) -> torch.Tensor:
        """Deformed points ``(*, N, D)`` for deformed cage vertices ``(*, V, D)``."""
        self._check_vertices(vertices, self.weight_values)
        batch = vertices.shape[:-2]
        flat = vertices.reshape(-1, self.num_vertices, self.dim).movedim(0, 1).reshape(self.num_vertices, -1)
        out = self._csr(vertices.dtype) @ flat  # (N, B * D)
        B = flat.shape[1] // self.dim
        return out.reshape(self.num_points, B, self.dim).movedim(1, 0).reshape(*batch, self.num_points, self.dim)

    def extra_repr(self) -> str:
        return super().extra_repr() + f", nnz={self.weight_values.numel()}"
