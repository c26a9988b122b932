"""The mean value coordinates module."""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchcage._core.module import DenseWeightsModule, detached, module_points
from torchcage.cage import Cage
from torchcage.families.mean_value.api import mean_value_coordinates
from torchcage.families.mean_value.derivatives import mean_value_derivatives

__all__ = ["MeanValueCoordinates"]


class MeanValueCoordinates(DenseWeightsModule):
    """Deform points embedded in a cage with mean value coordinates.

    The coordinates of ``points`` with respect to the rest ``cage`` are computed once (in float64
    by default) and stored as the buffer ``weights`` ``(N, V)``, saved in the ``state_dict``.
    ``forward`` maps deformed cage vertices to deformed points with one matrix product; gradients
    flow to the vertices.

    Args:
        cage: a closed triangle cage (3D; triangulate quad cages with ``cage.triangulated()``) or a
            closed polygon (2D).
        points: ``(N, D)`` points to embed.
        chunk_size: points per chunk while computing the weights.
        dtype: dtype of the stored weights (float64 by default); they are cast to the vertices'
            dtype on use.
        progress: show a progress bar while computing the weights, or a callable
            ``progress(done, total)`` (points done so far).
        store_derivatives: 0 (default), 1 or 2: also store the coordinates' analytic gradients
            (buffer ``gradients`` ``(N, V, D)``) and, for 2, Hessians (``hessians``
            ``(N, V, D, D)``), so that :meth:`jacobian` / :meth:`hessian` of every pose cost one
            matrix product (memory: ``8 N V D`` and ``8 N V D^2`` bytes in float64). Otherwise they
            are computed on each call. The points must be off the cage.

    Shape:
        - Input: ``(*, V, D)`` deformed cage vertices, any leading batch shape.
        - Output: ``(*, N, D)`` deformed points.

    Examples:
        >>> import torch, torchcage
        >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> pts = torch.rand(100, 3, dtype=torch.float64) * 2 - 1
        >>> mvc = torchcage.MeanValueCoordinates(cage, pts)
        >>> poses = cage.vertices * torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64).view(3, 1, 1)
        >>> mvc(poses).shape                     # (3 poses, 100 points, 3)
        torch.Size([3, 100, 3])
        >>> torch.allclose(mvc(cage.vertices), pts)
        True
        >>> J = mvc.jacobian(poses)              # deformation gradient at every point
        >>> J.shape, torch.allclose(J[0, 0], torch.diag(torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64)))
        (torch.Size([3, 100, 3, 3]), True)
    """

    def __init__(
        self,
        cage: Cage,
        points: torch.Tensor,
        *,
        chunk_size: int | None = None,
        dtype: torch.dtype = torch.float64,
        progress: bool | Callable[[int, int], None] = False,
        store_derivatives: int = 0,
    ) -> None:
        if store_derivatives not in (0, 1, 2):
            raise ValueError(f"store_derivatives must be 0, 1 or 2, got {store_derivatives}")
        points = module_points(points, cage)
        cage = detached(cage)
        w = mean_value_coordinates(points, cage, chunk_size=chunk_size, dtype=dtype, progress=progress)
        super().__init__(cage, points)
        self.register_buffer("weights", w)
        self.register_buffer("faces", (cage.triangles if cage.dim == 3 else cage.edges).detach().clone())
        g = h = None
        if store_derivatives:
            _, g, h = mean_value_derivatives(self.points.to(torch.float64), cage, store_derivatives)
            g, h = g.to(dtype), (h.to(dtype) if h is not None else None)
        self.gradients: torch.Tensor | None
        self.hessians: torch.Tensor | None
        self.register_buffer("gradients", g)
        self.register_buffer("hessians", h)

    def _derivative(self, order: int, dtype: torch.dtype) -> torch.Tensor:
        """Gradients (order 1) or Hessians (order 2) of the coordinates at the points: the stored
        buffer, else computed from the rest cage."""
        stored = self.gradients if order == 1 else self.hessians
        if stored is None:
            cage = Cage._from_faces(self.rest_vertices, self.faces)
            stored = mean_value_derivatives(self.points.to(torch.float64), cage, order)[order]
        return stored.to(dtype)

    def jacobian(self, vertices: torch.Tensor) -> torch.Tensor:
        """Jacobian of the deformation at the embedded points, ``J[..., n, a, c] = d y_a / d x_c``:
        ``(*, N, D, D)`` for deformed vertices ``(*, V, D)``; differentiable with respect to them.

        With ``y = sum_v lam_v(x) v'_v``, ``J = sum_v v'_v grad lam_v^T``: the identity at rest,
        the rotation (times the scale) of a similarity.
        """
        self._check_vertices(vertices, self.weights)
        g = self._derivative(1, vertices.dtype)  # (N, V, D)
        return torch.einsum("...nvc,...va->...nac", g, vertices)

    def hessian(self, vertices: torch.Tensor) -> torch.Tensor:
        """Hessian of the deformation at the embedded points, ``H[..., n, a, c, d] =
        d^2 y_a / d x_c d x_d``: ``(*, N, D, D, D)`` for deformed vertices ``(*, V, D)``;
        differentiable with respect to them. Zero for affine motions of the cage."""
        self._check_vertices(vertices, self.weights)
        h = self._derivative(2, vertices.dtype)  # (N, V, D, D)
        return torch.einsum("...nvcd,...va->...nacd", h, vertices)
