"""Shared helpers of the functional kernels: input checks, dtype resolution and chunking."""

from __future__ import annotations

import functools
import math
import sys
from collections.abc import Callable, Iterator
from typing import Any

import torch
from torch._C._functorch import is_functorch_wrapped_tensor
from torch.autograd import forward_ad

from torchcage._core.centre import rounding_extent
from torchcage.cage import Cage
from torchcage.errors import CageError, PointsError

#: Points closer to the cage than this fraction of its bounding-box diagonal are treated as lying
#: on it and get the interpolating values (the exact limit, up to rounding).
ON_CAGE_TOLERANCE = 16 * torch.finfo(torch.float64).eps
EXTENT_TOLERANCE = 2 * torch.finfo(torch.float64).eps


def on_cage_tolerance(cage: Cage) -> float:
    """Absolute on-cage tolerance: ``ON_CAGE_TOLERANCE`` times the larger of the cage's size and its
    largest coordinate (a point on a face of a cage far from the origin carries a rounding error of
    about ``eps * |x|``, which is larger than ``eps * size`` there)."""
    v = cage.vertices.detach()
    extent = max(float(v.abs().max()) if v.numel() else 0.0, rounding_extent())  # (centred copies: _centre)
    return ON_CAGE_TOLERANCE * cage.scale + EXTENT_TOLERANCE * extent


def on_cage_tolerances(vertices: torch.Tensor) -> torch.Tensor:
    """:func:`on_cage_tolerance` of a batch of cages ``vertices`` ``(B, V, D)`` at once: ``(B,)``
    float64, element by element the same numbers."""
    v = vertices.detach().to(torch.float64)
    scale = (v.amax(dim=-2) - v.amin(dim=-2)).norm(dim=-1)  # (as Cage.scale)
    extent = v.abs().amax(dim=(-2, -1)).clamp_min(rounding_extent())  # (centred copies: _centre)
    return ON_CAGE_TOLERANCE * scale + EXTENT_TOLERANCE * extent


def unit_sum(phi: torch.Tensor, x: torch.Tensor, vertices: torch.Tensor, band: float = 1e-8) -> torch.Tensor:
    """``phi`` ``(N, V)`` divided by its sum for the points ``x`` ``(N, D)`` nearer the centre of the
    cage's ``vertices`` ``(V, D)`` than the centre is to the origin, where the sum is within ``band``
    of 1. (A batch of cages: ``phi`` ``(B, N, V)``, ``x`` ``(B or 1, N, D)``, ``vertices``
    ``(B, V, D)``, each element as alone.)

    Green coordinates sum to 1 (inside the cage, and continued outside) only up to the rounding of
    their solid angles, some ``1e-14``. With ``s`` that sum and ``c`` the centre, the error of
    ``phi @ V`` is ``(s - 1) |c|`` (8e-15 of unity cost 4e-9 of the size on a cube translated by
    1e6); divided by ``s``, it is ``(s - 1) |x - c|``: the smaller one is kept. Rows whose sum is far
    from 1 (points outside the cage without the extension: 0) are returned as they are.

    ``phi`` without a graph is scaled in place: pass a tensor the caller does not hold (the kernels'
    outputs).

    Examples:
        >>> V = torch.tensor([[1e6, 0.0], [1e6 + 1, 0.0]], dtype=torch.float64)
        >>> phi = torch.tensor([[0.5, 0.5 + 1e-12], [0.0, 0.0]], dtype=torch.float64)
        >>> out = unit_sum(phi, V.mean(0).expand(2, 2), V)
        >>> bool(abs(out[0].sum() - 1) < 1e-15), out[1].tolist()
        (True, [0.0, 0.0])
    """
    c = (vertices.detach().amax(dim=-2) + vertices.detach().amin(dim=-2)) / 2  # (D,), or (B, D)
    closer = (x.detach() - c.unsqueeze(-2)).norm(dim=-1, keepdim=True) < c.norm(dim=-1)[..., None, None]
    plain = not phi.requires_grad and not is_functorch_wrapped_tensor(phi)
    if plain and not bool(closer.any()):  # (a cage about the origin: no row to scale, no pass over phi)
        return phi
    s = phi.sum(dim=-1, keepdim=True)
    near = ((s - 1).abs() <= band) & closer
    if plain:
        # (a kernel's fresh output: scaled in place, which spared 30 ms of allocation per 10^6 entries)
        return phi.mul_(torch.where(near, 1.0 / torch.where(near, s, 1.0), 1.0))
    return torch.where(near, phi / torch.where(near, s, 1.0), phi)


