"""Enclosure repair: push a coarse cage's faces outward until every point of the shape is inside
it with a given clearance, without letting the surface pass through itself.

Each round measures the signed clearance of the points (:func:`.checks.signed_clearance`), takes
for every face the largest deficit of the points nearest to it, and moves the face's vertices along
their normals so that the face's plane moves by that deficit (times a small overshoot). A round
that would make the surface intersect itself is retried with the moves spread over the
neighbouring vertices (one Laplacian pass) and halved.
"""

from __future__ import annotations

import torch

from torchcage.cagegen.checks import both_triangulations, self_intersections, signed_clearance
from torchcage.errors import CageMakerError

#: Deficits are over-corrected by this factor, so that rounds do not crawl.
OVERSHOOT = 1.25


def vertex_normals(vertices: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals ``(V, 3)`` of a surface ``triangles (T, 3)``.

    Examples:
        >>> import torchcage
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> n = vertex_normals(cube.vertices, cube.triangles)
        >>> bool(((n * cube.vertices).sum(-1) > 0).all())
        True
    """
    p = vertices[triangles]
    fn = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    n = torch.zeros_like(vertices).index_add_(0, triangles.flatten(), fn.repeat_interleave(3, dim=0))
    return torch.nn.functional.normalize(n, dim=-1)


def _face_normals(vertices: torch.Tensor, triangles: torch.Tensor, quads: torch.Tensor) -> torch.Tensor:
    """Unit normals ``(T + Q, 3)`` of the triangles, then of the quads (of their diagonals' cross
    product, the mean normal of the bilinear patch)."""
    p = vertices[triangles]
    nt = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    q = vertices[quads]
    nq = torch.linalg.cross(q[:, 2] - q[:, 0], q[:, 3] - q[:, 1], dim=-1)
    return torch.nn.functional.normalize(torch.cat([nt, nq]), dim=-1)


def _smooth(push: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    """The larger of each vertex's push and the mean push of its neighbours (one pass)."""
    e = torch.cat([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    total = torch.zeros_like(push).index_add_(0, e[:, 0], push[e[:, 1]])
    count = torch.zeros_like(push).index_add_(0, e[:, 0], torch.ones_like(push[e[:, 1]]))
    return torch.maximum(push, total / count.clamp_min(1))


def push_outward(
    vertices: torch.Tensor,
    triangles: torch.Tensor,
    quads: torch.Tensor,
    points: torch.Tensor,
    clearance: float,
    *,
    rounds: int = 60,
) -> torch.Tensor:
    """Move cage vertices outward until every point is inside with at least ``clearance``.

    Args:
        vertices: ``(V, 3)`` float64 cage vertices (not modified).
        triangles: ``(T, 3)``, quads ``(Q, 4)``: the cage's faces, outward.
        points: ``(N, 3)`` the shape's points.
        clearance: the distance every point must keep from the cage.
        rounds: the most rounds.

    Returns:
        the moved vertices ``(V, 3)``.

    Raises:
        CageMakerError: the points are still not enclosed after ``rounds`` rounds, or every move
            would make the cage intersect itself.

    Examples:
        >>> import torchcage
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))  # [-1, 1]^3
        >>> v = push_outward(cube.vertices, cube.triangles, cube.quads, torch.tensor([[0.0, 0, 1.5]]), 0.1)
        >>> s, _ = signed_clearance(torch.tensor([[0.0, 0, 1.5]]), v, cube.triangles, cube.quads)
        >>> bool(s.item() >= 0.1)
        True
    """
    v = vertices.detach().to(torch.float64).clone()
    split02, _ = both_triangulations(triangles, quads)
    T, Q = triangles.shape[0], quads.shape[0]
    members = torch.cat([triangles.flatten(), quads.flatten()])  # (3 T + 4 Q,) a face's vertices ...
    rows = torch.cat([torch.arange(T).repeat_interleave(3), T + torch.arange(Q).repeat_interleave(4)])  # ... its row
    crossings = self_intersections(v, triangles, quads)
    # Only points that may have come closer than the clearance are measured again: a point's signed
    # distance changes by at most the surface's motion, and no surface point moves farther than the
    # farthest vertex (faces interpolate their vertices). So ``known - (drift - drift_then)`` is a
    # lower bound of each point's clearance now, and points whose bound is above it are skipped.
    N = points.shape[0]
    known = torch.full((N,), -torch.inf, dtype=v.dtype)  # clearance when last measured
    drift_then = torch.zeros(N, dtype=v.dtype)  # total drift then
    drift = 0.0  # total of each round's largest vertex move
    for _ in range(rounds):
        check = torch.nonzero(known - (drift - drift_then) < clearance).flatten()
        s, face = signed_clearance(points[check], v, triangles, quads, below=clearance)
        known[check], drift_then[check] = s, drift
        bad = s < clearance
        if not bad.any():
            return v
        deficit = torch.zeros(T + Q, dtype=v.dtype).scatter_reduce_(
            0, face[bad], OVERSHOOT * clearance - s[bad], "amax", include_self=True
        )
        normal_v = vertex_normals(v, split02)
        push = torch.zeros(v.shape[0], dtype=v.dtype)
        push.scatter_reduce_(
            0,
            members,
            deficit[rows] / (normal_v[members] * _face_normals(v, triangles, quads)[rows]).sum(-1).clamp_min(0.25),
            "amax",
            include_self=True,
        )
        for attempt in range(6):
            moved = v + push[:, None] * normal_v
            if self_intersections(moved, triangles, quads) <= crossings:
                break
            push = 0.5 * _smooth(push, split02) if attempt % 2 == 0 else _smooth(push, split02)
        else:
            raise CageMakerError(
                "pushing the cage out around the shape would make it intersect itself; make the cage with more "
                "vertices (target_vertices), a larger margin, or a larger seal"
            )
        drift += float((moved - v).norm(dim=1).max())
        v = moved
    s, _ = signed_clearance(points, v, triangles, quads)
    raise CageMakerError(
        f"{int((s < clearance).sum())} of {points.shape[0]} points are still closer than {clearance:.3g} to the cage "
        f"after {rounds} rounds of pushing it outward; make the cage with more vertices (target_vertices) or a larger "
        "margin"
    )
