"""The maximum entropy coordinates module."""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchcage._core.module import DenseWeightsModule, detached, module_points
from torchcage.cage import Cage
from torchcage.families.maximum_entropy.api import maximum_entropy_coordinates

__all__ = ["MaximumEntropyCoordinates"]


class MaximumEntropyCoordinates(DenseWeightsModule):
    """Deform points inside a cage with maximum entropy coordinates (Hormann & Sukumar 2008):
    nonnegative coordinates closest to a prior (by default the mean value or quad mean value
    coordinates), so that no part of the shape moves against a handle's pull.

    The coordinates of ``points`` with respect to the rest ``cage`` are computed once (float64) by
    :func:`torchcage.functional.maximum_entropy_coordinates` and stored as the buffer ``weights``
    ``(N, V)``, with the Newton steps per point in ``iterations``; ``forward`` is one matrix
    product, differentiable with respect to the deformed vertices.

    Args:
        cage: a closed 2D polygon or 3D cage of triangles and/or quads (one cage, not a batch).
        points: ``(N, D)`` points inside the cage.
        prior: ``"mvc"``, ``"qmvc"``, ``"uniform"`` or masses ``(N, V)`` (see the function).
        n: grid parameter of the ``"qmvc"`` prior.
        tol: linear precision to reach, over the cage size.
        max_iter: most Newton steps per point.
        chunk_size: points per chunk while computing the weights.
        dtype: dtype of the stored weights (float64 by default).
        progress: show a progress bar while computing the weights, or a callable
            ``progress(done, total)`` (points done so far).

    Shape:
        - Input: ``(*, V, D)`` deformed cage vertices, any leading batch shape.
        - Output: ``(*, N, D)`` deformed points.

    Examples:
        >>> import torch, torchcage
        >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj"))
        >>> pts = torch.rand(20, 3, dtype=torch.float64) * 1.8 - 0.9
        >>> mec = torchcage.MaximumEntropyCoordinates(cage, pts)
        >>> bool((mec.weights >= 0).all()), torch.allclose(mec(cage.vertices), pts)
        (True, True)
    """

    def __init__(
        self,
        cage: Cage,
        points: torch.Tensor,
        prior: str | torch.Tensor | None = None,
        *,
        n: int = 4,
        tol: float = 1e-13,
        max_iter: int = 50,
        chunk_size: int | None = None,
        dtype: torch.dtype = torch.float64,
        progress: bool | Callable[[int, int], None] = False,
    ) -> None:
        pts = module_points(points, cage)
        cage = detached(cage)
        sol = maximum_entropy_coordinates(
            pts, cage, prior, n=n, tol=tol, max_iter=max_iter, chunk_size=chunk_size, dtype=dtype,
            progress=progress, return_info=True,
        )  # fmt: skip
        super().__init__(cage, pts)
        self.prior = prior if isinstance(prior, str) or prior is None else "masses"
        self.register_buffer("weights", sol.weights)
        self.register_buffer("iterations", sol.iterations)

    def extra_repr(self) -> str:
        return super().extra_repr() + f", prior={self.prior!r}"
