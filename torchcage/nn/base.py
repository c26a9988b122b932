"""Shared base of the coordinate modules: precomputed weights as buffers, batched deformation."""

from __future__ import annotations

import torch
from torch import nn

from ..cage import Cage
from ..errors import PointsError

__all__ = ["CageModule", "DenseWeightsModule", "module_points"]


def module_points(points: torch.Tensor, cage: Cage) -> torch.Tensor:
    """The point set ``(N, D)`` a coordinate module embeds (array-likes accepted).

    Raises:
        PointsError: points that are not one set ``(N, D)``: a batch ``(B, N, D)`` of point sets
            needs one module per set (or one module of the flattened set, its output split).
    """
    if not isinstance(cage, Cage):
        raise TypeError(f"cage must be a torchcage.Cage, got {type(cage).__name__}")
    pts = torch.as_tensor(points)
    if pts.ndim != 2 or pts.shape[-1] != cage.dim:
        raise PointsError(
            f"a coordinate module embeds one point set of shape (N, {cage.dim}), got {tuple(pts.shape)}; for a batch "
            "of point sets build one module per set, or flatten them into one set and split the output"
        )
    return pts


class CageModule(nn.Module):
    """Base class: holds the rest cage's vertices and the embedded points as buffers and checks
    deformed vertices. Subclasses store their weights as buffers and implement ``forward``."""

    rest_vertices: torch.Tensor
    points: torch.Tensor

    def __init__(self, cage: Cage, points: torch.Tensor) -> None:
        super().__init__()
        if not isinstance(cage, Cage):
            raise TypeError(f"cage must be a torchcage.Cage, got {type(cage).__name__}")
        self.register_buffer("rest_vertices", cage.vertices.detach().clone())
        self.register_buffer("points", torch.as_tensor(points).detach().clone())

    @property
    def num_vertices(self) -> int:
        return int(self.rest_vertices.shape[0])

    @property
    def dim(self) -> int:
        return int(self.rest_vertices.shape[1])

    @property
    def num_points(self) -> int:
        return int(self.points.shape[0])

    def _check_vertices(self, vertices: torch.Tensor, weights: torch.Tensor) -> None:
        """Raise a clear error when deformed vertices do not fit this module."""
        if not isinstance(vertices, torch.Tensor):
            raise TypeError(f"vertices must be a tensor of shape (*, {self.num_vertices}, {self.dim})")
        if not vertices.is_floating_point():
            raise TypeError(f"vertices must be floating point (float32 or float64), got {vertices.dtype}")
        if vertices.ndim < 2 or tuple(vertices.shape[-2:]) != (self.num_vertices, self.dim):
            raise ValueError(
                f"vertices must have shape (*, {self.num_vertices}, {self.dim}) for this cage, "
                f"got {tuple(vertices.shape)}"
            )
        if vertices.device != weights.device:
            raise ValueError(
                f"vertices are on {vertices.device} but the module's weights are on {weights.device}; "
                "call module.to(device) or move the vertices"
            )

    def extra_repr(self) -> str:
        return f"points={self.num_points}, cage_vertices={self.num_vertices}, dim={self.dim}"


class DenseWeightsModule(CageModule):
    """Base of the modules whose deformation is one dense product ``weights @ vertices``: the
    subclass stores its coordinates ``(N, V)`` in the buffer ``weights``."""

    weights: torch.Tensor

    def forward(self, vertices: torch.Tensor) -> torch.Tensor:
        """Deformed points ``(*, N, D)`` for deformed cage vertices ``(*, V, D)``."""
        self._check_vertices(vertices, self.weights)
        return torch.matmul(self.weights.to(vertices.dtype), vertices)
