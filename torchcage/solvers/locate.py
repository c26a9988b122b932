r"""Exact point location in a triangle or tetrahedral mesh: a uniform grid of cell bounding boxes.

Every cell is registered in each grid square (cube) its bounding box overlaps; a point's
candidates are the cells registered in its own square. A point inside a cell lies inside the
cell's bounding box, so the cell is among its candidates: the search is exact, however long and
thin the cell (a k-d tree on the centroids, searched for the nearest few, missed points inside
long thin tetrahedra whose centroid ranked beyond the candidates). The grid index of a coordinate
is ``floor((x - origin) / step)``, monotone under rounding, so a point on a bounding box's face is
found too.

Points in no cell lie outside the mesh (up to the barycentric tolerance): they get the exact
nearest point of the mesh's boundary (its faces that belong to one cell only) and their distance
to it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

__all__ = ["MeshLocator", "locate_points"]

#: Points whose smallest barycentric coordinate in their best cell is at least ``-INSIDE_TOL`` are
#: inside (the rounding of a point on a face).
INSIDE_TOL = 1e-9


def _boundary_faces(cells: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The faces of a mesh that belong to one cell only, ``(F, D)``, and those cells ``(F,)``."""
    k = cells.shape[1]
    faces = torch.cat([cells[:, [j for j in range(k) if j != i]] for i in range(k)])
    owner = torch.arange(cells.shape[0]).repeat(k)
    key = faces.sort(dim=1).values
    _, inverse, counts = torch.unique(key, dim=0, return_inverse=True, return_counts=True)
    once = counts[inverse] == 1
    return faces[once], owner[once]


