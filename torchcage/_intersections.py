"""Self-intersection tests of cages, vectorised and chunked: edges crossing triangles (3D) and
edges crossing edges (2D).

A closed surface intersects itself where an edge of one face passes through another face. The
3D test checks every edge against every triangle that shares no vertex with it (an
axis-aligned-box test first, then exact orientation signs), so it finds every crossing where the
surfaces pass through each other away from shared vertices. Touching and coplanar overlaps (signs
within rounding of zero) are not reported. The 2D test checks every pair of non-adjacent polygon
edges for a proper crossing (a bow-tie).
"""

from __future__ import annotations

import torch

__all__ = ["edge_edge_crossings", "edge_triangle_crossings"]

#: Orientation determinants below this fraction of ``size^3`` (``size^2`` in 2D) count as zero.
_RELATIVE_EPS = 1e-12


def _orient3(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Six times the signed volume of tetrahedra ``(a, b, c, d)``, all ``(..., 3)``."""
    return (torch.linalg.cross(b - a, c - a, dim=-1) * (d - a)).sum(-1)


def edge_triangle_crossings(
    vertices: torch.Tensor, edges: torch.Tensor, triangles: torch.Tensor, chunk: int = 1 << 20
) -> torch.Tensor:
    """Pairs ``(edge, triangle)`` where the segment properly crosses the triangle's interior.

    Args:
        vertices: ``(V, 3)``.
        edges: ``(E, 2)`` segment endpoints (indices).
        triangles: ``(T, 3)``.
        chunk: edge-triangle pairs tested at once (memory bound).

    Returns:
        ``(K, 2)`` int64 indices ``(edge, triangle)``; pairs sharing a vertex are not tested.

    Examples:
        >>> import torch
        >>> v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, -1], [0.2, 0.2, 1]], dtype=torch.float64)
        >>> edge_triangle_crossings(v, torch.tensor([[3, 4]]), torch.tensor([[0, 1, 2]])).tolist()
        [[0, 0]]
    """
    v = vertices.detach().to(torch.float64)
    size = float((v.amax(0) - v.amin(0)).norm()) if v.numel() else 0.0
    eps = _RELATIVE_EPS * size**3
    lo_t = v[triangles].amin(1)  # (T, 3)
    hi_t = v[triangles].amax(1)
    seg = v[edges]  # (E, 2, 3)
    lo_e, hi_e = seg.amin(1), seg.amax(1)
    T = triangles.shape[0]
    found = []
    step = max(1, chunk // max(1, T))
    for s in range(0, edges.shape[0], step):
        e = slice(s, s + step)
        overlap = ((lo_e[e, None] <= hi_t[None]) & (hi_e[e, None] >= lo_t[None])).all(-1)  # (e, T)
        ei, ti = torch.nonzero(overlap, as_tuple=True)
        if ei.numel() == 0:
            continue
        ei = ei + s
        shared = (edges[ei][:, :, None] == triangles[ti][:, None, :]).any(-1).any(-1)
        ei, ti = ei[~shared], ti[~shared]
        p, q = v[edges[ei, 0]], v[edges[ei, 1]]
        a, b, c = (v[triangles[ti, k]] for k in range(3))
        dp, dq = _orient3(a, b, c, p), _orient3(a, b, c, q)
        straddle = ((dp > eps) & (dq < -eps)) | ((dp < -eps) & (dq > eps))
        s1, s2, s3 = _orient3(p, q, a, b), _orient3(p, q, b, c), _orient3(p, q, c, a)
        inside = ((s1 > eps) & (s2 > eps) & (s3 > eps)) | ((s1 < -eps) & (s2 < -eps) & (s3 < -eps))
        hit = straddle & inside
        found.append(torch.stack([ei[hit], ti[hit]], dim=1))
    return torch.cat(found) if found else torch.zeros((0, 2), dtype=torch.long)


def edge_edge_crossings(vertices: torch.Tensor, edges: torch.Tensor, chunk: int = 1 << 20) -> torch.Tensor:
    """Pairs ``(i, j)``, ``i < j``, of polygon edges that properly cross (edges sharing a vertex are
    not tested).

    Args:
        vertices: ``(V, 2)``.
        edges: ``(E, 2)``.

    Returns:
        ``(K, 2)`` int64 edge indices.

    Examples:
        >>> import torch
        >>> bowtie = torch.tensor([[0.0, 0], [1, 1], [1, 0], [0, 1]], dtype=torch.float64)
        >>> edge_edge_crossings(bowtie, torch.tensor([[0, 1], [1, 2], [2, 3], [3, 0]])).tolist()
        [[0, 2]]
    """
    v = vertices.detach().to(torch.float64)
    size = float((v.amax(0) - v.amin(0)).norm()) if v.numel() else 0.0
    eps = _RELATIVE_EPS * size**2
    E = edges.shape[0]
    P, Q = v[edges[:, 0]], v[edges[:, 1]]

    def orient(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])

    found = []
    step = max(1, chunk // max(1, E))
    for s in range(0, E, step):
        i = torch.arange(s, min(E, s + step))
        ii, jj = torch.meshgrid(i, torch.arange(E), indexing="ij")
        keep = jj > ii
        ii, jj = ii[keep], jj[keep]
        shared = (edges[ii][:, :, None] == edges[jj][:, None, :]).any(-1).any(-1)
        ii, jj = ii[~shared], jj[~shared]
        a, b, c, d = P[ii], Q[ii], P[jj], Q[jj]
        d1, d2, d3, d4 = orient(a, b, c), orient(a, b, d), orient(c, d, a), orient(c, d, b)
        cross = (((d1 > eps) & (d2 < -eps)) | ((d1 < -eps) & (d2 > eps))) & (
            ((d3 > eps) & (d4 < -eps)) | ((d3 < -eps) & (d4 > eps))
        )
        found.append(torch.stack([ii[cross], jj[cross]], dim=1))
    return torch.cat(found) if found else torch.zeros((0, 2), dtype=torch.long)
