"""What a made cage must satisfy, as checks that return the offenders: self-intersections,
enclosure (signed clearance of the shape's points) and tightness (distance from the cage to the
shape).

Crossings of quads are checked through both of their triangulations (along ``q0-q2`` and
``q1-q3``): the bilinear patch of a quad lies in the tetrahedron of its corners, whose four faces
are those two triangulations' triangles, so a surface whose both triangulations are free of
crossings has no face entering a patch's tetrahedron.

Enclosure of quads is measured on two closed surfaces, and a point must be inside both: the split
along ``q0-q2`` (what :meth:`torchcage.Cage.triangulated` and MVC see) and the bilinear patches
themselves (what QMVC and QGC see), on an ``n x n`` grid per quad (:func:`patch_grid`) whose
distance to the patch is bounded and subtracted. (Demanding clearance from the ``q1-q3`` split
instead of the patch, as an earlier version did, pushed bent quads' corners out by their whole
bend.)
"""

from __future__ import annotations

import math

import torch

from torchcage._intersections import edge_triangle_crossings
from torchcage.geometry import nearest_triangle, winding_number

__all__ = [
    "both_triangulations",
    "crossing_quads",
    "folded_edges",
    "measured_surfaces",
    "patch_grid",
    "self_intersections",
    "signed_clearance",
    "tightness",
    "unique_edges",
]

#: Cells per side of the grid on which a quad's bilinear patch is measured.
PATCH_GRID = 5


def both_triangulations(triangles: torch.Tensor, quads: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The triangles ``(T + 2 Q, 3)`` of the split along ``q0-q2`` (the :class:`~torchcage.Cage`
    convention) and those ``(T + 2 Q, 3)`` of the split along ``q1-q3``.

    Examples:
        >>> a, b = both_triangulations(torch.zeros(0, 3, dtype=torch.long), torch.tensor([[0, 1, 2, 3]]))
        >>> a.tolist(), b.tolist()
        ([[0, 1, 2], [0, 2, 3]], [[0, 1, 3], [1, 2, 3]])
    """
    q = quads
    split02 = torch.cat([triangles, q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    split13 = torch.cat([triangles, q[:, [0, 1, 3]], q[:, [1, 2, 3]]])
    return split02, split13


def unique_edges(triangles: torch.Tensor) -> torch.Tensor:
    """The edges ``(E, 2)`` of triangles ``(T, 3)``, each once, smaller index first.

    Examples:
        >>> unique_edges(torch.tensor([[0, 1, 2], [2, 1, 3]])).tolist()
        [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]
    """
    e = torch.cat([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    return torch.unique(e.sort(dim=1).values, dim=0)


def folded_edges(vertices: torch.Tensor, triangles: torch.Tensor, cosine: float = -0.98) -> torch.Tensor:
    """Edges ``(K, 2)`` whose two triangles fold back onto each other (unit normals with a cosine
    below ``cosine``): the overlap of adjacent faces that the crossing test does not see.

    Examples:
        >>> v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.1, 0.9, 1e-3]])
        >>> folded_edges(v, torch.tensor([[0, 1, 2], [1, 0, 3]])).tolist()
        [[0, 1]]
    """
    v = vertices.detach().to(torch.float64)
    p = v[triangles]
    n = torch.nn.functional.normalize(torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1), dim=-1)
    e = torch.cat([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]).sort(dim=1).values
    owner = torch.arange(triangles.shape[0]).repeat(3)
    key = e[:, 0] * v.shape[0] + e[:, 1]
    order = torch.argsort(key, stable=True)
    key, owner, e = key[order], owner[order], e[order]
    pair = torch.nonzero(key[1:] == key[:-1]).flatten()
    cos = (n[owner[pair]] * n[owner[pair + 1]]).sum(-1)
    return e[pair[cos < cosine]]


def self_intersections(vertices: torch.Tensor, triangles: torch.Tensor, quads: torch.Tensor | None = None) -> int:
    """The number of self-intersections of a closed surface: edge-face crossings between faces that
    share no vertex, plus folded edges (:func:`folded_edges`); with quads, in either triangulation.

    Args:
        vertices: ``(V, 3)``.
        triangles: ``(T, 3)``.
        quads: ``(Q, 4)`` or ``None``.

    Returns:
        the count (0 for a surface free of self-intersections).

    Examples:
        >>> import torchcage
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
        >>> self_intersections(cube.vertices, cube.triangles, cube.quads)
        0
    """
    v = vertices.detach().to(torch.float64)
    quads = torch.zeros((0, 4), dtype=torch.long) if quads is None else quads
    count = 0
    for tri in both_triangulations(triangles, quads) if quads.shape[0] else (triangles,):
        count += edge_triangle_crossings(v, unique_edges(tri), tri).shape[0] + folded_edges(v, tri).shape[0]
    return count


def patch_grid(
    vertices: torch.Tensor, quads: torch.Tensor, n: int = PATCH_GRID
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Bilinear patches of quads on an ``n x n`` grid of their parameter square, two triangles a cell.

    On a cell of side ``h`` the patch ``x(u, v)`` differs from the two triangles by the twist term
    ``(q0 - q1 + q2 - q3) du dv`` with ``du dv <= h^2 / 4``: every point of the patch is within
    ``|q0 - q1 + q2 - q3| / (4 n^2)`` of the grid and back.

    Args:
        vertices: ``(V, 3)``.
        quads: ``(Q, 4)``.
        n: cells per side.

    Returns:
        the grid's points ``(Q (n + 1)^2, 3)``, triangles ``(2 Q n^2, 3)`` (indices into those points,
        oriented like the quads) and each triangle's distance bound to the patch ``(2 Q n^2,)``.

    Examples:
        >>> q = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 1], [0, 1, 0]])  # a bent quad
        >>> p, t, slack = patch_grid(q, torch.tensor([[0, 1, 2, 3]]), n=2)
        >>> p.shape, t.shape, round(float(slack[0]), 4)  # |twist| = 1: slack 1 / 16
        (torch.Size([9, 3]), torch.Size([8, 3]), 0.0625)
    """
    s = torch.linspace(0.0, 1.0, n + 1, dtype=vertices.dtype, device=vertices.device)
    u, w = (g.flatten() for g in torch.meshgrid(s, s, indexing="ij"))  # u along q0 -> q1, w along q0 -> q3
    basis = torch.stack([(1 - u) * (1 - w), u * (1 - w), u * w, (1 - u) * w], dim=1)  # ((n+1)^2, 4)
    q = vertices[quads]  # (Q, 4, 3)
    points = torch.einsum("gk,qkd->qgd", basis, q).reshape(-1, 3)
    at = torch.arange((n + 1) ** 2, device=quads.device).reshape(n + 1, n + 1)
    a, b, c, d = at[:-1, :-1].flatten(), at[1:, :-1].flatten(), at[1:, 1:].flatten(), at[:-1, 1:].flatten()
    cell = torch.cat([torch.stack([a, b, c], dim=1), torch.stack([a, c, d], dim=1)])  # (2 n^2, 3)
    offset = (torch.arange(quads.shape[0], device=quads.device) * (n + 1) ** 2)[:, None, None]
    triangles = (cell[None] + offset).reshape(-1, 3)
    twist = (q[:, 0] - q[:, 1] + q[:, 2] - q[:, 3]).norm(dim=-1)
    return points, triangles, (twist / (4 * n * n)).repeat_interleave(2 * n * n)


