"""The mean value coordinates module."""

from __future__ import annotations

import torch

from ..cage import Cage
from ..functional.mean_value import mean_value_coordinates
from .base import DenseWeightsModule

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
        progress: show a progress bar while computing the weights.

    Shape:
        - Input: ``(*, V, D)`` deformed cage vertices, any leading batch shape.
        - Output: ``(*, N, D)`` deformed points.

    Example:
        >>> import torch, torchcage
        >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> pts = torch.rand(100, 3, dtype=torch.float64) * 2 - 1
        >>> mvc = torchcage.MeanValueCoordinates(cage, pts)
        >>> poses = cage.vertices * torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64).view(3, 1, 1)
        >>> mvc(poses).shape                     # (3 poses, 100 points, 3)
        torch.Size([3, 100, 3])
        >>> torch.allclose(mvc(cage.vertices), pts)
        True
    """

    def __init__(
        self,
        cage: Cage,
        points: torch.Tensor,
        *,
        chunk_size: int | None = None,
        dtype: torch.dtype = torch.float64,
        progress: bool = False,
    ) -> None:
        w = mean_value_coordinates(points, cage, chunk_size=chunk_size, dtype=dtype, progress=progress)
        super().__init__(cage, torch.as_tensor(points).reshape(-1, cage.dim))
        self.register_buffer("weights", w.reshape(-1, cage.num_vertices))
