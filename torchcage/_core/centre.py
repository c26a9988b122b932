"""Coordinates computed relative to the cage's centre.

Mean value coordinates (and their quad and derivative variants) are translation invariant: the
weights of ``x`` for the vertices ``V`` equal those of ``x - c`` for ``V - c``. On a cage far from
the origin (translated by ``t``), every quantity a kernel forms from absolute positions (quadrature
nodes, centres, the far-field moments, products such as ``w @ V``) carries a rounding error of
``eps |t|``, which reached 10-20 times the rounding of the input point in linear precision and the
derivative identity (1.4e-9 and 2.4e-9 of the size at ``|t| = 1e6``). Subtracting the bounding-box
centre first (along the axes where the cage lies further from the origin than its extent) is
exact for the vertices and for points within a few sizes of the cage (Sterbenz: both terms are
within a factor 2 of each other), so the kernels see the same numbers as on the cage at the
origin.

The coordinates are then those of the given point itself: a point within the rounding of its
coordinates (``eps |x|``) of a face is no longer snapped to the face's interpolant, which put
linear precision off by up to that rounding (8.7 times ``eps |t|`` next to edges). The
derivatives keep refusing such points as on the cage (where the coordinates are not
differentiable: one side's derivatives would be a guess): :func:`keep_extent` makes the on-cage
tolerances computed inside it (``_common.on_cage_tolerance``) cover the uncentred coordinates'
rounding.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar

import torch

from torchcage.cage import Cage

__all__ = ["centre_of", "centred", "centred_batch", "extent_of", "keep_extent", "rounding_extent"]

_EXTENT: ContextVar[float] = ContextVar("torchcage_rounding_extent", default=0.0)


def rounding_extent() -> float:
    """The largest absolute coordinate of the cage whose centred copy is being computed with (0
    outside :func:`keep_extent`)."""
    return _EXTENT.get()


@contextmanager
def keep_extent(extent: float) -> Iterator[None]:
    """Within the block, on-cage tolerances cover the rounding of coordinates of size ``extent``
    (the uncentred cage's largest coordinate): see the module docstring."""
    token = _EXTENT.set(max(_EXTENT.get(), float(extent)))
    try:
        yield
    finally:
        _EXTENT.reset(token)


def extent_of(vertices: torch.Tensor) -> float:
    """The largest absolute coordinate of ``vertices`` (0 for none)."""
    v = vertices.detach()
    return float(v.abs().max()) if v.numel() else 0.0


def centre_of(vertices: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """The shift ``(*B, D)`` that centres ``vertices`` ``(*B, V, D)`` (one cage, or a batch of cages
    each centred on its own), detached, in ``dtype``: along each
    axis the middle of the bounding box where the cage lies further from the origin than its
    extent (then every coordinate is within a factor 2 of the middle and the subtraction is
    exact), else 0 (a cage around the origin is left as it is: subtracting a small middle from
    larger coordinates would round them).

    Examples:
        >>> v = torch.tensor([[1e6, -1.0], [1e6 + 2, 3.0]], dtype=torch.float64)
        >>> centre_of(v, torch.float64).tolist()
        [1000001.0, 0.0]
    """
    v = vertices.detach().to(dtype)
    if v.numel() == 0:
        return v.new_zeros(*v.shape[:-2], v.shape[-1])
    hi, lo = v.amax(dim=-2), v.amin(dim=-2)
    mid = (hi + lo) / 2
    return torch.where(mid.abs() > hi - lo, mid, torch.zeros_like(mid))


def centred(points: torch.Tensor, cage: Cage, dtype: torch.dtype) -> tuple[torch.Tensor, Cage]:
    """``points - c`` and the cage around ``vertices - c`` (same topology, no new checks), both in
    ``dtype``, with ``c`` the :func:`centre_of` the (unbatched) cage's vertices (detached, so
    that derivatives with respect to the points and the vertices are those of the coordinates
    themselves).

    Args:
        points: ``(N, D)`` points (a graph, if any, is kept).
        cage: one cage (not a batch).
        dtype: the compute dtype (the subtraction itself is done in float64, except on MPS).

    Returns:
        ``(x (N, D), cage)`` in ``dtype``.
    """
    wide = torch.float64 if points.device.type != "mps" else dtype  # (the subtraction is exact in float64)
    c = centre_of(cage.vertices, wide)
    x = (points.to(wide) - c).to(dtype)
    return x, cage._like((cage.vertices.to(wide) - c).to(dtype))


def centred_batch(
    points: torch.Tensor, vertices: torch.Tensor, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`centred` for a batch of cages at once: each cage ``b`` and its points relative to its
    own centre, element by element the same numbers as :func:`centred` on ``cage[b]``.

    Args:
        points: ``(B, N, D)`` points, one set per cage, or ``(1, N, D)``, shared.
        vertices: ``(B, V, D)`` the cages' vertices.
        dtype: the compute dtype (the subtraction itself is done in float64, except on MPS).

    Returns:
        ``(x, vertices (B, V, D))`` in ``dtype``, detached; ``x`` is ``(B, N, D)``, or ``(1, N, D)``
        when the points are shared and no cage needs a shift (cages around the origin).
    """
    wide = torch.float64 if points.device.type != "mps" else dtype
    c = centre_of(vertices, wide)[:, None, :]  # (B, 1, D)
    p = points.detach().to(wide)
    x = (p if points.shape[0] == 1 and not bool(c.any()) else p - c).to(dtype)
    return x, (vertices.detach().to(wide) - c).to(dtype)
