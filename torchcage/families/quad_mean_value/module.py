"""The quad mean value coordinates module."""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchcage._core.module import DenseWeightsModule, detached, module_points
from torchcage.cage import Cage
from torchcage.families.quad_mean_value.api import quad_mean_value_coordinates

__all__ = ["QuadMeanValueCoordinates"]


class QuadMeanValueCoordinates(DenseWeightsModule):
    """Deform points embedded in a quad or triquad cage with quad mean value coordinates.

    Quads act as bilinear patches (Thiery, Memari, Boubekeur 2018), so a symmetric cage edit gives
    a symmetric deformation, with no artefacts of a triangulation. The coordinates of ``points``
    with respect to the rest ``cage`` are computed once (float64 by default) and stored as the
    buffer ``weights`` ``(N, V)``; ``forward`` is one matrix product, differentiable with respect
    to the deformed vertices. (For gradients with respect to the query points, call
    :func:`torchcage.functional.quad_mean_value_coordinates` on points that require grad.)

    Args:
        cage: a closed 3D cage of triangles and/or valid quads.
        points: ``(N, 3)`` points to embed.
        n: grid parameter of the quad integrals (``(2n+1)^2`` samples per quad; 4 by default).
        chunk_size: points per chunk while computing the weights.
        dtype: dtype of the stored weights (float64 by default).
        progress: show a progress bar while computing the weights, or a callable
            ``progress(done, total)`` (points done so far).
        allow_invalid: compute even if some quads fail the validity predicate (with a warning).
        tol: if given, the quads' defining integrals to this relative tolerance instead of the
            Riemann sum of resolution ``n`` (the coordinates to within about ``tol``; docs/qmvc.md).

    Shape:
        - Input: ``(*, V, 3)`` deformed cage vertices, any leading batch shape.
        - Output: ``(*, N, 3)`` deformed points.

    Examples:
        >>> import torch, torchcage
        >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj"))       # 6 quads
        >>> pts = torch.rand(50, 3, dtype=torch.float64) * 2 - 1
        >>> qmvc = torchcage.QuadMeanValueCoordinates(cage, pts)
        >>> qmvc(torch.stack([cage.vertices, 2 * cage.vertices])).shape
        torch.Size([2, 50, 3])
        >>> torch.allclose(qmvc(cage.vertices), pts)
        True
    """

    def __init__(
        self,
        cage: Cage,
        points: torch.Tensor,
        n: int = 4,
        *,
        chunk_size: int | None = None,
        dtype: torch.dtype = torch.float64,
        progress: bool | Callable[[int, int], None] = False,
        allow_invalid: bool = False,
        tol: float | None = None,
    ) -> None:
        pts = module_points(points, cage)
        cage = detached(cage)
        w = quad_mean_value_coordinates(
            pts, cage, n, chunk_size=chunk_size, dtype=dtype, progress=progress, allow_invalid=allow_invalid, tol=tol
        )
        super().__init__(cage, pts)
        self.n = n
        self.tol = tol
        self.register_buffer("weights", w)

    def extra_repr(self) -> str:
        return super().extra_repr() + (f", n={self.n}" if self.tol is None else f", tol={self.tol:g}")