def _closest_on_segments(x: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The closest points ``(n, D)`` of segments ``a -> b`` ``(n, D)`` to points ``x`` ``(n, D)``."""
    ab = b - a
    t = ((x - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-300)
    return a + t.clamp(0, 1)[:, None] * ab


def _closest_on_triangles(x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """The closest points ``(n, 3)`` of triangles ``p`` ``(n, 3, 3)`` to points ``x`` ``(n, 3)``: the
    projection on the plane where it falls inside, else the nearest of the three edges' closest
    points."""
    a, b, c = p[:, 0], p[:, 1], p[:, 2]
    n = torch.linalg.cross(b - a, c - a, dim=-1)
    nn = (n * n).sum(-1).clamp_min(1e-300)
    foot = x - (((x - a) * n).sum(-1) / nn)[:, None] * n
    # a zero-area face has no plane: only its edges' closest points count (its zero normal made the
    # side tests pass for any point, which then came back as its own closest point)
    inside = (n * n).sum(-1) > 0
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= (torch.linalg.cross(v - u, foot - u, dim=-1) * n).sum(-1) >= 0
    cands = torch.stack([_closest_on_segments(x, u, v) for u, v in ((a, b), (b, c), (c, a))], 1)  # (n, 3, 3)
    j = (cands - x[:, None]).square().sum(-1).argmin(dim=1)
    edge = cands[torch.arange(x.shape[0]), j]
    return torch.where(inside[:, None], foot, edge)


class _Grid:
    """One level of :class:`MeshLocator`: cells registered in the squares of a uniform grid of
    ``step`` that their bounding boxes overlap; only occupied squares are kept (sorted keys)."""

    def __init__(self, origin: torch.Tensor, extent: torch.Tensor, step: float, ids: torch.Tensor,
                 lo: torch.Tensor, hi: torch.Tensor) -> None:  # fmt: skip
        D = origin.shape[0]
        self.origin, self.step = origin, step
        self.n = torch.floor(extent / step).to(torch.int64) + 1
        i0, i1 = self.index(lo), self.index(hi)
        span = i1 - i0 + 1  # (c, D)
        per = span.prod(dim=1)
        total = int(per.sum())
        cell_of = torch.repeat_interleave(torch.arange(ids.shape[0]), per)
        local = torch.arange(total) - (torch.cumsum(per, 0) - per)[cell_of]
        strides = [1] * D
        for d in range(D - 2, -1, -1):
            strides[d] = strides[d + 1] * int(self.n[d + 1])
        self.strides = torch.tensor(strides, dtype=torch.int64)
        sq = torch.zeros(total, dtype=torch.int64)
        for d in range(D - 1, -1, -1):  # mixed-radix offsets in each cell's span
            sd = span[cell_of, d]
            sq += (i0[cell_of, d] + local % sd) * strides[d]
            local = local // sd
        sq, order = torch.sort(sq, stable=True)
        self.entries = ids[cell_of[order]]
        self.keys, counts = torch.unique_consecutive(sq, return_counts=True)
        self.starts = torch.cat([torch.zeros(1, dtype=torch.int64), torch.cumsum(counts, 0)])

    def index(self, x: torch.Tensor) -> torch.Tensor:
        """Grid indices ``(n, D)`` of points, clamped to the grid."""
        g = torch.floor((x - self.origin) / self.step).to(torch.int64)
        return torch.minimum(g.clamp_min(0), self.n - 1)

    def squares(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """For points ``(n, D)``: the first entry of their square and its count (0 off the grid)."""
        g = torch.floor((x - self.origin) / self.step)
        on = ((g >= 0) & (g < self.n.to(g.dtype))).all(dim=1)
        key = (torch.minimum(g.clamp_min(0).to(torch.int64), self.n - 1) * self.strides).sum(dim=1)
        if self.keys.numel() == 0:
            return torch.zeros_like(key), torch.zeros_like(key)
        pos = torch.searchsorted(self.keys, key).clamp(max=self.keys.numel() - 1)
        on &= self.keys[pos] == key
        return self.starts[pos], torch.where(on, self.starts[pos + 1] - self.starts[pos], 0)


class MeshLocator:
    """Exact point location in a simplicial mesh (see the module docstring).

    The grid is hierarchical: a cell goes to the level whose step is at least half its bounding
    box's largest side (steps growing by 4 from the cells' smallest size), so it overlaps at most
    ``3^D`` squares there; a query looks up its square at every level. Large and small cells then
    cost the same, however unevenly sized the mesh.

    Args:
        vertices: ``(Nv, D)`` float64 mesh vertices.
        cells: ``(C, D + 1)`` int64 triangles or tetrahedra.

    Examples:
        >>> v = torch.tensor([[0.0, 0], [1, 0], [0, 1], [1, 1]], dtype=torch.float64)
        >>> loc = MeshLocator(v, torch.tensor([[0, 1, 2], [1, 3, 2]]))
        >>> cell, bary, inside, dist = loc.query(torch.tensor([[0.9, 0.8], [2.0, 0.5]], dtype=torch.float64))
        >>> cell.tolist(), inside.tolist(), dist.tolist()
        ([1, 1], [True, False], [0.0, 1.0])
    """

    def __init__(self, vertices: torch.Tensor, cells: torch.Tensor) -> None:
        v = vertices.detach().to("cpu", torch.float64)
        cells = cells.to("cpu", torch.int64)
        self.vertices, self.cells = v, cells
        C, k = cells.shape
        D = k - 1
        self.dim = D
        p = v[cells]  # (C, D+1, D)
        self.p0 = p[:, 0]
        inv, info = torch.linalg.inv_ex((p[:, 1:] - p[:, :1]).transpose(1, 2))  # maps x - p0 to (b1..bD)
        self.usable = info == 0  # (a flat cell holds no point: it never wins)
        self.inv = torch.where(self.usable[:, None, None], inv, torch.zeros_like(inv))
        lo, hi = p.amin(dim=1), p.amax(dim=1)
        pad = INSIDE_TOL * (hi - lo).amax(dim=1, keepdim=True)  # (a point on a face, rounded out of the box)
        lo, hi = lo - pad, hi + pad
        self.lo, self.hi = lo, hi
        origin = v.amin(dim=0) if v.shape[0] else torch.zeros(D, dtype=torch.float64)
        extent = (v.amax(dim=0) - origin).clamp_min(0) if v.shape[0] else torch.zeros(D, dtype=torch.float64)
        diag = float(extent.norm()) or 1.0
        size = (hi - lo).amax(dim=1).clamp_min(1e-6 * diag)  # (a million squares per axis at most: int64 keys)
        self.grids: list[_Grid] = []
        if C:
            step = float(size.min()) / 2
            level = torch.ceil(torch.log(size / (2 * step)) / math.log(4)).clamp_min(0).to(torch.int64)
            for ell in torch.unique(level).tolist():
                ids = torch.nonzero(level == ell).flatten()
                self.grids.append(_Grid(origin, extent, step * 4**ell, ids, lo[ids], hi[ids]))
        self._faces: tuple | None = None

    def _bary(self, x: torch.Tensor, cell: torch.Tensor) -> torch.Tensor:
        b = torch.einsum("nij,nj->ni", self.inv[cell], x - self.p0[cell])
        return torch.cat([1 - b.sum(-1, keepdim=True), b], dim=-1)

    def query(
        self, points: torch.Tensor, max_pairs: int = 1 << 22
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Locate points.

        Args:
            points: ``(N, D)`` points (any float dtype; located in float64).
            max_pairs: bound on the point-candidate pairs held at once.

        Returns:
            ``cell (N,)``, ``bary (N, D + 1)`` (non-negative, summing to 1), ``inside (N,)`` and
            ``distance (N,)``: for points inside a cell, that cell and the point's barycentric
            coordinates (distance 0); for the others, the cell and coordinates of the nearest point
            of the mesh, and the distance to it.
        """
        x = points.detach().to("cpu", torch.float64)
        N, D = x.shape[0], self.dim
        cell = torch.zeros(N, dtype=torch.int64)
        bary = torch.zeros((N, D + 1), dtype=torch.float64)
        score = torch.full((N,), -math.inf, dtype=torch.float64)
        if N == 0 or self.cells.shape[0] == 0:
            return cell, bary, torch.zeros(N, dtype=torch.bool), torch.zeros(N, dtype=torch.float64)
        for grid in self.grids:
            start, count = grid.squares(x)
            s = 0
            while s < N:  # chunks of points whose candidate pairs fit in max_pairs
                csum = torch.cumsum(count[s:], 0)
                e = s + max(1, int(torch.searchsorted(csum, max_pairs, right=True)))
                c = count[s:e]
                pt = torch.repeat_interleave(torch.arange(s, e), c)
                if pt.numel():
                    off = torch.arange(pt.numel()) - torch.repeat_interleave(torch.cumsum(c, 0) - c, c)
                    cand = grid.entries[start[pt] + off]
                    inb = ((x[pt] >= self.lo[cand]) & (x[pt] <= self.hi[cand])).all(dim=1)  # (cheaper first)
                    pt, cand = pt[inb], cand[inb]
                    b = self._bary(x[pt], cand)
                    sc = torch.where(self.usable[cand], b.amin(dim=1), -math.inf)
                    best = torch.full((e - s,), -math.inf, dtype=torch.float64)
                    best.scatter_reduce_(0, pt - s, sc, reduce="amax")
                    # one winner per point: its first pair of the best score, if better than before
                    pair = torch.arange(pt.numel())
                    big = pt.numel()
                    first = torch.full((e - s,), big, dtype=torch.int64)
                    first.scatter_reduce_(0, pt - s, torch.where(sc == best[pt - s], pair, big), reduce="amin")
                    better = (first < big) & (best > score[s:e])
                    wi = first[better]
                    cell[pt[wi]] = cand[wi]
                    bary[pt[wi]] = b[wi]
                    score[pt[wi]] = sc[wi]
                s = e
        inside = score >= -INSIDE_TOL
        bary = bary.clamp_min(0.0)
        bary = bary / bary.sum(dim=1, keepdim=True).clamp_min(1e-300)
        distance = torch.zeros(N, dtype=torch.float64)
        out = torch.nonzero(~inside).flatten()
        if out.numel():
            c_out, b_out, d_out = self._nearest(x[out])
            cell[out], bary[out], distance[out] = c_out, b_out, d_out
        return cell, bary, inside, distance

    def _nearest(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The nearest points of the mesh's boundary to points ``x`` ``(n, D)`` (outside it): their
        cells, barycentric coordinates there and distances.

        Exact, without measuring every boundary face: the faces with the 8 nearest centroids give
        an upper bound ``r`` of the distance; a face nearer than ``r`` has its centroid within
        ``r + R`` of the point (``R`` the largest distance from a face's centroid to its corners),
        so the faces whose centroids a k-d tree finds in that ball are measured."""
        from scipy.spatial import cKDTree

        if self._faces is None:
            faces, owner = _boundary_faces(self.cells)
            corners = self.vertices[faces]  # (F, D, D)
            centre = corners.mean(dim=1)
            radius = float((corners - centre[:, None]).norm(dim=-1).max()) if faces.shape[0] else 0.0
            self._faces = (faces, owner, corners, cKDTree(centre.numpy()), radius)
        faces, owner, corners, tree, radius = self._faces
        n = x.shape[0]
        k = min(8, faces.shape[0])
        _, near = tree.query(x.numpy(), k=k)
        near = torch.from_numpy(near.reshape(n, k)).to(torch.int64)
        bound = self._distance(x.repeat_interleave(k, dim=0), near.reshape(-1)).reshape(n, k).amin(dim=1)
        balls = tree.query_ball_point(x.numpy(), (bound + radius).numpy() * (1 + 1e-12) + 1e-300)
        counts = torch.tensor([len(b) for b in balls], dtype=torch.int64)
        cand = torch.from_numpy(np.concatenate([np.asarray(b, dtype=np.int64) for b in balls]))
        pt = torch.repeat_interleave(torch.arange(n), counts)
        foot = self._closest(x[pt], cand)
        d = (foot - x[pt]).norm(dim=1)
        best = torch.full((n,), math.inf, dtype=torch.float64)
        best.scatter_reduce_(0, pt, d, reduce="amin")
        pair = torch.arange(pt.numel())
        first = torch.full((n,), pt.numel(), dtype=torch.int64)
        first.scatter_reduce_(0, pt, torch.where(d == best[pt], pair, pt.numel()), reduce="amin")
        j, foot = cand[first], foot[first]
        cell = owner[j]
        bary = self._bary(foot, cell).clamp_min(0.0)
        bary = bary / bary.sum(dim=1, keepdim=True).clamp_min(1e-300)
        return cell, bary, best

    def _closest(self, x: torch.Tensor, face: torch.Tensor) -> torch.Tensor:
        """The closest points ``(n, D)`` of boundary faces ``face`` ``(n,)`` to points ``(n, D)``."""
        p = self._faces[2][face]  # type: ignore[index]
        return _closest_on_triangles(x, p) if self.dim == 3 else _closest_on_segments(x, p[:, 0], p[:, 1])

    def _distance(self, x: torch.Tensor, face: torch.Tensor) -> torch.Tensor:
        return (self._closest(x, face) - x).norm(dim=1)


def locate_points(
    points: torch.Tensor, domain: Any, max_pairs: int = 1 << 22
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:meth:`MeshLocator.query` on a :class:`~torchcage.solvers.domain.Domain`'s mesh, with the
    locator built once per domain (kept on it)."""
    loc = getattr(domain, "_locator", None)
    if loc is None:
        loc = MeshLocator(domain.vertices, domain.cells)
        domain._locator = loc
    return loc.query(points, max_pairs)


def outside_points(
    points: torch.Tensor,
    inside: torch.Tensor,
    distance: torch.Tensor,
    domain,
    cage=None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Which points the caller should be warned about, ``(N,)`` bool: those in no cell of the mesh
    that lie farther from it than the rounding of their dtype (``64 eps`` of the mesh's size) and,
    when ``cage`` is given, outside the cage (bilinear quads). Points inside the cage but just
    outside the mesh (a mesh's chords cut inside a curved cage by about ``h^2`` times its
    curvature) take the value of the nearest mesh point without a word: a discretisation error
    like any other."""
    out = ~inside
    if not bool(out.any()):
        return out
    v = domain.vertices
    size = float((v.amax(dim=0) - v.amin(dim=0)).norm()) if v.shape[0] else 1.0
    eps = torch.finfo(dtype if dtype is not None and dtype.is_floating_point else torch.float64).eps
    out &= distance > 64 * eps * size
    if cage is not None and bool(out.any()):
        from torchcage.solvers.domain import inside_bilinear_cage

        idx = torch.nonzero(out).flatten()
        out[idx[inside_bilinear_cage(points.detach().to("cpu", torch.float64)[idx], cage)]] = False
    return out
