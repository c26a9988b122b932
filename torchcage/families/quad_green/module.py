"""The Green coordinates module for triquad cages."""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchcage._core.module import CageModule, detached, module_points
from torchcage.cage import Cage
from torchcage.families.quad_green.api import quad_green_coordinates
from torchcage.families.quad_green.deformation import quad_corner_factors, quad_green_deformation

__all__ = ["QuadGreenCoordinates", "quad_corner_factors"]


#: The regular (u, v) pattern of Eq. 22's averages: 5 x 5 cell centres.
class QuadGreenCoordinates(CageModule):
    """Deform points inside a triquad cage with Green coordinates for triquad cages (QGC).

    Quads stay bilinear patches (no triangulation, so symmetric edits stay symmetric) and the
    deformation is quasi-conformal like triangle Green coordinates. ``phi`` ``(N, V)`` and ``psi``
    ``(N, T + 4Q)`` are computed once at rest (buffers). ``forward`` returns
    ``phi @ V' + psi[:, :T] @ (s_t n'_t) + sum_{q,k} psi[:, T+4q+k] sigma_{q,k} N'_{q,k}`` with
    Lipman's stretch ``s_t`` on triangles, the deformed corner normals ``N'_{q,k}`` and the
    per-corner factors ``sigma`` (Eq. 23), all differentiable with respect to the deformed vertices.

    Args:
        cage: a closed 3D cage of triangles and/or valid quads.
        points: ``(N, 3)`` points inside the cage (points outside it warn with their count
            (:class:`torchcage.OutsideCageWarning`)).
        n: tessellation parameter of the coordinates (see
            :func:`torchcage.functional.quad_green_coordinates`).
        correction: ``"conformal"`` (default): the corner factors of Eq. 22, which mimic Lipman's
            stretch; rotations, uniform scalings and translations are reproduced. ``"area"``: the
            area-based Neumann condition (factors 1): rigid motions are reproduced, scalings not.
        chunk_size: points per chunk while computing the coordinates.
        dtype: dtype of the stored coordinates (float64 by default).
        allow_invalid: compute even if some quads fail the validity predicate (with a warning).
        progress: ``True`` for a progress bar while computing the coordinates, or a callable
            ``progress(done, total)`` (points done so far).
        tol: if given, the quads' integrals to this relative tolerance instead of the Riemann sum
            of parameter ``n`` (docs/green.md).

    Shape:
        - Input: ``(*, V, 3)`` deformed cage vertices.
        - Output: ``(*, N, 3)`` deformed points.

    Examples:
        >>> import torch, torchcage
        >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj"))
        >>> pts = torch.rand(20, 3, dtype=torch.float64) * 1.6 - 0.8
        >>> qgc = torchcage.QuadGreenCoordinates(cage, pts)
        >>> torch.allclose(qgc(cage.vertices), pts)
        True
        >>> torch.allclose(qgc(2 * cage.vertices + 1), 2 * pts + 1)
        True
    """

    phi: torch.Tensor
    psi: torch.Tensor
    triangles: torch.Tensor
    quads: torch.Tensor

    def __init__(
        self,
        cage: Cage,
        points: torch.Tensor,
        n: int = 2,
        *,
        correction: str = "conformal",
        chunk_size: int | None = None,
        dtype: torch.dtype = torch.float64,
        allow_invalid: bool = False,
        progress: bool | Callable[[int, int], None] = False,
        tol: float | None = None,
    ) -> None:
        if correction not in ("conformal", "area"):
            raise ValueError(f"correction must be 'conformal' or 'area', got {correction!r}")
        pts = module_points(points, cage)
        cage = detached(cage)
        phi, psi = quad_green_coordinates(
            pts, cage, n, chunk_size=chunk_size, dtype=dtype, allow_invalid=allow_invalid, progress=progress, tol=tol
        )
        super().__init__(cage, pts)
        self.correction = correction
        self.tol = tol
        self.register_buffer("phi", phi)
        self.register_buffer("psi", psi)
        self.register_buffer("triangles", cage.triangles.clone())
        self.register_buffer("quads", cage.quads.clone())

    def forward(self, vertices: torch.Tensor) -> torch.Tensor:
        """Deformed points ``(*, N, 3)`` for deformed cage vertices ``(*, V, 3)``."""
        self._check_vertices(vertices, self.phi)
        return quad_green_deformation(
            self.phi, self.psi, self.rest_vertices, vertices, self.triangles, self.quads, self.correction
        )

    def extra_repr(self) -> str:
        tol = "" if self.tol is None else f", tol={self.tol:g}"
        return super().extra_repr() + f", correction={self.correction!r}" + tol
