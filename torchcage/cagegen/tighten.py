"""Tightening: pull the cage vertices that stand farthest from the shape back towards it.

The push-out (:mod:`.enclosure`) moves a face by its worst deficit; on a bent quad that can carry a
corner far out. Here each far vertex, farthest first, is moved back along its normal by a fraction
of its slack (its distance to the shape beyond a few margins), and the move is kept only if the
cage stays valid: every point of the shape at least ``margin`` inside, no new self-intersection,
every quad still valid for QMVC. Halved fractions are tried before giving a vertex up.
"""

from __future__ import annotations

import torch

from torchcage.cagegen.checks import both_triangulations, measured_surfaces, self_intersections, tightness
from torchcage.cagegen.enclosure import vertex_normals
from torchcage.cagegen.quads import MIN_COSINE, corner_cosines
from torchcage.geometry import nearest_triangle, winding_number

__all__ = ["tighten"]


def _still_clear(
    x: torch.Tensor,
    old: torch.Tensor,
    new: torch.Tensor,
    triangles: torch.Tensor,
    quads: torch.Tensor,
    margin: float,
) -> bool:
    """Whether points ``x`` that were at least ``margin`` inside the cage ``old`` still are in ``new``,
    where only the faces ``triangles (T, 3)`` and ``quads (Q, 4)`` (those at the moved vertex)
    changed. A point's distance to the other faces is as before, so it suffices that, on each of
    :func:`.checks.measured_surfaces`, the moved faces keep ``margin`` from every point and no
    point changed sides: the winding number of the surface made of the old faces (reversed) and
    the new ones, which share their boundary, is zero at every point.
    """
    for (p_old, t, _), (p_new, _, slack) in zip(
        measured_surfaces(old, triangles, quads), measured_surfaces(new, triangles, quads), strict=True
    ):
        if float(nearest_triangle(x, p_new, t, slack=slack)[0].min()) < margin:
            return False
        swept = torch.cat([t.flip(1), t + p_old.shape[0]])
        if not bool((winding_number(x, torch.cat([p_old, p_new]), swept).abs() < 0.5).all()):
            return False
    return True


def _vertex_distances(v: torch.Tensor, points: torch.Tensor, mesh_faces: torch.Tensor | None) -> torch.Tensor:
    """``(V,)`` distances from the cage vertices to the shape (its triangles, or its points)."""
    none = torch.zeros((0, 3), dtype=torch.long)
    return tightness(v, none, none.new_zeros((0, 4)), points, mesh_faces)


#: Vertices farther from the shape than this many times the median vertex's distance, and than
#: ``FAR_DIAGONAL`` of the shape's bounding-box diagonal, are pulled: at most ``MOST`` of them per
#: round, the farthest first.
FAR = 2.0
FAR_DIAGONAL = 0.05
MOST = 8
#: Fractions of the slack tried, in turn.
FRACTIONS = (0.75, 0.5, 0.25)


def tighten(
    vertices: torch.Tensor,
    triangles: torch.Tensor,
    quads: torch.Tensor,
    points: torch.Tensor,
    mesh_faces: torch.Tensor | None,
    margin: float,
    *,
    rounds: int = 3,
) -> torch.Tensor:
    """Move far cage vertices towards the shape while the cage stays enclosing and valid.

    Args:
        vertices: ``(V, 3)`` float64 cage vertices (not modified).
        triangles: ``(T, 3)``, quads ``(Q, 4)``: the cage's faces, outward.
        points: ``(N, 3)`` the shape's vertices; ``mesh_faces`` ``(F, 3)`` its triangles or ``None``.
        margin: the least clearance every point keeps.
        rounds: passes over the far vertices.

    Returns:
        the moved vertices ``(V, 3)``.

    Examples:
        >>> import torch, torchcage
        >>> from torchcage.cagegen import signed_clearance
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))  # [-1, 1]^3
        >>> v = cube.vertices.clone()
        >>> v[0] *= 3  # one corner far out
        >>> pts = torch.rand(500, 3, dtype=torch.float64) * 1.6 - 0.8
        >>> w = tighten(v, cube.triangles, cube.quads, pts, None, 0.05)
        >>> bool(w[0].norm() < v[0].norm()), bool(signed_clearance(pts, w, cube.triangles, cube.quads)[0].min() >= 0.05)
        (True, True)
    """
    v = vertices.detach().to(torch.float64).clone()
    split02, split13 = both_triangulations(triangles, quads)
    both = torch.cat([split02, split13[triangles.shape[0] :]])  # every triangle of either triangulation
    crossings = self_intersections(v, triangles, quads)
    diagonal = float((points.amax(0) - points.amin(0)).norm())
    d = _vertex_distances(v, points, mesh_faces)
    for _ in range(rounds):
        far = torch.nonzero((d > FAR * d.median()) & (d > FAR_DIAGONAL * diagonal)).flatten()
        if not far.numel():
            break
        far = far[torch.argsort(d[far], descending=True)][:MOST]
        moved_any = False
        normal = vertex_normals(v, split02)
        for i in far.tolist():
            slack = float(d[i]) - 4 * margin
            if slack <= 0:
                continue
            own = quads[(quads == i).any(dim=1)]  # the faces at i: the only ones that move
            own_tri = triangles[(triangles == i).any(dim=1)]
            for fraction in FRACTIONS:
                trial = v.clone()
                trial[i] = v[i] - fraction * slack * normal[i]
                if own.numel() and bool((corner_cosines(trial[own]) <= 0.2 * MIN_COSINE).any()):
                    continue
                # only the faces at vertex i move, within the box of their old and new corners: points
                # farther than the margin from that box keep their distance and side
                corners = torch.cat([v[both[(both == i).any(dim=1)].flatten()], trial[i : i + 1]])
                lo, hi = corners.amin(0) - margin, corners.amax(0) + margin
                near = ((points >= lo) & (points <= hi)).all(dim=1)
                if near.any() and not _still_clear(points[near], v, trial, own_tri, own, margin):
                    continue
                if self_intersections(trial, triangles, quads) > crossings:
                    continue
                v, moved_any = trial, True
                d[i] = _vertex_distances(v[i : i + 1], points, mesh_faces)[0]
                break
        if not moved_any:
            break
    return v
