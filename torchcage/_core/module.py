"""Shared base of the coordinate modules: precomputed weights as buffers, batched deformation."""

from __future__ import annotations

import torch
from torch import nn

from torchcage.cage import Cage
from torchcage.errors import PointsError

__all__ = ["CageModule", "DenseWeightsModule", "detached", "module_points"]


def detached(cage: Cage) -> Cage:
    """The cage with detached vertices (same topology): a module's coordinates are constants."""
    if not isinstance(cage, Cage):
        raise TypeError(f"cage must be a torchcage.Cage, got {type(cage).__name__}")
    return cage.with_vertices(cage.vertices.detach()) if cage.vertices.requires_grad else cage


def module_points(points: torch.Tensor, cage: Cage) -> torch.Tensor:
    """The point set a coordinate module embeds, detached (array-likes accepted): ``(N, D)`` for
    one cage; for a batched cage ``(*B, V, D)``, ``(*B, N, D)`` (one set per cage) or ``(N, D)``
    (shared, expanded to every cage).

    Raises:
        PointsError: points that do not fit the cage: a batch ``(B, N, D)`` of point sets with one
            cage (give the module a batched cage, or one module per set).
    """
    if not isinstance(cage, Cage):
        raise TypeError(f"cage must be a torchcage.Cage, got {type(cage).__name__}")
    pts = torch.as_tensor(points).detach()
    D, batch = cage.dim, cage.batch_shape
    if pts.ndim < 2 or pts.shape[-1] != D:
        raise PointsError(f"a coordinate module embeds points of shape (N, {D}), got {tuple(pts.shape)}")
    if not cage.is_batched:
        if pts.ndim != 2:
            raise PointsError(
                f"a coordinate module of one cage embeds one point set of shape (N, {D}), got {tuple(pts.shape)}; "
                f"for a batch of point sets give the module a batched cage (*B, V, {D}) (cage.with_vertices(...) "
                "repeats one), or flatten the sets into one and split the output"
            )
        return pts
    if pts.ndim == 2:
        return pts.expand(*batch, *pts.shape)
    if tuple(pts.shape[:-2]) != tuple(batch):
        raise PointsError(
            f"points of batch shape {tuple(pts.shape[:-2])} do not match the cages' batch shape {tuple(batch)}; "
            f"give one point set per cage (*B, N, {D}) or one shared set (N, {D})"
        )
    return pts


class CageModule(nn.Module):
    """Base class: holds the rest cage's vertices and the embedded points as buffers and checks
    deformed vertices. Subclasses store their weights as buffers and implement ``forward``.

    With a batched rest cage ``(*B, V, D)`` the buffers carry its batch shape (weights
    ``(*B, N, V)``) and ``forward`` takes deformed vertices ``(*, *B, V, D)``. Buffers never hold an
    autograd graph: the points and the rest cage are detached (for coordinates recomputed under
    autograd each call, use :func:`torchcage.deform`)."""

    rest_vertices: torch.Tensor
    points: torch.Tensor
    #: Check deformed vertices for NaN and inf on every ``forward`` (set ``False`` in hot loops; the
    #: check is skipped inside ``torch.compile``d code, where it would break the graph).
    check_inputs: bool = True

    def __init__(self, cage: Cage, points: torch.Tensor) -> None:
        super().__init__()
        if not isinstance(cage, Cage):
            raise TypeError(f"cage must be a torchcage.Cage, got {type(cage).__name__}")
        self.register_buffer("rest_vertices", cage.vertices.detach().clone())
        self.register_buffer("points", torch.as_tensor(points).detach().clone())

    @property
    def num_vertices(self) -> int:
        return int(self.rest_vertices.shape[-2])

    @property
    def dim(self) -> int:
        return int(self.rest_vertices.shape[-1])

    @property
    def num_points(self) -> int:
        return int(self.points.shape[-2])

    @property
    def batch_shape(self) -> torch.Size:
        """The rest cages' batch shape (``torch.Size([])`` for a module of one cage)."""
        return self.rest_vertices.shape[:-2]

    def _check_vertices(self, vertices: torch.Tensor, weights: torch.Tensor) -> None:
        """Raise a clear error when deformed vertices do not fit this module."""
        if not isinstance(vertices, torch.Tensor):
            raise TypeError(f"vertices must be a tensor of shape (*, {self.num_vertices}, {self.dim})")
        if not vertices.is_floating_point():
            raise TypeError(f"vertices must be floating point (float32 or float64), got {vertices.dtype}")
        batch = tuple(self.batch_shape)
        want = f"(*, {', '.join(map(str, batch)) + ', ' if batch else ''}{self.num_vertices}, {self.dim})"
        lead = tuple(vertices.shape[:-2])
        fits = lead[len(lead) - len(batch) :] == batch if len(lead) >= len(batch) else False
        if vertices.ndim < 2 or tuple(vertices.shape[-2:]) != (self.num_vertices, self.dim) or not fits:
            raise ValueError(f"vertices must have shape {want} for this module's cage, got {tuple(vertices.shape)}")
        if vertices.device != weights.device:
            raise ValueError(
                f"vertices are on {vertices.device} but the module's weights are on {weights.device}; "
                "call module.to(device) or move the vertices"
            )
        skip = not self.check_inputs or torch.compiler.is_compiling() or vertices.device.type == "meta"
        if not skip and not bool(torch.isfinite(vertices).all()):
            bad = torch.nonzero(~torch.isfinite(vertices).all(dim=-1))[:5].tolist()
            raise ValueError(
                f"deformed vertices contain NaN or inf (indices {bad}); fix the pose, or set "
                "module.check_inputs = False to skip this check (one host synchronisation per call on a GPU)"
            )

    def extra_repr(self) -> str:
        batch = f", batch_shape={tuple(self.batch_shape)}" if self.batch_shape else ""
        return f"points={self.num_points}, cage_vertices={self.num_vertices}, dim={self.dim}{batch}"


class DenseWeightsModule(CageModule):
    """Base of the modules whose deformation is one dense product ``weights @ vertices``: the
    subclass stores its coordinates ``(N, V)`` in the buffer ``weights``."""

    weights: torch.Tensor

    def forward(self, vertices: torch.Tensor) -> torch.Tensor:
        """Deformed points ``(*, N, D)`` for deformed cage vertices ``(*, V, D)``."""
        self._check_vertices(vertices, self.weights)
        return torch.matmul(self.weights.to(vertices.dtype), vertices)
