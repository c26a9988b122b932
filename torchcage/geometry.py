"""Small geometric predicates shared by the image warper and the domain mesher."""

from __future__ import annotations

import math

import torch

__all__ = [
    "distance_to_cage",
    "inside_cage",
    "inside_polygon",
    "near_cage",
    "nearest_triangle",
    "triangle_distances",
    "winding_number",
]


def inside_polygon(points: torch.Tensor, vertices: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Whether points lie inside a closed polygon (even-odd crossing rule), chunked over points.

    Args:
        points: ``(N, 2)`` points.
        vertices: ``(V, 2)`` polygon vertices.
        edges: ``(E, 2)`` directed edges (any orientation).

    Returns:
        ``(N,)`` bool; points exactly on an edge may go either way.

    Examples:
        >>> import torch
        >>> sq = torch.tensor([[0.0, 0], [2, 0], [2, 2], [0, 2]])
        >>> e = torch.tensor([[0, 1], [1, 2], [2, 3], [3, 0]])
        >>> inside_polygon(torch.tensor([[1.0, 1.0], [3.0, 1.0]]), sq, e)
        tensor([ True, False])
    """
    a, b = vertices[edges[:, 0]], vertices[edges[:, 1]]
    dy = b[:, 1] - a[:, 1]
    slope = (b[:, 0] - a[:, 0]) / torch.where(dy != 0, dy, 1.0)
    out = torch.empty(points.shape[0], dtype=torch.bool, device=points.device)
    step = max(1, (1 << 22) // max(1, edges.shape[0]))
    for s in range(0, points.shape[0], step):
        p = points[s : s + step]
        y = p[:, 1:2]
        spans = (a[:, 1] > y) != (b[:, 1] > y)
        crosses = spans & (p[:, 0:1] < a[:, 0] + (y - a[:, 1]) * slope)
        out[s : s + step] = crosses.sum(dim=1) % 2 == 1
    return out


def winding_number(
    points: torch.Tensor, vertices: torch.Tensor, triangles: torch.Tensor, backend: str = "auto"
) -> torch.Tensor:
    """Generalised winding number of a closed triangle surface at points: the sum of the signed
    solid angles of the triangles (Van Oosterom and Strackee) over 4 pi; 1 inside an outward
    oriented closed surface, 0 outside. Chunked over points.

    Args:
        points: ``(N, 3)``.
        vertices: ``(V, 3)``.
        triangles: ``(T, 3)`` outward oriented.
        backend: ``"auto"`` (the native kernel for float64 CPU tensors without a graph, 10x
            faster; else torch), ``"native"`` or ``"torch"``.

    Returns:
        ``(N,)`` winding numbers.

    Examples:
        >>> import torch, torchcage
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> w = winding_number(torch.tensor([[0.0, 0, 0], [3.0, 0, 0]]), cube.vertices.float(), cube.triangles)
        >>> w.double().round(decimals=6).tolist()
        [1.0, 0.0]
    """
    p = vertices[triangles]  # (T, 3, 3)
    out = torch.empty(points.shape[0], dtype=points.dtype, device=points.device)
    if backend != "torch":
        from torchcage.backends import Op, select
        from torchcage.backends import native as _native

        op = Op("winding numbers")
        lib = select(op, backend, points, p).lib if p.dtype == points.dtype or backend == "native" else None
        if lib is not None:  # (the same sums)
            _native.call(lib, "tc_winding3d", P=p.contiguous(), T=p.shape[0], X=points.contiguous(),
                         n=points.shape[0], W=out)  # fmt: skip
            return out
    step = max(1, (1 << 21) // max(1, triangles.shape[0]))
    for s in range(0, points.shape[0], step):
        x = points[s : s + step, None, None, :]
        a, b, c = (p[None, :, k] - x[:, :, 0] for k in range(3))
        la, lb, lc = a.norm(dim=-1), b.norm(dim=-1), c.norm(dim=-1)
        det = (a * torch.linalg.cross(b, c, dim=-1)).sum(-1)
        den = la * lb * lc + (a * b).sum(-1) * lc + (b * c).sum(-1) * la + (c * a).sum(-1) * lb
        out[s : s + step] = 2 * torch.atan2(det, den).sum(dim=1) / (4 * math.pi)
    return out


def inside_cage(points: torch.Tensor, cage) -> torch.Tensor:
    """Whether points lie inside a 2D or 3D cage (quads split along q0-q2), ``(N,)`` bool."""
    if cage.dim == 2:
        return inside_polygon(points, cage.vertices.to(points.dtype), cage.edges)
    tri = cage.triangulated().triangles if cage.has_quads else cage.triangles
    return winding_number(points, cage.vertices.to(points.dtype), tri) > 0.5


def _segment_distance(x: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Distances ``(n, E)`` from points ``(n, D)`` to segments ``a -> b`` ``(E, D)``."""
    ab = b - a
    rel = x[:, None, :] - a[None]
    t = ((rel * ab[None]).sum(-1) / (ab * ab).sum(-1).clamp_min(torch.finfo(x.dtype).tiny)).clamp(0, 1)
    return (rel - t[..., None] * ab[None]).norm(dim=-1)


def distance_to_cage(points: torch.Tensor, cage, chunk: int = 1 << 20) -> torch.Tensor:
    """Euclidean distance ``(N,)`` from points ``(N, D)`` to a cage's boundary: its polygon edges
    (2D) or its triangles (3D; quads split along ``q0-q2``). Brute force over the faces, in chunks
    of about ``chunk`` point-face pairs.

    Examples:
        >>> import torchcage
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))  # [-1, 1]^3
        >>> distance_to_cage(torch.tensor([[0.0, 0.0, 0.5], [3.0, 0.0, 0.0]]), cube).tolist()
        [0.5, 2.0]
    """
    v = cage.vertices.to(points.dtype)
    if cage.dim == 2:
        e = cage.edges
        rows = max(1, chunk // max(1, e.shape[0]))
        return torch.cat(
            [_segment_distance(points[s : s + rows], v[e[:, 0]], v[e[:, 1]]).min(dim=1).values
             for s in range(0, points.shape[0], rows)]
        ) if points.shape[0] else points.new_zeros(0)  # fmt: skip
    tri = cage.triangulated().triangles if cage.has_quads else cage.triangles
    return nearest_triangle(points, v, tri, chunk)[0]


def triangle_distances(x: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """Distances ``(n, T)`` from points ``(n, 3)`` to every triangle ``(T, 3, 3)``."""
    p = corners
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(x.dtype).tiny)
    best = torch.stack([_segment_distance(x, p[:, i], p[:, (i + 1) % 3]) for i in range(3)]).amin(dim=0)
    h = ((x[:, None, :] - p[None, :, 0]) * n[None]).sum(-1)  # (n, T)
    foot = x[:, None, :] - h[..., None] * n[None]
    inside = (n != 0).any(dim=-1)[None].expand_as(h)  # a degenerate triangle: its edges only
    for i in range(3):
        a, b = p[None, :, i], p[None, :, (i + 1) % 3]
        inside = inside & ((torch.linalg.cross(b - a, foot - a, dim=-1) * n[None]).sum(-1) >= 0)
    return torch.minimum(best, torch.where(inside, h.abs(), torch.inf))


def nearest_triangle(
    points: torch.Tensor,
    vertices: torch.Tensor,
    triangles: torch.Tensor,
    chunk: int = 1 << 20,
    *,
    slack: torch.Tensor | None = None,
    backend: str = "auto",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Distance ``(N,)`` from points ``(N, 3)`` to a triangle soup ``vertices (V, 3)``,
    ``triangles (T, 3)``, and the index ``(N,)`` of the nearest triangle. Brute force: the native
    kernel (float64 CPU tensors without a graph, about 20x faster) or torch in chunks of about
    ``chunk`` point-triangle pairs.

    A point or triangle with a NaN coordinate gives a NaN distance (both backends).

    Args:
        slack: ``(T,)`` subtracted from each triangle's distance before the minimum (a triangle
            that stands for a curved face within ``slack`` of it gives a lower bound of the
            distance to that face); ``None`` for none.
        backend: ``"auto"``, ``"native"`` or ``"torch"`` (as :func:`winding_number`).

    Examples:
        >>> v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5], [6, 5, 5], [5, 6, 5]])
        >>> d, t = nearest_triangle(torch.tensor([[0.2, 0.2, 1.0]]), v, torch.tensor([[0, 1, 2], [3, 4, 5]]))
        >>> d.tolist(), t.tolist()
        ([1.0], [0])
    """
    p = vertices.to(points.dtype)[triangles]  # (T, 3, 3)
    if slack is not None:
        if slack.shape != triangles.shape[:1]:
            raise ValueError(
                f"slack must have one value per triangle, shape ({triangles.shape[0]},), got {tuple(slack.shape)}"
            )
        slack = slack.to(points.dtype)
    if backend != "torch" and triangles.shape[0] and points.shape[0]:
        from torchcage.backends import Op, select
        from torchcage.backends import native as _native

        lib = select(Op("distances to triangles"), backend, points, p).lib
        if lib is not None:
            dist = torch.empty(points.shape[0], dtype=points.dtype)
            index = torch.empty(points.shape[0], dtype=torch.int32)
            _native.call(lib, "tc_nearest3d", P=p.contiguous(), T=p.shape[0],
                         S=None if slack is None else slack.contiguous(), X=points.contiguous(),
                         n=points.shape[0], D=dist, I=index)  # fmt: skip
            return dist, index.long()
    rows = max(1, chunk // max(1, triangles.shape[0]))
    dist, index = [], []
    for s in range(0, points.shape[0], rows):
        d = triangle_distances(points[s : s + rows], p)
        d, i = (d if slack is None else d - slack).min(dim=1)
        dist.append(d)
        index.append(i)
    if not dist:
        return points.new_zeros(0), torch.zeros(0, dtype=torch.long, device=points.device)
    return torch.cat(dist), torch.cat(index)


def near_cage(points: torch.Tensor, cage, radius: float, chunk: int = 1 << 22) -> torch.Tensor:
    """Whether points ``(N, D)`` lie within ``radius`` of a cage's boundary, ``(N,)`` bool: the
    faces' bounding boxes (grown by ``radius``) pick candidate pairs, and only those are measured
    (:func:`distance_to_cage` measures every pair).

    Examples:
        >>> import torchcage
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))  # [-1, 1]^3
        >>> near_cage(torch.tensor([[0.0, 0.0, 1.0 - 1e-9], [0.0, 0.0, 0.5]]), cube, 1e-6).tolist()
        [True, False]
    """
    v = cage.vertices.to(points.dtype)
    faces = cage.edges if cage.dim == 2 else (cage.triangulated().triangles if cage.has_quads else cage.triangles)
    corners = v[faces]  # (F, k, D)
    lo, hi = corners.amin(dim=1) - radius, corners.amax(dim=1) + radius
    out = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
    rows = max(1, chunk // max(1, faces.shape[0]))
    for s in range(0, points.shape[0], rows):
        x = points[s : s + rows]
        cand = ((x[:, None, :] >= lo[None]) & (x[:, None, :] <= hi[None])).all(dim=-1)  # (n, F)
        pi, fi = torch.nonzero(cand, as_tuple=True)
        if pi.numel() == 0:
            continue
        d = _pair_distance(x[pi], corners[fi])
        hit = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
        hit[pi[d <= radius]] = True
        out[s : s + rows] = hit
    return out


def _pair_distance(x: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """Distance ``(P,)`` from each point ``(P, D)`` to its own segment or triangle ``(P, k, D)``."""
    k = corners.shape[1]
    if k == 2:
        a, b = corners[:, 0], corners[:, 1]
        ab = b - a
        t = (((x - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(torch.finfo(x.dtype).tiny)).clamp(0, 1)
        return (x - a - t[:, None] * ab).norm(dim=-1)
    best = torch.full((x.shape[0],), torch.inf, dtype=x.dtype, device=x.device)
    for i in range(3):
        a, b = corners[:, i], corners[:, (i + 1) % 3]
        ab = b - a
        t = (((x - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(torch.finfo(x.dtype).tiny)).clamp(0, 1)
        best = torch.minimum(best, (x - a - t[:, None] * ab).norm(dim=-1))
    p0, p1, p2 = corners[:, 0], corners[:, 1], corners[:, 2]
    n = torch.linalg.cross(p1 - p0, p2 - p0, dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(x.dtype).tiny)
    h = ((x - p0) * n).sum(-1)
    foot = x - h[:, None] * n
    inside = (n != 0).any(dim=-1)  # a degenerate triangle: its edges only
    for i in range(3):
        a, b = corners[:, i], corners[:, (i + 1) % 3]
        inside = inside & ((torch.linalg.cross(b - a, foot - a, dim=-1) * n).sum(-1) >= 0)
    return torch.minimum(best, torch.where(inside, h.abs(), torch.inf))