def measured_surfaces(
    vertices: torch.Tensor, triangles: torch.Tensor, quads: torch.Tensor
) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    """The closed surfaces a point must be inside of to be inside the cage: the ``q0-q2`` split, and
    (with quads) the triangles plus the quads' patch grids (:func:`patch_grid`).

    Each is ``(points (P, 3), triangles (F, 3), slack (F,))``, where ``slack`` bounds how far a
    triangle is from the surface it stands for (0 for flat faces). The layout depends only on the
    faces, so the surfaces of two poses of one cage correspond face by face.

    Examples:
        >>> import torchcage
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
        >>> [t.shape[0] for _, t, _ in measured_surfaces(cube.vertices, cube.triangles, cube.quads)]
        [12, 300]
    """
    split02, _ = both_triangulations(triangles, quads)
    flat = vertices.new_zeros(split02.shape[0])
    surfaces = [(vertices, split02, flat)]
    if quads.shape[0]:
        p, t, slack = patch_grid(vertices, quads)
        surfaces.append(
            (
                torch.cat([vertices, p]),
                torch.cat([triangles, t + vertices.shape[0]]),
                torch.cat([vertices.new_zeros(triangles.shape[0]), slack]),
            )
        )
    return surfaces


def crossing_quads(vertices: torch.Tensor, triangles: torch.Tensor, quads: torch.Tensor) -> torch.Tensor:
    """Which quads take part in a self-intersection (:func:`self_intersections`) of either
    triangulation: one of their triangles is crossed, or an edge with both ends on the quad
    crosses or folds.

    Args:
        vertices: ``(V, 3)``.
        triangles: ``(T, 3)``, quads ``(Q, 4)``: the faces.

    Returns:
        ``(Q,)`` bool.

    Examples:
        >>> import torchcage
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
        >>> crossing_quads(cube.vertices, cube.triangles, cube.quads).any().item()
        False
    """
    v = vertices.detach().to(torch.float64)
    T, Q = triangles.shape[0], quads.shape[0]
    hit = torch.zeros(Q, dtype=torch.bool)
    for tri in both_triangulations(triangles, quads):
        edges = unique_edges(tri)
        pairs = edge_triangle_crossings(v, edges, tri)
        t = pairs[:, 1][pairs[:, 1] >= T]
        hit[(t - T) % max(Q, 1)] = True
        for e in (edges[pairs[:, 0]], folded_edges(v, tri)):
            hit |= (
                (quads[:, :, None] == e[None, None, :, 0])
                .any(1)
                .logical_and((quads[:, :, None] == e[None, None, :, 1]).any(1))
                .any(-1)
            )
    return hit