#: Green coordinates take points within ``VERTEX_SNAP * ON_CAGE_TOLERANCE`` of the cage's size of a
#: vertex at the vertex (the limit there): seen from a few tolerances the corner's faces are known
#: to a few per mille (the rounding of ``v - x``), and a point 4 tolerances outside a corner was
#: reproduced to 7.5e-6. (Relative to the size, not to the largest coordinate: the snap moves a
#: point by at most 2.3e-13 of the size.)
VERTEX_SNAP = 64.0


#: The snaps' exact test takes (rows, vertices) squared distances at most this many at a time.
SNAP_ENTRIES = 1 << 22


def snap_to_vertices(x: torch.Tensor, vertices: torch.Tensor, radius: float) -> torch.Tensor:
    """``x`` ``(N, D)`` with every point within ``radius`` of a vertex ``(V, D)`` replaced by that
    vertex (a new tensor; differentiable: snapped rows follow the vertex, others the point).

    Examples:
        >>> V = torch.tensor([[0.0, 0.0], [1.0, 0.0]])
        >>> snap_to_vertices(torch.tensor([[1e-9, 0.0], [0.5, 0.0]]), V, 1e-6).tolist()
        [[0.0, 0.0], [0.5, 0.0]]
    """
    if x.shape[0] == 0 or vertices.shape[0] == 0:
        return x
    V = vertices.to(x.dtype)
    best = torch.zeros(x.shape[0], dtype=torch.int64, device=x.device)
    near = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
    Vd = V.detach()
    with torch.no_grad():
        # A screen first: a point within radius of a vertex is within radius of some vertex's
        # coordinate along every axis (the nearest one, by searchsorted on the sorted coordinates,
        # N log V; each axis only over the rows the previous one kept: 0.9 ms on 28,000 points and
        # 152 vertices, an eighth of the matrix product |x|^2 + |v|^2 - 2 x.v it replaced). The
        # differences are those the test below squares:
        # its sum of squares <= radius^2 implies each |x_k - v_k| <= radius (1 + 2 eps), so the screen
        # keeps every row the test would snap. Only the rows it keeps are measured (few: none away
        # from vertices).
        xd = x.detach()
        reach = radius * (1 + max(1e-12, 4 * torch.finfo(x.dtype).eps))  # (the squares' rounding)
        rows = None  # (the rows still in: all, then the first axis's survivors, then the second's)
        for k in range(x.shape[1]):
            coord = Vd[:, k].sort().values
            xk = xd[:, k].contiguous() if rows is None else xd[rows, k]
            i = torch.searchsorted(coord, xk).clamp_(1, coord.shape[0] - 1) if coord.shape[0] > 1 else None
            if i is None:
                gap = (xk - coord[0]).abs()
            else:
                gap = torch.minimum((xk - coord[i - 1]).abs(), (xk - coord[i]).abs())
            keep = torch.nonzero(gap <= reach).flatten()
            rows = keep if rows is None else rows[keep]
            if rows.numel() == 0:
                return x
        assert rows is not None
        step = max(1, SNAP_ENTRIES // max(1, V.shape[0]))
        for s in range(0, rows.numel(), step):
            rs = rows[s : s + step]
            xs = xd[rs]
            # squared distances component by component (the same sums as .square().sum(-1) over
            # the last axis, a third of its time), their minimum by amin, and the nearest vertex
            # only for the rows that snap (min(dim) with indices cost twice the rest)
            d2 = (xs[:, None, 0] - Vd[:, 0]).square()
            for k in range(1, xs.shape[1]):
                d2 = d2 + (xs[:, None, k] - Vd[:, k]).square()
            ns = d2.amin(dim=1) <= radius * radius
            near[rs] = ns
            if bool(ns.any()):
                idx = torch.nonzero(ns).flatten()
                best[rs[idx]] = d2[idx].argmin(dim=1)
    if not bool(near.any()):
        return x
    return torch.where(near[:, None], V[best], x)


def snap_to_vertices_batch(x: torch.Tensor, vertices: torch.Tensor, radius: torch.Tensor) -> torch.Tensor:
    """:func:`snap_to_vertices` for a batch of cages at once: ``x`` ``(B, N, D)`` with every point
    within ``radius[b]`` ``(B,)`` of a vertex of ``vertices[b]`` ``(B, V, D)`` replaced by that
    vertex (a new tensor, or ``x`` itself when no point snaps); element by element the same points
    as :func:`snap_to_vertices`, and differentiable as it (snapped rows follow the vertex).

    Examples:
        >>> V = torch.tensor([[[0.0, 0.0], [1.0, 0.0]], [[0.0, 1.0], [1.0, 1.0]]])
        >>> x = torch.tensor([[[0.25**12, 0.0]], [[0.25**12, 0.0]]])  # (6e-8 from (0, 0))
        >>> snap_to_vertices_batch(x, V, torch.tensor([1e-6, 1e-6])).tolist()
        [[[0.0, 0.0]], [[5.960464477539063e-08, 0.0]]]
    """
    N, D = x.shape[1:]
    if N == 0 or vertices.shape[1] == 0:
        return x
    Vd, xd = vertices.detach().to(x.dtype), x.detach()
    r = radius.to(x.dtype)
    with torch.no_grad():
        # The screen of snap_to_vertices, axis by axis: the first axis over every row of every
        # element (one batched search), the others over the (element, row) pairs it kept, in chunks
        # that bound the (pairs, V) temporaries as snap_to_vertices does.
        reach = r * (1 + max(1e-12, 4 * torch.finfo(x.dtype).eps))  # (B,)
        coords = Vd.transpose(1, 2).sort(dim=-1).values  # (B, D, V): each element's coordinates per axis, sorted

        def screen(coord: torch.Tensor, xk: torch.Tensor, rk: torch.Tensor) -> torch.Tensor:
            """Whether a vertex coordinate lies within ``rk`` of ``xk`` ``(m, k)`` in its row of the
            sorted ``coord`` ``(m, V)``."""
            if coord.shape[1] == 1:
                return (xk - coord).abs() <= rk
            i = torch.searchsorted(coord, xk).clamp_(1, coord.shape[1] - 1)
            return torch.minimum((xk - coord.gather(1, i - 1)).abs(), (xk - coord.gather(1, i)).abs()) <= rk

        first = screen(coords[:, 0].contiguous(), xd[..., 0].contiguous(), reach[:, None])  # (B, N)
        b0, n0 = torch.nonzero(first, as_tuple=True)
        step = max(1, SNAP_ENTRIES // max(1, Vd.shape[1]))
        hits: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []
        for s in range(0, b0.numel(), step):
            b, n = b0[s : s + step], n0[s : s + step]
            for k in range(1, D):
                keep = screen(coords[b, k], xd[b, n, k][:, None], reach[b][:, None])[:, 0]
                b, n = b[keep], n[keep]
            if b.numel() == 0:
                continue
            # (the test of snap_to_vertices: the same sums of squares, the same comparison)
            xs, vs = xd[b, n], Vd[b]
            d2 = (xs[:, None, 0] - vs[..., 0]).square()
            for k in range(1, D):
                d2 = d2 + (xs[:, None, k] - vs[..., k]).square()
            rb = r[b]
            ns = d2.amin(dim=1) <= rb * rb
            if bool(ns.any()):
                hits.append((b[ns], n[ns], d2[ns].argmin(dim=1)))
        if not hits:
            return x
        b, n, best = (torch.cat(t) for t in zip(*hits, strict=True))
    out = x.clone()
    out[b, n] = vertices.to(x.dtype)[b, best]
    return out


#: Entries of a gradient table ``(n, V, D)`` that a backward pass builds at once (32 MB of float64):
#: the closed-form point gradients are contracted with their cotangents chunk by chunk of points.
GRADIENT_TABLE_ENTRIES = 1 << 22


def records_graph(*tensors: torch.Tensor) -> bool:
    """True when autograd (reverse or forward mode, or a torch.func transform) differentiates
    through a call on ``tensors``."""
    if any(is_functorch_wrapped_tensor(t) or has_tangent(t) for t in tensors):
        return True
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)


def refuse_transforms(points: torch.Tensor, cage: Cage, what: str) -> None:
    """Families whose point location reads the points' values (meshed interiors) cannot run under
    ``torch.func`` transforms, whose tensors hold no data.

    Raises:
        NotImplementedError: ``points`` or the cage's vertices wrapped by a ``torch.func``
            transform (``vmap``, ``jvp``, ``jacrev``, ``jacfwd``, ``grad``), naming what works.
    """
    if is_functorch_wrapped_tensor(points) or is_functorch_wrapped_tensor(cage.vertices):
        raise NotImplementedError(
            f"{what} cannot run under torch.func transforms (vmap, jvp, jacrev, jacfwd, grad): locating the "
            "points in the meshed interior reads their values. Call it once per point set (a loop instead of "
            "vmap), and take derivatives with respect to the points with torch.autograd (backward, "
            "torch.autograd.grad) or forward mode (torch.autograd.forward_ad), which both work"
        )


def no_vertex_tangent(dP: torch.Tensor | None) -> None:
    """Forward mode covers tangents of the points only (torch.func passes zeros for the others).

    Raises:
        NotImplementedError: a nonzero tangent ``dP`` of the rest cage's vertices.
    """
    if dP is None:
        return
    try:
        zero = bool((dP == 0).all())
    except RuntimeError:  # a batched tangent whose values cannot be inspected
        zero = False
    if not zero:
        raise NotImplementedError(
            "forward-mode derivatives with respect to the rest cage's vertices are not implemented; "
            "use reverse mode (backward, torch.func.jacrev)"
        )


def has_tangent(t: torch.Tensor) -> bool:
    """True when ``t`` carries a forward-mode tangent at the current level
    (:mod:`torch.autograd.forward_ad`): a call on it must keep the derivative.

    Examples:
        >>> import torch.autograd.forward_ad as fwAD
        >>> x = torch.ones(2)
        >>> with fwAD.dual_level():
        ...     has_tangent(fwAD.make_dual(x, torch.ones(2))), has_tangent(x)
        (True, False)
    """
    return forward_ad.unpack_dual(t).tangent is not None


def outside_point(vertices: torch.Tensor) -> torch.Tensor:
    """A point ``(D,)`` well outside the bounding box of ``vertices`` ``(V, D)`` (detached), in no
    special position: kernels evaluate their regular formula there in place of points on the cage,
    whose values come from the interpolant, so that the discarded branch has finite derivatives
    (``torch.where`` multiplies the unused branch's gradient by zero, and ``0 * inf`` is NaN)."""
    v = vertices.detach()
    lo, hi = v.min(dim=0).values, v.max(dim=0).values
    size = (hi - lo).norm()
    direction = v.new_tensor([0.8017, 0.4751, 0.3625][: v.shape[1]])
    return hi + size * direction


#: Beyond this many cage radii from its centre, mean value weights are normalised by their first
#: moment (see :func:`normalise_weights`; the native kernels use the same, TC_FAR_MOMENT).
FAR_MOMENT = 1e3


def far_region(vertices: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(c (*B, D), far (*B, n))``: the centre (bounding-box middle) of ``vertices`` ``(*B, V, D)``
    and which points ``x`` ``(*B, n, D)`` lie beyond ``FAR_MOMENT`` times the cage's radius from it
    (``*B``: no batch axis, or a batch of cages with one point set each)."""
    v = vertices.detach()
    # (amax / amin, not max(dim).values: the same values, without the index pass, which cost
    # milliseconds on 2 busy cores)
    c = (v.amax(dim=-2) + v.amin(dim=-2)) / 2
    far2 = FAR_MOMENT**2 * ((v - c[..., None, :]) ** 2).sum(dim=-1).amax(dim=-1)
    y = x.detach().to(c.dtype) - c[..., None, :]
    return c, (y * y).sum(dim=-1) > far2[..., None]


def may_be_far(vertices: torch.Tensor, x: torch.Tensor) -> bool:
    """Whether some point of ``x`` ``(*B, n, D)`` may lie in the far region (:func:`far_region`) of
    its cage ``vertices`` ``(*B, V, D)`` (``*B``: a shared batch shape, or a point set broadcast
    over it): False when the points' bounding box lies within half the far radius of the centre
    (a margin no rounding can cross). One min/max pass over the points, a third of the time of
    :func:`far_region`'s squared distances on 39,000 points.

    Examples:
        >>> V = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
        >>> may_be_far(V, torch.tensor([[0.2, 0.3]])), may_be_far(V, torch.tensor([[5e3, 0.0]]))
        (False, True)
    """
    if x.shape[-2] == 0:
        return False
    v = vertices.detach()
    c = (v.amax(dim=-2) + v.amin(dim=-2)) / 2  # (*B, D), as far_region
    r2 = ((v - c[..., None, :]) ** 2).sum(dim=-1).amax(dim=-1)  # (*B,)
    lo, hi = torch.aminmax(x.detach().to(c.dtype), dim=-2)  # (one pass over the points)
    corner = torch.maximum((hi - c).abs(), (lo - c).abs())  # (*B, D): the farthest box corner
    return bool(((corner**2).sum(dim=-1) > 0.25 * FAR_MOMENT**2 * r2).any())


def far_unity(
    w: torch.Tensor, x: torch.Tensor, vertices: torch.Tensor, *derivatives: torch.Tensor | None
) -> tuple[torch.Tensor | None, ...]:
    """Mean value coordinates ``w`` ``(n, V)`` of far points made to sum to 1 without moving their
    linear precision, and their ``derivatives`` ``(n, V, ...)`` alike.

    ``w`` ``(*B, n, V)``, ``x`` ``(*B, n, D)``, ``vertices`` ``(*B, V, D)``: a leading batch
    shape ``*B`` (a batch of cages, one point set each) is allowed.

    Far from the cage (:func:`far_region`) the weights are normalised by their first moment, so
    their sum is 1 only to ``eps * distance / size`` (3e-11 at 500 sizes); ``w @ V`` then carries
    that defect times the distance of the cage from the origin (3e-8 relative on a cube translated
    by 1e6). Adding the defect to every vertex in equal parts, ``w + (1 - sum w) / V``, restores the
    sum and keeps ``w @ (V - m)`` for the vertices' mean ``m``: the derivatives lose their mean over
    the vertices. Near points are returned as they are (their sum is already 1 to rounding).

    Examples:
        >>> V = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
        >>> x = torch.tensor([[3e3, 0.0]], dtype=torch.float64)
        >>> w = torch.tensor([[-5999.0, 3000.0 + 1e-9, 3000.0]], dtype=torch.float64)
        >>> round(float(w.sum() - 1), 12), abs(float(far_unity(w, x, V)[0].sum() - 1)) < 1e-12
        (1e-09, True)
    """
    wrapped = is_functorch_wrapped_tensor(x)  # (no data-dependent branch under vmap)
    if not wrapped and not may_be_far(vertices, x):  # (the common case: no pass over the points' distances)
        return (w, *derivatives)
    _, far = far_region(vertices, x)
    if not wrapped and not bool(far.any()):
        return (w, *derivatives)
    k = far.dim()  # the vertex axis of w and of the derivatives
    defect = torch.where(far, 1 - w.sum(dim=k), 0.0)[..., None] / w.shape[k]
    out = [w + defect]
    for g in derivatives:
        if g is None:
            out.append(None)
            continue
        mask = far.reshape(*far.shape, *([1] * (g.dim() - k)))
        out.append(g - torch.where(mask, g.mean(dim=k, keepdim=True), 0.0))
    return tuple(out)


def normalise_weights(W: torch.Tensor, on: torch.Tensor, vertices: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Mean value weights ``W`` ``(n, V)`` of points ``x`` ``(n, D)`` divided by their total, except
    rows on the cage (``on`` ``(n,)``, already final). A batch of cages ``vertices`` ``(B, V, D)``:
    ``W`` ``(B, n, V)``, ``on`` ``(B, n)``, ``x`` ``(B or 1, n, D)``.

    The total is the sum of the weights, except far from the cage (beyond ``FAR_MOMENT`` times its
    radius from its centre ``c``), where the sum cancels to about ``size / distance`` of its terms; there it is the
    first moment ``(W @ (V - c)) . (x - c) / |x - c|^2``, equal to the sum by linear precision and
    free of that cancellation (relative linear precision 1e-16 out to 1e9 cage sizes, where the
    sum gave 1e-7 to 1). Partition of unity then holds to ``eps * distance / size``.
    """
    c, far = far_region(vertices, x)
    y = x - c[..., None, :]
    y2 = (y * y).sum(dim=-1)
    total = W.sum(dim=-1)
    if bool(far.any()):
        moment = ((W @ (vertices.to(W.dtype) - c[..., None, :])) * y).sum(dim=-1) / torch.where(far, y2, 1.0)
        total = torch.where(far, moment, total)
    return torch.where(on[..., None], W, W / torch.where(on, 1.0, total)[..., None])


def safe_sqrt(x: torch.Tensor) -> torch.Tensor:
    """``sqrt(max(x, 0))`` whose derivative at 0 is 0 instead of inf (a finite subgradient)."""
    pos = x > 0
    return torch.sqrt(torch.where(pos, x, 1.0)) * pos


def log_ratio(num: torch.Tensor, den: torch.Tensor) -> torch.Tensor:
    """``log(num / den)`` where both are positive, 0 elsewhere; finite derivatives everywhere."""
    ok = (num > 0) & (den > 0)
    return torch.log(torch.where(ok, num, 1.0) / torch.where(ok, den, 1.0))


def safe_norm(x: torch.Tensor, dim: int = -1, keepdim: bool = False) -> torch.Tensor:
    """Euclidean norm over ``dim`` whose derivative at the zero vector is 0 (not NaN)."""
    return safe_sqrt((x * x).sum(dim=dim, keepdim=keepdim))


def safe_atan2(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``atan2(y, x)`` with the value 0 and zero derivatives at ``(0, 0)`` (torch gives NaN there)."""
    zero = (y == 0) & (x == 0)
    return torch.atan2(torch.where(zero, 0.0, y), torch.where(zero, 1.0, x))


def nearest_where(mask: torch.Tensor, value: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per column of ``value`` ``(F, n)``, the entry of smallest ``|value|`` among those where
    ``mask`` ``(F, n)`` holds (chosen without a gradient, returned with one; 1 in a column where
    none does), and the ``(F, n)`` bool mask of that entry.

    Examples:
        >>> v = torch.tensor([[3.0, -1.0], [-2.0, 5.0]])
        >>> star, at = nearest_where(torch.tensor([[True, False], [True, False]]), v)
        >>> star.tolist(), at.tolist()
        ([-2.0, 1.0], [[False, False], [True, False]])
    """
    key = torch.where(mask, value.detach().abs(), torch.inf)
    best = key.argmin(dim=0)
    found = torch.isfinite(key.min(dim=0).values)
    star = torch.where(found, value.gather(0, best[None])[0], 1.0)
    at = (torch.arange(value.shape[0], device=value.device)[:, None] == best[None]) & found[None]
    return star, at


def safe_div(num: torch.Tensor, den: torch.Tensor, ok: torch.Tensor, fill: float = 0.0) -> torch.Tensor:
    """``num / den`` where ``ok``, ``fill`` elsewhere, with finite derivatives on both branches."""
    return torch.where(ok, num / torch.where(ok, den, 1.0), fill)


def triangle_geometry(cage: Cage, dtype: torch.dtype, quad_hint: str) -> tuple[torch.Tensor, ...]:
    """Corners ``(T, 3, 3)``, unit outward normals ``(T, 3)`` and twice the areas ``(T,)`` of a
    triangle cage's faces, in ``dtype``.

    Raises:
        CageError: a 2D cage, or a cage with quads (the message ends with ``quad_hint``).
    """
    if cage.dim != 3:
        raise CageError("expected a 3D cage")
    if cage.has_quads:
        raise CageError(f"this needs a triangle cage, but the cage has {cage.quads.shape[0]} quads; {quad_hint}")
    p = cage.vertices.to(dtype)[cage.triangles]
    cross = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    two_area = cross.norm(dim=-1)
    return p, cross / two_area[:, None], two_area


def as_inputs(points: Any, cage: Any) -> tuple[torch.Tensor, Cage]:
    """The public functions' first step: points as a tensor (lists and arrays accepted; integers and
    nested lists become float64) and a check that ``cage`` is a :class:`~torchcage.Cage`.

    Raises:
        TypeError: ``cage`` is not a Cage (a ``(vertices, faces)`` pair is named as such).
        PointsError: points or cage on the ``meta`` device, which holds no values to compute with.
        CageError: a cage whose geometry cannot be computed with (:meth:`~torchcage.Cage.check_geometry`).
    """
    if not isinstance(cage, Cage):
        if isinstance(cage, (tuple, list)) and len(cage) == 2:
            raise TypeError(
                "cage must be a torchcage.Cage; for a (vertices, faces) pair pass torchcage.Cage(vertices, faces)"
            )
        raise TypeError(f"cage must be a torchcage.Cage, got {type(cage).__name__}")
    if not isinstance(points, torch.Tensor):
        if hasattr(points, "__array__"):  # an array keeps its floating dtype
            t = torch.as_tensor(points)
            points = t if t.is_floating_point() else t.to(torch.float64)
        else:  # nested lists: float64, the library's working precision
            points = torch.as_tensor(points, dtype=torch.float64)
    if points.device.type == "meta" or cage.device.type == "meta":
        raise PointsError(
            "coordinates cannot be computed on the meta device (it holds shapes, not values); compute them on a "
            "real device (cpu, cuda) and move the module with .to(device) afterwards"
        )
    if not (is_functorch_wrapped_tensor(cage.vertices) or torch.compiler.is_compiling()):
        # a cage built without geometric checks (validate=False / "topology", with_vertices in a loop)
        # is checked here once: NaN/inf vertices, coincident vertices, zero-area faces raise instead of
        # answering NaN or a finite wrong value (a cage that passed is not checked again)
        cage.check_geometry()
    return points, cage


def check_points(points: torch.Tensor, cage: Cage) -> torch.Tensor:
    """Validate query points against a cage and return them flattened to ``(N, D)``.

    Raises:
        TypeError: ``points`` is not a floating-point tensor.
        PointsError: wrong last dimension, non-finite values, or a device other than the cage's.
    """
    if cage.is_batched:
        raise CageError(
            f"this function takes one cage, got a batch of shape {tuple(cage.batch_shape)}; call it per element "
            "(cage[b]) or use a closed-form method (mean value, Green, quad mean value, quad Green), which take batches"
        )
    if not isinstance(points, torch.Tensor):
        points = torch.as_tensor(points)
        if not points.is_floating_point():
            points = points.to(torch.float64)
    if not points.is_floating_point():
        raise TypeError(f"points must be a floating-point tensor, got dtype {points.dtype}")
    if points.ndim < 1 or points.shape[-1] != cage.dim:
        raise PointsError(f"points must have shape (..., {cage.dim}) for a {cage.dim}D cage, got {tuple(points.shape)}")
    if points.device != cage.device:
        raise PointsError(f"points are on {points.device} but the cage is on {cage.device}; move one with .to(device)")
    flat = points.reshape(-1, cage.dim)
    if not is_functorch_wrapped_tensor(flat):  # (under torch.func transforms the kernels' ops check)
        check_finite(flat)
    return flat


def check_finite(flat: torch.Tensor) -> None:
    """Raise a PointsError naming the rows of ``flat`` ``(N, D)`` that hold NaN or inf."""
    if flat.shape[0] == 0:
        return
    # (a NaN or an inf anywhere shows in the columns' min or max: one pass, a quarter of the time
    # of isfinite's; the rows are looked for only then)
    if bool(torch.isfinite(torch.stack(torch.aminmax(flat.detach(), dim=0))).all()):
        return
    step = 1 << 20  # check in slices: no temporary grows with the number of points
    for start in range(0, flat.shape[0], step):
        bad = ~torch.isfinite(flat[start : start + step]).all(dim=1)
        if bool(bad.any()):
            idx = (torch.nonzero(bad).flatten()[:10] + start).tolist()
            raise PointsError(f"points contain NaN or inf (flattened indices {idx}); remove or fix them")


def result_dtype(
    points: torch.Tensor, cage: Cage, dtype: torch.dtype | None, backend: str = "auto"
) -> tuple[torch.dtype, torch.dtype]:
    """(compute dtype, output dtype): compute in float64; return in the promoted dtype of the inputs
    unless ``dtype`` is given explicitly. ``backend="triton"`` with ``dtype=torch.float32`` computes
    in float32 (the Triton kernel keeps its stable forms in float32: docs/gpu.md).

    A lower ``dtype`` (float32, float16, bfloat16) is the output dtype: the kernels still compute
    in float64 (an automatic promotion, documented in docs/accuracy.md). Evaluated in float32, these
    closed forms lose up to the whole cage size in linear precision near the cage (cancellations of
    order ``eps32 * size / distance``) and their total weight underflows far away; float64 keeps
    them within 1e-9. Devices without float64 (MPS) compute in the requested dtype.
    """
    if dtype is not None and not dtype.is_floating_point:
        raise TypeError(f"dtype must be a floating-point dtype, got {dtype}")
    compute = torch.float64
    if dtype is not None and (dtype.itemsize > 8 or points.device.type == "mps"):
        compute = dtype
    if backend == "triton" and dtype == torch.float32:
        compute = dtype
    out = torch.promote_types(points.dtype, cage.dtype) if dtype is None else dtype
    return compute, out


def default_chunk(num_faces: int, target: int = 1 << 16) -> int:
    """Points per chunk so that one ``(faces, chunk)`` temporary holds about ``target`` entries."""
    return max(64, target // max(1, num_faces))


def chunks(n: int, size: int, progress: bool | Callable[[int, int], None] = False, desc: str = "") -> Iterator[slice]:
    """Yield slices of ``range(n)`` of length ``size``; report progress when asked.

    ``progress`` may be ``True`` (a tqdm bar when tqdm is installed, else a line on stderr) or a
    callable ``progress(done, total)``.
    """
    if size <= 0:
        raise ValueError(f"chunk_size must be positive, got {size}")
    total = max(1, math.ceil(n / size))
    bar = None
    if progress is True:
        try:
            from tqdm.auto import tqdm

            bar = tqdm(total=n, desc=desc or "points", unit="pt", unit_scale=True, leave=False)
        except ImportError:  # pragma: no cover - tqdm is a dependency, but keep a fallback
            bar = None
    for k in range(total):
        start, stop = k * size, min(n, (k + 1) * size)
        yield slice(start, stop)
        if bar is not None:
            bar.update(stop - start)
        elif callable(progress):
            progress(stop, n)
        elif progress is True:
            print(f"\r{desc} {stop}/{n}", end="", file=sys.stderr)
    if bar is not None:
        bar.close()


def unique_face_edges(tri: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Unique edges of triangles ``tri`` ``(T, 3)``: ``(edges (E, 2)`` sorted pairs,
    ``face_edge (T, 3)`` the index of the edge opposite each corner, ``sign (T, 3)`` +1 where that
    edge is stored as ``(t[i+1], t[i+2])``, else -1 (float64)``)``.

    Examples:
        >>> edges, face_edge, sign = unique_face_edges(torch.tensor([[0, 1, 2], [0, 2, 3]]))
        >>> edges.shape[0], face_edge.tolist()
        (5, [[3, 1, 0], [4, 2, 1]])
    """
    plain = type(tri) is torch.Tensor and not is_functorch_wrapped_tensor(tri)  # (no fake or vmapped table)
    if plain and tri.device.type == "cpu" and tri.dim() == 2 and tri.shape[1] == 3:
        # (a plain CPU table, the native kernels' case: computed once per topology; torch.unique
        # took 0.6 ms on 92 triangles and 1.8 ms on 300, 1.5% of a mean value call, on every call)
        cached = _unique_face_edges_cached(tri.dtype, tri.shape[0], tri.contiguous().numpy().tobytes())
        return tuple(t.clone() for t in cached)  # type: ignore[return-value]
    return _unique_face_edges(tri)


def _unique_face_edges(tri: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`unique_face_edges`, computed."""
    opp = torch.stack([tri.roll(-1, dims=1), tri.roll(-2, dims=1)], dim=-1)  # (T, 3, 2)
    lo, hi = torch.minimum(opp[..., 0], opp[..., 1]), torch.maximum(opp[..., 0], opp[..., 1])
    uniq, inv = torch.unique(torch.stack([lo, hi], dim=-1).reshape(-1, 2), dim=0, return_inverse=True)
    sign = torch.where(opp[..., 0] == lo, 1.0, -1.0).to(torch.float64)
    return uniq, inv.reshape(-1, 3), sign


@functools.lru_cache(maxsize=32)
def _unique_face_edges_cached(
    dtype: torch.dtype, T: int, table: bytes
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`unique_face_edges` of the CPU table ``(T, 3)`` of ``dtype`` whose bytes are ``table``
    (the key is the table's content: a cage edited in place is a new key). The caller gets clones."""
    tri = torch.frombuffer(bytearray(table), dtype=dtype).reshape(T, 3) if T else torch.empty(0, 3, dtype=dtype)
    return _unique_face_edges(tri)


def jacobian_rows(y: torch.Tensor, x: torch.Tensor, create_graph: bool) -> list[torch.Tensor]:
    """``[d y / d x[:, c]`` ``(n, V)`` for each ``c]`` of a row-wise map ``y (n, V) = f(x (n, D))``
    (row ``p`` of ``y`` depends on row ``p`` of ``x`` only), by differentiating the vector-Jacobian
    product ``r(Z) = J^T Z`` (linear in ``Z``) with respect to ``Z``: ``D + 1`` backward passes."""
    Z = torch.zeros_like(y, requires_grad=True)
    (r,) = torch.autograd.grad(y, x, Z, create_graph=True)
    D = x.shape[1]
    return [torch.autograd.grad(r[:, c].sum(), Z, retain_graph=True, create_graph=create_graph)[0] for c in range(D)]


def collapsed_gauss(order: int, dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Gauss–Legendre rule on the unit triangle by the collapsed square ``s = u, t = v (1 - u)``.

    Returns:
        ``(bary (Q, 3), weights (Q,))``: barycentric coordinates of the ``Q = order^2`` nodes and
        weights summing to 1/2 (the reference triangle's area).

    Examples:
        >>> import torch
        >>> bary, w = collapsed_gauss(3, torch.float64, torch.device("cpu"))
        >>> bary.shape, round(float(w.sum()), 12)
        (torch.Size([9, 3]), 0.5)
    """
    bary, weight = _collapsed_gauss(order)
    # (fresh tensors: the cached arrays stay unchanged whatever a caller does with them)
    return torch.tensor(bary, dtype=dtype, device=device), torch.tensor(weight, dtype=dtype, device=device)


@functools.lru_cache(maxsize=16)
def _collapsed_gauss(order: int) -> tuple[Any, Any]:
    """:func:`collapsed_gauss`'s float64 nodes and weights as read-only numpy arrays, computed once
    per order (numpy's ``leggauss`` solves an eigenproblem: 0.1 ms per call)."""
    import numpy as np

    g, w = np.polynomial.legendre.leggauss(order)
    g, w = (g + 1) / 2, w / 2
    u, v = np.meshgrid(g, g, indexing="ij")
    wu, wv = np.meshgrid(w, w, indexing="ij")
    s, t = u.ravel(), (v * (1 - u)).ravel()
    weight = (wu * wv * (1 - u)).ravel()
    bary = np.stack([1 - s - t, s, t], axis=1)
    bary.flags.writeable = False
    weight.flags.writeable = False
    return bary, weight
