"""Deformation by cage coordinates: the maps from coordinates and a deformed cage to deformed
points (used by the modules' ``forward``), and :func:`deform`, which recomputes the coordinates
under autograd on each call (rest cage and points differentiable: the Neural Cages pattern).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import torch

from ..cage import Cage
from ..errors import OutsideCageWarning
from ..families import FAMILIES, family, names
from ._common import safe_norm
from ._qgc3d import corner_normals
from ._stretch import conformal_stretch, stretched_normals, stretched_triangle_normals
from .green import green_coordinates
from .mean_value import mean_value_coordinates
from .quad_green import quad_green_coordinates
from .quad_mean_value import quad_mean_value_coordinates

__all__ = [
    "OUTSIDE_TOLERANCE",
    "Outside",
    "deform",
    "find_outside",
    "green_deformation",
    "quad_corner_factors",
    "quad_green_deformation",
]

_PATTERN = (torch.arange(5, dtype=torch.float64) + 0.5) / 5


def quad_corner_factors(rest: torch.Tensor, deformed: torch.Tensor) -> torch.Tensor:
    """Per-corner correction factors of quads (Thiery and Boubekeur 2022, Eq. 22):
    ``sigma_k = sum_s b_k(s) sigma_L(s) |N(s)| / sum_s b_k(s) |N'(s)|`` over a 5 x 5 pattern of the
    (u, v) square, ``sigma_L`` Lipman's stretch of the sheet's tangent map and ``N`` (``N'``) the
    rest (deformed) sheet normal. For a similarity of scale ``s`` every factor is ``1 / s``, so that
    ``sigma_k N'_k`` is ``s R N_k``. A quad collapsed to zero area gets factors 0 (its corner
    normals are zero anyway).

    Args:
        rest: ``(Q, 4, 3)`` rest quad corners.
        deformed: ``(*, Q, 4, 3)`` deformed quad corners.

    Returns:
        ``(*, Q, 4)``.
    """
    t = _PATTERN.to(deformed)
    u, v = (g.reshape(-1) for g in torch.meshgrid(t, t, indexing="ij"))  # (S,)
    b = torch.stack([(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v], dim=-1)  # (S, 4)

    def tangents(q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        q0, q1, q2, q3 = (q[..., None, i, :] for i in range(4))  # (*, Q, 1, 3)
        du = (1 - v)[:, None] * (q1 - q0) + v[:, None] * (q2 - q3)
        dv = (1 - u)[:, None] * (q3 - q0) + u[:, None] * (q2 - q1)
        return du, dv  # (*, Q, S, 3)

    du0, dv0 = tangents(rest.to(deformed.dtype))
    du1, dv1 = tangents(deformed)
    area0 = safe_norm(torch.linalg.cross(du0, dv0, dim=-1))
    area1 = safe_norm(torch.linalg.cross(du1, dv1, dim=-1))
    num = torch.einsum("...s,sk->...k", conformal_stretch(du0, dv0, du1, dv1) * area0, b)
    den = torch.einsum("...s,sk->...k", area1, b)
    return torch.where(den > 0, num / torch.where(den > 0, den, 1.0), 0.0)


def green_deformation(
    phi: torch.Tensor, psi: torch.Tensor, rest: torch.Tensor, deformed: torch.Tensor, faces: torch.Tensor
) -> torch.Tensor:
    """``phi @ V' + psi @ (s n')``: Green deformation with Lipman's stretch factors (3D; the edge
    stretch ``|a'| / |a|`` in 2D), differentiable with respect to everything.

    Args:
        phi: ``(*B, N, V)``; psi: ``(*B, N, T)`` (``T`` triangles, or edges in 2D).
        rest: ``(*B, V, D)`` rest vertices; deformed: ``(*, *B, V, D)``.
        faces: ``(T, 3)`` triangles, or ``(E, 2)`` edges in 2D.

    Returns:
        ``(*, *B, N, D)`` deformed points.
    """
    dt = deformed.dtype
    if deformed.shape[-1] == 2:
        sn = stretched_normals(rest, deformed, faces)
    else:
        sn = stretched_triangle_normals(rest, deformed, faces)
    return torch.matmul(phi.to(dt), deformed) + torch.matmul(psi.to(dt), sn)


def quad_green_deformation(
    phi: torch.Tensor,
    psi: torch.Tensor,
    rest: torch.Tensor,
    deformed: torch.Tensor,
    triangles: torch.Tensor,
    quads: torch.Tensor,
    correction: str = "conformal",
) -> torch.Tensor:
    """Quad Green deformation: ``phi @ V' + psi[:T] @ (s_t n'_t) + sum psi[T+4q+k] sigma_qk N'_qk``.

    Args:
        phi: ``(*B, N, V)``; psi: ``(*B, N, T + 4Q)``.
        rest: ``(*B, V, 3)``; deformed: ``(*, *B, V, 3)``.
        triangles: ``(T, 3)``; quads: ``(Q, 4)``.
        correction: ``"conformal"`` (corner factors, Eq. 22) or ``"area"`` (factors 1).

    Returns:
        ``(*, *B, N, 3)`` deformed points.
    """
    dt = deformed.dtype
    T = triangles.shape[0]
    out = torch.matmul(phi.to(dt), deformed)
    if T:
        sn = stretched_triangle_normals(rest, deformed, triangles)
        out = out + torch.matmul(psi[..., :T].to(dt), sn)
    if quads.shape[0]:
        q1 = deformed[..., quads, :]  # (*, Q, 4, 3)
        N1 = corner_normals(q1)
        if correction == "conformal":
            N1 = quad_corner_factors(rest[..., quads, :], q1)[..., None] * N1
        out = out + torch.matmul(psi[..., T:].to(dt), N1.flatten(-3, -2))
    return out


#: Points farther outside the cage than this fraction of its size (bounding-box diagonal), beyond
#: the rounding of their coordinates, are reported by :func:`find_outside` (and warn in
#: :func:`deform` and ``torchcage deform``, for every family).
OUTSIDE_TOLERANCE = 1e-6


@dataclass(frozen=True)
class Outside:
    """Points outside a cage (:func:`find_outside`).

    Attributes:
        count: how many points lie outside (over the batch, for a batched cage).
        total: how many points were checked (over the batch).
        max_distance: the largest distance outside, relative to the cage's size (its bounding-box
            diagonal; per batch element); 0 when none lies outside.
        mask: ``(*B, N)`` bool, True for the points outside.
    """

    count: int
    total: int
    max_distance: float
    mask: torch.Tensor

    def message(self, effect: str = "") -> str:
        """One line: the count, how far, and ``effect`` (what the coordinates do with them)."""
        text = (
            f"{self.count:,} of {self.total:,} points lie outside the cage, up to {self.max_distance:.3g} of its "
            "size (bounding-box diagonal) away from it"
        )
        return f"{text}: {effect}" if effect else text


def find_outside(points: torch.Tensor, cage: Cage, tolerance: float = OUTSIDE_TOLERANCE) -> Outside:
    """The points that lie outside a cage by more than ``tolerance`` times its size (plus the
    rounding of the coordinates), and how far: the winding number (3D; quads split along
    ``q0-q2``) or the crossing rule (2D) picks the candidates, their distance to the boundary
    decides. Vectorised and chunked over points (:func:`torchcage.geometry.winding_number`,
    :func:`torchcage.geometry.distance_to_cage`); no graph.

    Args:
        points: ``(N, D)``, or ``(*B, N, D)`` with a batched cage (``(N, D)`` is shared).
        cage: the cage, ``(V, D)`` or batched ``(*B, V, D)``.
        tolerance: the distance outside, relative to the cage's size, that still counts as on it.

    Returns:
        :class:`Outside`: the count, the total, the largest distance relative to the size and
        the ``(*B, N)`` mask.

    Examples:
        >>> import torch, torchcage
        >>> from torchcage.functional.deform import find_outside
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))  # [-1, 1]^3, size 2 sqrt(3)
        >>> r = find_outside(torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0]]), cube)
        >>> r.count, r.total, round(r.max_distance * 12**0.5, 6), r.mask.tolist()
        (1, 3, 2.0, [False, False, True])
    """
    from ..geometry import distance_to_cage, inside_cage

    x = points.detach()
    B = cage.batch_shape
    x = x.expand(*B, *x.shape[-2:]) if B else x
    still = cage.with_vertices(cage.vertices.detach())  # (a predicted cage: no graph, no grad)
    cages = still.unbind() if still.is_batched else [still]
    flat = x.reshape(len(cages), *x.shape[-2:])
    dtype = torch.float64 if x.device.type != "mps" else torch.float32
    masks, count, worst = [], 0, 0.0
    for c, p in zip(cages, flat, strict=True):
        c = c.to(dtype=dtype, device=x.device)
        p = p.to(dtype)
        v = c.vertices
        size = c.scale
        # the rounding of the coordinates as given (float32 points on the cage round to just outside it)
        rounding = 8 * torch.finfo(x.dtype).eps * float(v.abs().max()) if v.numel() else 0.0
        mask = torch.zeros(p.shape[0], dtype=torch.bool, device=x.device)
        if p.shape[0] and size > 0:
            candidates = torch.nonzero(~inside_cage(p, c)).flatten()
            if candidates.numel():
                d = distance_to_cage(p[candidates], c)
                far = d > tolerance * size + rounding
                mask[candidates[far]] = True
                if bool(far.any()):
                    worst = max(worst, float(d[far].max()) / size)
        count += int(mask.sum())
        masks.append(mask)
    mask = torch.stack(masks).reshape(*x.shape[:-1]) if masks else torch.zeros(x.shape[:-1], dtype=torch.bool)
    return Outside(count, int(mask.numel()), worst, mask)


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
        from ..errors import PointsError

        raise PointsError(message + ' (outside="error")')
    warnings.warn(message, OutsideCageWarning, stacklevel=3)
