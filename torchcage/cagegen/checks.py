"""What a made cage must satisfy, as checks that return the offenders: self-intersections,
enclosure (signed clearance of the shape's points) and tightness (distance from the cage to the
shape).

Quads are checked through both of their triangulations (along ``q0-q2`` and ``q1-q3``): the
bilinear patch of a quad lies in the tetrahedron of its corners, between the two, so a point that
clears both clears the patch up to the quad's bend, and a surface whose both triangulations are
free of crossings has no crossing far from the bends.
"""

from __future__ import annotations

import torch

from .._intersections import edge_triangle_crossings
from ..geometry import nearest_triangle, winding_number

__all__ = ["both_triangulations", "folded_edges", "self_intersections", "signed_clearance", "tightness"]


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


def _edges(triangles: torch.Tensor) -> torch.Tensor:
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
        count += edge_triangle_crossings(v, _edges(tri), tri).shape[0] + folded_edges(v, tri).shape[0]
    return count


def signed_clearance(
    points: torch.Tensor, vertices: torch.Tensor, triangles: torch.Tensor, quads: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed distance ``(N,)`` of points to a closed surface, positive inside (by winding number),
    and the nearest face ``(N,)`` (an index into ``triangles``, then ``T + q`` for quad ``q``).
    With quads, the distance is the smaller of the two triangulations'.

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
    split02, split13 = both_triangulations(triangles, quads)
    d, i = nearest_triangle(x, v, split02)
    if Q:
        d13, i13 = nearest_triangle(x, v, split13)
        closer = d13 < d
        d, i = torch.where(closer, d13, d), torch.where(closer, i13, i)
    face = torch.where(i < T, i, T + (i - T) % max(Q, 1))
    inside = winding_number(x, v, split02) > 0.5
    return torch.where(inside, d, -d), face


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