def signed_clearance(
    points: torch.Tensor,
    vertices: torch.Tensor,
    triangles: torch.Tensor,
    quads: torch.Tensor | None = None,
    *,
    below: float = math.inf,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed distance ``(N,)`` of points to a closed surface, positive inside (by winding number),
    and the nearest face ``(N,)`` (an index into ``triangles``, then ``T + q`` for quad ``q``).
    With quads, a point is inside if it is inside both of :func:`measured_surfaces` (the ``q0-q2``
    split and the bilinear patches), and its distance is a lower bound of the nearer one's.

    A patch is within ``|q0 - q1 + q2 - q3| / 4`` of its quad's ``q0-q2`` split, so that split less
    this slack bounds every point's distance from below first; only points whose bound is under
    ``below`` are measured on the patch grids (the others keep the bound, which is then at least
    ``below``, and their side, which the patch cannot change that far from the split).

    Examples:
        >>> import torchcage
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))  # [-1, 1]^3
        >>> s, _ = signed_clearance(torch.tensor([[0.0, 0, 0.5], [0, 0, 3]]), cube.vertices, cube.triangles, cube.quads)
        >>> s.tolist()
        [0.5, -2.0]
    """
    x = points.detach().to(torch.float64)
    v = vertices.detach().to(torch.float64)
    quads = torch.zeros((0, 4), dtype=torch.long) if quads is None else quads
    T, Q = triangles.shape[0], quads.shape[0]
    (p, split02, _), *patches = measured_surfaces(v, triangles, quads)
    d, i = nearest_triangle(x, p, split02)
    face = torch.where(i < T, i, T + (i - T) % max(Q, 1))
    inside = winding_number(x, p, split02) > 0.5
    if patches:
        q = v[quads]
        sag = (q[:, 0] - q[:, 1] + q[:, 2] - q[:, 3]).norm(dim=-1) / 4
        bound, _ = nearest_triangle(x, p, split02, slack=torch.cat([sag.new_zeros(T), sag, sag]))
        coarse = bound >= max(below, 0.0)
        fine = torch.nonzero(~coarse).flatten()
        d = torch.where(coarse, torch.minimum(d, bound), d)
        (pp, tp, slack), x_fine = patches[0], x[fine]
        dp, ip = nearest_triangle(x_fine, pp, tp, slack=slack)
        closer = dp < d[fine]
        d[fine] = torch.where(closer, dp, d[fine])
        face[fine] = torch.where(closer, torch.where(ip < T, ip, T + (ip - T) // (2 * PATCH_GRID**2)), face[fine])
        inside[fine] &= winding_number(x_fine, pp, tp) > 0.5
    return torch.where(inside, d, -d.abs().clamp_min(torch.finfo(d.dtype).tiny)), face


def tightness(
    vertices: torch.Tensor,
    triangles: torch.Tensor,
    quads: torch.Tensor,
    mesh_vertices: torch.Tensor,
    mesh_faces: torch.Tensor | None,
) -> torch.Tensor:
    """Distances ``(V + T + Q,)`` from the cage's vertices and face centroids to the shape: its
    triangles, or its points for a point cloud (``mesh_faces=None``).

    Examples:
        >>> import torchcage
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))  # [-1, 1]^3
        >>> d = tightness(cube.vertices, cube.triangles, cube.quads, torch.zeros(1, 3, dtype=torch.float64), None)
        >>> round(float(d.max()), 6), round(float(d.min()), 6)
        (1.732051, 1.0)
    """
    v = vertices.detach().to(torch.float64)
    probes = [v]
    if triangles.shape[0]:
        probes.append(v[triangles].mean(1))
    if quads.shape[0]:
        probes.append(v[quads].mean(1))
    x = torch.cat(probes)
    m = mesh_vertices.detach().to(torch.float64)
    if mesh_faces is None:
        rows = max(1, (1 << 22) // max(1, m.shape[0]))
        return torch.cat([torch.cdist(x[s : s + rows], m).amin(1) for s in range(0, x.shape[0], rows)])
    return nearest_triangle(x, m, mesh_faces, chunk=1 << 22)[0]
