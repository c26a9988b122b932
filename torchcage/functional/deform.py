"""Deformation by cage coordinates across the families: :func:`deform`, which recomputes the
coordinates under autograd on each call (rest cage and points differentiable: the Neural Cages
pattern). The per-family maps from coordinates and a deformed cage to deformed points live with
their families and are re-exported here (``green_deformation``, ``quad_green_deformation``), as
are the outside checks of :mod:`torchcage._core.outside`.
"""

from __future__ import annotations

import warnings
from typing import Any

import torch

from torchcage._core.outside import OUTSIDE_TOLERANCE, Outside, find_outside
from torchcage.cage import Cage
from torchcage.errors import OutsideCageWarning
from torchcage.families import FAMILIES, family, names
from torchcage.families.green.api import green_coordinates
from torchcage.families.green.deformation import green_deformation
from torchcage.families.mean_value.api import mean_value_coordinates
from torchcage.families.quad_green.api import quad_green_coordinates
from torchcage.families.quad_green.deformation import quad_corner_factors, quad_green_deformation
from torchcage.families.quad_mean_value.api import quad_mean_value_coordinates

__all__ = [
    "OUTSIDE_TOLERANCE",
    "Outside",
    "deform",
    "find_outside",
    "green_deformation",
    "quad_corner_factors",
    "quad_green_deformation",
]

#: What each family does with points outside the cage (the end of the outside warning; from the
#: registry, :mod:`torchcage.families`).
OUTSIDE_EFFECT = {f.short: f.outside for f in FAMILIES}

_METHODS = names(lambda f: f.deform)
_OUTSIDE = ("warn", "error", "ignore")


def deform(
    points: torch.Tensor,
    cage: Cage,
    vertices: torch.Tensor,
    method: str = "mvc",
    *,
    outside: str = "warn",
    **options: Any,
) -> torch.Tensor:
    """Deform points with coordinates recomputed, under autograd, on every call: differentiable
    with respect to the points, the rest cage's vertices and the deformed vertices (a network that
    predicts both the source cage and its deformation, as in Neural Cages).

    The coordinate modules compute their coordinates once and store them as constants; use this
    when the rest cage or the points change from call to call. Gradients with respect to the rest
    cage and the points come from custom autograd Functions (mean value: one fused analytic pass;
    Green: recomputation chunk by chunk) whose memory is that of the coordinates, not of autograd's
    intermediates.

    Args:
        points: ``(N, D)``, or ``(*B, N, D)`` with a batched cage (``(N, D)`` is shared).
        cage: the rest cage, ``(V, D)`` or batched ``(*B, V, D)``.
        vertices: deformed vertices ``(*, V, D)`` (``(*, *B, V, D)`` for a batched cage).
        method: ``"mvc"`` (mean value), ``"qmvc"`` (quad mean value), ``"gc"`` (Green), ``"qgc"``
            (quad Green; ``correction=`` is passed to the deformation).
        outside: points outside the cage by more than :data:`OUTSIDE_TOLERANCE` of its size:
            ``"warn"`` (default: a :class:`torchcage.OutsideCageWarning` with their count and the
            largest distance, for every method), ``"error"`` (a
            :class:`torchcage.errors.PointsError` with the same message) or ``"ignore"`` (no
            check: saves a winding-number pass per call, about the cost of the mean value
            coordinates themselves, in a training loop that keeps its points inside).
        **options: passed to the coordinate function (``chunk_size``, ``n``, ``backend``, ...).

    Returns:
        ``(*, *B, N, D)`` deformed points.

    Raises:
        ValueError: an unknown method or ``outside``; ``vertices`` whose shape does not end with
            ``(V, D)`` or whose batch dimensions do not broadcast with the cage's ``*B``.
        PointsError: with ``outside="error"``, points outside the cage.

    Examples:
        >>> import torch, torchcage
        >>> ico = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> rest = ico.vertices.expand(2, -1, -1).clone().requires_grad_()   # two predicted rest cages
        >>> x = torch.rand(2, 10, 3, dtype=torch.float64) * 1.6 - 0.8
        >>> y = torchcage.deform(x, torchcage.Cage(rest, ico.triangles), 2 * rest)
        >>> torch.allclose(y, 2 * x), y.shape
        (True, torch.Size([2, 10, 3]))
        >>> y.sum().backward(); rest.grad.shape
        torch.Size([2, 8, 3])
    """
    method = family(method, _METHODS).short
    if not isinstance(vertices, torch.Tensor) or tuple(vertices.shape[-2:]) != (cage.num_vertices, cage.dim):
        shape = tuple(vertices.shape) if isinstance(vertices, torch.Tensor) else type(vertices).__name__
        raise ValueError(f"vertices must have shape (*, {cage.num_vertices}, {cage.dim}), got {shape}")
    if outside not in _OUTSIDE:
        raise ValueError(f"outside must be one of {_OUTSIDE}, got {outside!r}")
    B = cage.batch_shape
    lead = tuple(vertices.shape[:-2])
    tail = lead[max(0, len(lead) - len(B)) :]
    if any(a != b and a != 1 for a, b in zip(reversed(tail), reversed(B), strict=False)):
        raise ValueError(
            f"deformed vertices of shape {tuple(vertices.shape)} do not match the batched rest cage of batch shape "
            f"{tuple(B)}: their dimensions before ({cage.num_vertices}, {cage.dim}) must end with {tuple(B)} (one "
            f"deformed cage per rest cage, e.g. ({', '.join(map(str, B))}, {cage.num_vertices}, {cage.dim}), or "
            f"(K, {', '.join(map(str, B))}, {cage.num_vertices}, {cage.dim}) for K poses of each), or with 1s that "
            "broadcast"
        )
    out = _deform(points, cage, vertices, method, options)
    if outside != "ignore":  # (after the coordinate function has checked the cage and the points)
        _check_outside(points, cage, method, outside)
    return out


