r"""Lipman, Levin and Cohen-Or's exterior extension of Green coordinates (2008, "extending the
coordinates outside the cage").

Inside the cage the Green map is ``F(x) = sum_i phi_i v_i + sum_j psi_j n_j = x``; outside it the
same integrals give ``F(x) = 0`` (Green's third identity). Across a face ``t_j`` the double-layer
potentials ``phi`` jump by the face's hat functions and the single-layer potential ``psi_j`` keeps
its value while its normal derivative jumps by one, so the interior coordinates continue
analytically through ``t_j`` as

    phi~_{j_k}(x) = phi_{j_k}(x) + alpha_k(x),    psi~_j(x) = psi_j(x) + h_j(x),

``alpha_k`` the (affine) barycentric coordinates of ``x``'s projection onto the plane of ``t_j``
and ``h_j`` its height above that plane. At rest ``sum_k alpha_k v_k + h_j n_j = x``, so the
continued coordinates reproduce every outside point; under a deformation the continued map is the
analytic continuation of the interior one through ``t_j``, so points crossing ``t_j`` move
continuously.

Every face gives its own continuation, and they differ away from the face. A point outside takes
a blend of the continuations through the faces nearest to it: face ``j`` at distance ``d_j`` gets
the weight ``max(0, 1 - (d_j - d) / (BLEND d))^2`` (``d`` the distance to the cage) times its shape
quality ``2 area / longest edge^2`` (a sliver's continuation extrapolates its hat functions by
the inverse of its width, so slivers defer to their neighbours), normalised. Each continuation
reproduces the rest pose, so the blend does; the weights are continuous in the point, so the
extended map is continuous outside the cage; on a face (``d = 0``) only that face has weight, so
the map continues the interior one across it. Near an edge both faces' weights meet, and there
their continuations agree to the distance from the edge.

All in torch ops: differentiable with respect to the points and the cage's vertices.
"""

from __future__ import annotations

import torch

from torchcage._core.common import safe_div, safe_sqrt
from torchcage.cage import Cage

__all__ = ["BLEND", "extend_outside", "exterior_terms"]

#: Relative width of the blend between the continuations of faces at nearly the same distance.
BLEND = 0.5

