"""Quad-dominant cages from triangle cages: adjacent triangles paired into quads by a maximum
weight matching of the dual graph (networkx, blossom algorithm).

Every pair of triangles across an edge is a candidate quad; it is kept when its other split
(along ``q1-q3``) crosses no face of the triangle surface, and the quad is valid for
quad mean value coordinates with a margin (all pairwise cosines of its four corner normals at
least ``min_cosine``, see :meth:`torchcage.Cage.invalid_quads`), and weighted by that smallest
cosine, so that the matching pairs as many triangles as it can (``maxcardinality``) and among
those prefers flat, convex quads. The dual graph of a closed triangle surface is cubic and
bridgeless, so without the validity filter a perfect matching always exists (Petersen's theorem).

A quad is written so that its ``q0-q2`` diagonal is the edge the two triangles shared: the
triangulation that :meth:`torchcage.Cage.triangulated` uses is then the triangle cage itself.
"""

from __future__ import annotations

import torch

from torchcage._intersections import edge_triangle_crossings
from torchcage.cagegen._deps import require
from torchcage.cagegen.checks import crossing_quads, unique_edges

#: Candidate quads need all pairwise corner-normal cosines at least this (strictly valid, not bent).
MIN_COSINE = 0.1
#: Where chosen quads' other splits cross each other, those pairs are banned and the matching
#: redone, at most this often.
REMATCHES = 3


def corner_cosines(quads: torch.Tensor) -> torch.Tensor:
    """Smallest pairwise cosine ``(Q,)`` of the unit corner normals of quads ``(Q, 4, 3)``
    (positive exactly for quads valid for QMVC).

    Examples:
        >>> square = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]])
        >>> corner_cosines(square).tolist()
        [1.0]
    """
    e = quads.roll(-1, dims=-2) - quads
    c = torch.nn.functional.normalize(torch.linalg.cross(e.roll(1, dims=-2), e, dim=-1), dim=-1)
    return (c @ c.transpose(-1, -2)).flatten(-2).amin(-1)


def _other_split_crosses(vertices: torch.Tensor, triangles: torch.Tensor, quads: torch.Tensor) -> torch.Tensor:
    """Which candidate quads ``(C,)`` bool (``q0-q2`` an edge of ``triangles``) would cross the
    triangle surface through their other split: its diagonal ``q1-q3`` through a triangle, or an
    edge of the surface through one of the split's two triangles."""
    other = torch.cat([quads[:, [0, 1, 3]], quads[:, [1, 2, 3]]])  # (2 C, 3)
    edges = unique_edges(triangles)
    C = quads.shape[0]
    hit = torch.zeros(C, dtype=torch.bool)
    hit[edge_triangle_crossings(vertices, quads[:, [1, 3]], triangles)[:, 0]] = True
    hit[edge_triangle_crossings(vertices, edges, other)[:, 1] % max(C, 1)] = True
    return hit


def pair_triangles(
    vertices: torch.Tensor, triangles: torch.Tensor, min_cosine: float = MIN_COSINE
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pair the triangles of a closed surface into quads.

    Args:
        vertices: ``(V, 3)``.
        triangles: ``(T, 3)`` outward.
        min_cosine: the validity margin of a candidate quad (see the module docstring).

    Returns:
        ``triangles (T', 3)`` left unpaired and ``quads (Q, 4)`` (``T' + 2 Q = T``), outward.

    Examples:
        >>> import torchcage
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> t, q = pair_triangles(cube.vertices, cube.triangles)
        >>> t.shape[0], q.shape[0]
        (0, 6)
    """
    nx = require("networkx")
    tri = triangles.cpu()
    T = tri.shape[0]
    directed = torch.stack([tri, tri.roll(-1, dims=1)], dim=-1).reshape(-1, 2)  # (3T, 2): edge k of t is row 3t+k
    key = directed.sort(dim=1).values
    key = key[:, 0] * (int(tri.max()) + 1) + key[:, 1]
    order = torch.argsort(key, stable=True)
    same = torch.nonzero(key[order][1:] == key[order][:-1]).flatten()
    r1, r2 = order[same], order[same + 1]  # rows of the two triangles' copies of each shared edge
    t1, k1, t2, k2 = r1 // 3, r1 % 3, r2 // 3, r2 % 3
    rows = torch.arange(t1.shape[0])
    # t1 = (a, b, c) rotated so that the shared edge is b -> c; t2 holds it as c -> b, opposite corner d.
    b, c = tri[t1, k1], tri[t1, (k1 + 1) % 3]
    a = tri[t1, (k1 + 2) % 3]
    d = tri[t2, (k2 + 2) % 3]
    quads = torch.stack([b, d, c, a], dim=1)  # q0-q2 = b-c: the shared edge
    v = vertices.detach().to(torch.float64)
    score = corner_cosines(v[quads])
    ok = (score >= min_cosine) & ~_other_split_crosses(v, tri, quads)
    graph = nx.Graph()
    graph.add_nodes_from(range(T))
    for i, j, w, r in zip(t1[ok].tolist(), t2[ok].tolist(), score[ok].tolist(), rows[ok].tolist(), strict=True):
        graph.add_edge(i, j, weight=1.0 + w, row=r)
    best: tuple[torch.Tensor, torch.Tensor] | None = None
    for _ in range(REMATCHES + 1):
        matching = nx.max_weight_matching(graph, maxcardinality=True)
        chosen = torch.tensor([graph.edges[i, j]["row"] for i, j in matching], dtype=torch.long)
        used = torch.zeros(T, dtype=torch.bool)
        used[t1[chosen]] = used[t2[chosen]] = True
        left, made = tri[~used], quads[chosen]
        # two chosen quads' other splits may cross each other: those stay two triangles (the
        # triangle surface is free of crossings), and the pairs are banned from the next matching
        crossing = crossing_quads(v, left, made)
        left = torch.cat([left, made[crossing][:, [0, 1, 2]], made[crossing][:, [0, 2, 3]]])
        if best is None or int((~crossing).sum()) > best[1].shape[0]:
            best = (left, made[~crossing])
        if not crossing.any():
            break
        graph.remove_edges_from((int(t1[r]), int(t2[r])) for r in chosen[crossing].tolist())
    left, quads = best
    return left.to(triangles.device), quads.to(triangles.device)