def _deform(points: torch.Tensor, cage: Cage, vertices: torch.Tensor, method: str, options: dict) -> torch.Tensor:
    if method == "mvc":
        return torch.matmul(mean_value_coordinates(points, cage, **options).to(vertices.dtype), vertices)
    if method == "qmvc":
        return torch.matmul(quad_mean_value_coordinates(points, cage, **options).to(vertices.dtype), vertices)
    if method == "gc":
        with warnings.catch_warnings():  # (outside points are reported once, by `outside`)
            warnings.simplefilter("ignore", OutsideCageWarning)
            phi, psi = green_coordinates(points, cage, **options)
        faces = cage.edges if cage.dim == 2 else cage.triangles
        return green_deformation(phi, psi, cage.vertices, vertices, faces)
    correction = options.pop("correction", "conformal")
    with warnings.catch_warnings():  # (outside points are reported once, by `outside`)
        warnings.simplefilter("ignore", OutsideCageWarning)
        phi, psi = quad_green_coordinates(points, cage, **options)
    return quad_green_deformation(phi, psi, cage.vertices, vertices, cage.triangles, cage.quads, correction)


def _check_outside(points: Any, cage: Cage, method: str, outside: str) -> None:
    """Warn about (or refuse) points outside the cage (``stacklevel``: the caller of :func:`deform`)."""
    if (
        not isinstance(points, torch.Tensor)
        or points.dim() < 2
        or points.shape[-1] != cage.dim
        or points.is_complex()
        or not points.is_floating_point()
        or points.device.type == "meta"
        or not bool(torch.isfinite(points).all())
    ):
        return
    try:
        if torch.broadcast_shapes(points.shape[:-2], cage.batch_shape) != cage.batch_shape:
            return
    except RuntimeError:
        return
    found = find_outside(points, cage)
    if not found.count:
        return
    message = found.message(OUTSIDE_EFFECT[method])
    if outside == "error":
        from torchcage.errors import PointsError

        raise PointsError(message + ' (outside="error")')
    warnings.warn(message, OutsideCageWarning, stacklevel=3)