#: Point–face pairs per chunk.
_PAIRS = 1 << 18


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``(a * b).sum(-1)`` over the last axis (2 or 3 components), component by component: a
    reduction over an axis of 3 took ten times as long (5 ms for 616 x 300 pairs)."""
    out = a[..., 0] * b[..., 0]
    for k in range(1, a.shape[-1]):
        out = out + a[..., k] * b[..., k]
    return out


def _segment_distance2(y: torch.Tensor, e: torch.Tensor) -> torch.Tensor:
    """Squared distance from ``y`` ``(m, T, D)`` (relative to a segment's start) to the segment
    ``[0, e]`` ``(T, D)``; ``(m, T)``."""
    ee = _dot(e, e)
    t = safe_div(_dot(y, e), ee, ee > 0).clamp(0.0, 1.0)
    out = (y[..., 0] - t * e[..., 0]).square()  # (|y - t e|^2, component by component)
    for k in range(1, y.shape[-1]):
        out = out + (y[..., k] - t * e[..., k]).square()
    return out


def _terms3d(x: torch.Tensor, P: torch.Tensor, tri: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Per point–triangle pair: barycentrics of the projection ``(m, T, 3)``, height ``(m, T)``,
    distance ``(m, T)`` and the usable mask ``(T,)`` (triangles of nonzero area)."""
    a, b, c = P[tri[:, 0]], P[tri[:, 1]], P[tri[:, 2]]
    e1, e2 = b - a, c - a
    N = torch.linalg.cross(e1, e2, dim=-1)  # (T, 3), twice the area
    NN = _dot(N, N)
    ok = NN > 0
    y = x[:, None, :] - a[None]  # (m, T, 3)
    # (u x w) . N = (u x w) . N for the in-plane parts only: affine barycentrics of the projection,
    # (y x e2) . N = y . (e2 x N) and (e1 x y) . N = y . (N x e1) (no (m, T, 3) cross products)
    ab = safe_div(_dot(y, torch.linalg.cross(e2, N, dim=-1)), NN, ok)
    ac = safe_div(_dot(y, torch.linalg.cross(N, e1, dim=-1)), NN, ok)
    alpha = torch.stack([1 - ab - ac, ab, ac], dim=-1)
    h = safe_div(_dot(y, N), safe_sqrt(NN), ok)
    inside = (alpha >= 0).all(dim=-1)
    d2 = torch.minimum(
        torch.minimum(_segment_distance2(y, e1), _segment_distance2(y, e2)),
        _segment_distance2(x[:, None, :] - b[None], c - b),
    )
    d2 = torch.where(inside, h * h, d2)
    longest2 = torch.stack([_dot(e1, e1), _dot(e2, e2), _dot(c - b, c - b)]).max(dim=0).values
    quality = safe_div(safe_sqrt(NN), longest2, ok)
    return alpha, h, safe_sqrt(d2), ok & (quality > 0), quality


def _terms2d(x: torch.Tensor, P: torch.Tensor, edges: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """As :func:`_terms3d` for the edges of a polygon (outward normal on the right of each edge)."""
    a, b = P[edges[:, 0]], P[edges[:, 1]]
    e = b - a
    ee = _dot(e, e)
    ok = ee > 0
    y = x[:, None, :] - a[None]
    t = safe_div(_dot(y, e), ee, ok)
    alpha = torch.stack([1 - t, t], dim=-1)
    n = torch.stack([e[:, 1], -e[:, 0]], dim=-1)
    h = safe_div(_dot(y, n), safe_sqrt(ee), ok)
    return alpha, h, safe_sqrt(_segment_distance2(y, e)), ok, ok.to(x.dtype)


def exterior_terms(
    x: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The terms the blended continuation adds to the Green coordinates of outside points.

    Args:
        x: ``(m, D)`` points outside the cage.
        vertices: ``(V, D)`` cage vertices.
        faces: ``(T, D)`` triangles (3D) or edges (2D), outward oriented.

    Returns:
        ``(dphi (m, V), dpsi (m, T), distance (m,))``: add ``dphi`` to ``phi`` and ``dpsi`` to
        ``psi``; ``distance`` is each point's distance to the cage.

    Examples:
        >>> import torch
        >>> V = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], dtype=torch.float64)
        >>> E = torch.tensor([[0, 1], [1, 2], [2, 3], [3, 0]])
        >>> dphi, dpsi, d = exterior_terms(torch.tensor([[0.25, -0.125]], dtype=torch.float64), V, E)
        >>> dphi.tolist(), (dpsi + 0.0).tolist(), d.tolist()
        ([[0.75, 0.25, 0.0, 0.0]], [[0.125, 0.0, 0.0, 0.0]], [0.125])
    """
    terms = _terms3d if vertices.shape[-1] == 3 else _terms2d
    alpha, h, dist, ok, quality = terms(x, vertices, faces)
    far = torch.finfo(dist.dtype).max
    dist_ok = torch.where(ok, dist, far)
    dmin = dist_ok.min(dim=1).values  # (m,)
    # (a point at distance 0 is on the cage: only its faces at distance 0 get weight)
    tiny = torch.finfo(dist.dtype).tiny
    width = BLEND * dmin + tiny
    s = (1 - (dist_ok - dmin[:, None]) / width[:, None]).clamp_min(0.0)
    w = torch.where(ok, s * s * quality, 0.0)
    w = w / w.sum(dim=1, keepdim=True)  # the nearest face has a positive weight
    # (summed into the vertices' rows of the transpose: index_add along the first axis adds
    # contiguous rows; along the second it took 70 ms for 616 points on 300 faces)
    dphi_t = torch.zeros(vertices.shape[0], x.shape[0], dtype=x.dtype, device=x.device)
    dphi_t = dphi_t.index_add(0, faces.reshape(-1), (w[..., None] * alpha).reshape(x.shape[0], -1).T)
    return dphi_t.T, w * h, dmin


def extend_outside(
    points: torch.Tensor, cage: Cage, phi: torch.Tensor, psi: torch.Tensor, inplace: bool = False
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Green coordinates continued outside the cage (module docstring).

    Args:
        points: ``(N, D)`` checked points, in the compute dtype.
        cage: the (single) cage.
        phi: ``(N, V)`` Green coordinates of the points; ``psi`` ``(N, T)``.
        inplace: add the continuation into ``phi`` and ``psi`` themselves (tensors without a graph
            that the caller owns, such as a kernel's fresh outputs: no copy of the tables).

    Returns:
        ``(phi, psi, distance)``: the coordinates with the outside rows continued (new tensors
        unless ``inplace``), and ``(N,)`` each point's distance outside the cage (0 for points
        inside it or on it). Outside is where ``phi`` sums to less than 1/2 (the winding number:
        1 inside, 0 outside).
    """
    faces = cage.triangles if cage.dim == 3 else cage.edges
    rows = torch.nonzero(phi.detach().sum(dim=-1) < 0.5).squeeze(1)
    distance = torch.zeros(points.shape[0], dtype=points.dtype, device=points.device)
    if rows.numel() == 0:
        return phi, psi, distance
    P = cage.vertices.to(points.dtype)
    size = max(1, _PAIRS // max(1, faces.shape[0]))
    parts = [exterior_terms(points[rows[s : s + size]], P, faces) for s in range(0, rows.numel(), size)]
    dphi, dpsi, dist = (torch.cat(t) for t in zip(*parts, strict=True))
    if inplace:
        phi.index_add_(0, rows, dphi.to(phi.dtype))
        psi.index_add_(0, rows, dpsi.to(psi.dtype))
    else:
        phi = phi.index_add(0, rows, dphi.to(phi.dtype))
        psi = psi.index_add(0, rows, dpsi.to(psi.dtype))
    return phi, psi, distance.index_copy(0, rows, dist.detach())
