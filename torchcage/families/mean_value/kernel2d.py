"""Torch kernel of 2D mean value coordinates (closed polygons), chunk by chunk.

Floater 2003; Hormann & Floater 2006: ``w_j = (tan(α_{j-1}/2) + tan(α_j/2)) / r_j`` with the
half-angle tangent evaluated as ``sin α / (1 + cos α)`` or ``(1 - cos α) / sin α``, whichever does
not cancel. Points on an edge (within ``ON_CAGE_TOLERANCE`` times the cage size) get the linear
interpolation along it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchcage._core.common import nearest_where, on_cage_tolerance, outside_point, records_graph, safe_div, safe_sqrt
from torchcage.cage import Cage


@dataclass(frozen=True)
class PolygonData:
    vertices: torch.Tensor  # (2, V)
    edges: torch.Tensor  # (E, 2)
    edge_vec: torch.Tensor  # (2, E, 1)  p_k - p_j
    edge_len2: torch.Tensor  # (E, 1)
    tol: float


def polygon_data(cage: Cage, dtype: torch.dtype) -> PolygonData:
    v = cage.vertices.to(dtype)
    e = cage.edges
    d = v[e[:, 1]] - v[e[:, 0]]
    return PolygonData(
        vertices=v.T.contiguous(),
        edges=e,
        edge_vec=d.T.contiguous()[:, :, None],
        edge_len2=(d * d).sum(dim=1)[:, None],
        tol=on_cage_tolerance(cage),
    )


def _pair_terms(x: torch.Tensor, data: PolygonData) -> dict[str, torch.Tensor]:
    """Per edge-point quantities ``(E, n)``: ``a = p - x`` at both ends, their lengths, the cross
    and dot products of the two."""
    a_all = data.vertices[:, :, None] - x.T[:, None, :]  # (2, V, n)
    R_all = safe_sqrt((a_all * a_all).sum(dim=0))
    j, k = data.edges[:, 0], data.edges[:, 1]
    ajx, ajy = a_all[0].index_select(0, j), a_all[1].index_select(0, j)
    akx, aky = a_all[0].index_select(0, k), a_all[1].index_select(0, k)
    ex, ey = data.edge_vec[0], data.edge_vec[1]
    return {
        "ajx": ajx,
        "ajy": ajy,
        "Rj": R_all.index_select(0, j),
        "Rk": R_all.index_select(0, k),
        "cross": ajx * ey - ajy * ex,  # a_j ^ a_k = a_j ^ (p_k - p_j): twice the signed area (x, p_j, p_k)
        "dot": ajx * akx + ajy * aky,
    }


def _regular_weights(q: dict[str, torch.Tensor], data: PolygonData, V: int, scaled: bool = False) -> torch.Tensor:
    """Unnormalised weights ``(V, n)`` of points off the cage; with ``scaled``, times ``c*``, the
    cross product of each point's edge of smallest ``|cross|`` among those seen under an obtuse
    angle (whose ``tan(alpha/2) = (R_j R_k - d) / cross`` grows like one over the distance), that
    edge's term taken as ``R_j R_k - d`` (no division): the same coordinates once normalised, with
    derivatives that do not cancel next to an edge."""
    cross, dot, Rj, Rk = q["cross"], q["dot"], q["Rj"], q["Rk"]
    RR = Rj * Rk
    tan_half = torch.where(dot >= 0, safe_div(cross, RR + dot, RR + dot > 0), safe_div(RR - dot, cross, cross != 0))
    if scaled:
        cstar, is_best = nearest_where((dot < 0) & (cross != 0), cross)
        tan_half = torch.where(is_best, RR - dot, cstar * tan_half)
    W = cross.new_zeros((V, cross.shape[1]))
    W.index_add_(0, data.edges[:, 0], safe_div(tan_half, Rj, Rj > 0))
    W.index_add_(0, data.edges[:, 1], safe_div(tan_half, Rk, Rk > 0))
    return W


def mvc2d_chunk(x: torch.Tensor, data: PolygonData, scaled: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """2D counterpart of :func:`mvc3d_chunk`: ``x`` ``(n, 2)`` -> weights ``(V, n)`` and on-cage mask
    (``scaled``: see :func:`_regular_weights`).

    Points on the cage get the linear interpolation along the edge holding them, differentiable in
    the point and the edge's ends (the coordinates of the point's projection on the edge; constant
    at a vertex); their regular formula, which is singular there, is evaluated at a point off the
    cage instead when a graph is recorded, so that no NaN reaches the gradients.
    """
    V = data.vertices.shape[1]
    q = _pair_terms(x, data)
    j, k = data.edges[:, 0], data.edges[:, 1]
    ex, ey = data.edge_vec[0], data.edge_vec[1]
    Rj, Rk = q["Rj"], q["Rk"]
    # Points on an edge (or a vertex): linear interpolation along the edge.
    ell2 = data.edge_len2
    t = -(q["ajx"] * ex + q["ajy"] * ey) / ell2  # projection parameter of x on the edge, 0 at p_j
    dist = q["cross"].abs() / torch.sqrt(ell2)
    tol = data.tol
    on_edge = (dist <= tol) & (t >= -tol / torch.sqrt(ell2)) & (t <= 1 + tol / torch.sqrt(ell2))
    on_edge |= (Rj <= tol) | (Rk <= tol)
    on_cage = on_edge.any(dim=0)
    if not bool(on_cage.any()):
        return _regular_weights(q, data, V, scaled), on_cage
    if records_graph(x, data.vertices):
        W = _regular_weights(
            _pair_terms(torch.where(on_cage[:, None], outside_point(data.vertices.T), x), data), data, V, scaled
        )
    else:
        W = _regular_weights(q, data, V, scaled)
    cols = torch.nonzero(on_cage).squeeze(1)
    f = on_edge[:, cols].to(torch.int8).argmax(dim=0)
    tt = t[f, cols].clamp(0.0, 1.0)
    tt = torch.where(Rj[f, cols] <= tol, 0.0, torch.where(Rk[f, cols] <= tol, 1.0, tt))
    Wc = torch.zeros((V, cols.shape[0]), dtype=x.dtype, device=x.device)
    Wc = Wc.scatter_add(0, torch.stack([j[f], k[f]]), torch.stack([1.0 - tt, tt]))
    W = W.index_copy(1, cols, Wc)
    return W, on_cage
