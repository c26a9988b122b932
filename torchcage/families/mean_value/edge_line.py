"""Points on the line of a cage edge outside the edge: where the torch kernel's split form is not
differentiable term by term (each adjacent face's weight has a ``|h|`` kink that cancels only in
the sum), the derivatives are taken as the mean of those at two points beside the line. Used by the
autograd fallbacks (``ops``) and by ``mean_value_derivatives``' torch path
(``derivatives_torch``)."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["EDGE_LINE_BAND", "EDGE_LINE_STEP", "edge_line_offsets"]

#: Points nearer an edge's line (outside the edge) than this fraction of their distance to the
#: nearest vertex take the rest vertices' derivative as the mean of those at two points
#: ``EDGE_LINE_STEP`` of that distance to either side of the line.
EDGE_LINE_BAND = 1e-5
EDGE_LINE_STEP = 1e-4


def edge_line_offsets(points: Tensor, vertices: Tensor, faces: Tensor) -> Tensor | None:
    """``(m, 3)`` offsets off the nearest edge line for the points within ``EDGE_LINE_BAND`` of an
    edge's line outside the edge (zero rows elsewhere), or None when there are none.

    On the line of an edge (and so on both adjacent faces' planes) each face's weight in the
    torch kernel's split form has a ``|h|`` kink that cancels only in the sum: autograd of the
    kernel gave the edge's vertices a derivative off by a factor 7 there, and nearby it loses
    ``eps / distance``. The coordinates are smooth there, so the symmetric mean of the
    derivatives at ``x +- e`` (``e`` perpendicular to the edge, ``EDGE_LINE_STEP`` of the distance
    to the nearest vertex or to the cage, whichever is smaller) is their derivative to
    ``(EDGE_LINE_STEP)^2``."""
    x, P = points.detach(), vertices.detach()
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).sort(dim=1).values.unique(dim=0)
    a, b = P[e[:, 0]], P[e[:, 1]]  # (E, 3)
    u = b - a
    ell2 = (u * u).sum(-1)
    L = torch.cdist(x, P).min(dim=1).values  # distance to the nearest vertex
    k = torch.full((x.shape[0],), -1, dtype=torch.long, device=x.device)  # the nearest such line
    rk = torch.full((x.shape[0],), torch.inf, dtype=x.dtype, device=x.device)  # its distance
    step = max(1, (1 << 20) // max(1, e.shape[0]))  # (rows per chunk: memory bounded by 2^20 pairs)
    for s in range(0, x.shape[0], step):
        rel = x[s : s + step, None, :] - a[None]  # (rows, E, 3)
        t = (rel * u).sum(-1) / ell2  # parameter of the foot on the edge
        r = (rel - t[..., None] * u).norm(dim=-1)  # distance to the edge's line
        Ls = L[s : s + step, None]
        near = (r < EDGE_LINE_BAND * Ls) & ((t < 0) | (t > 1)) & (Ls > 0)
        rn, kn = torch.where(near, r, torch.inf).min(dim=1)
        k[s : s + step] = torch.where(near.any(dim=1), kn, -1)
        rk[s : s + step] = rn
    on_line = k >= 0
    if not bool(on_line.any()):
        return None
    # The reach is also bounded by the distance to the cage: a point near an edge's line can be
    # nearer another face, where the derivatives vary on the scale of that distance (a step of 1e-4
    # of the vertex distance, across a face 1e-6 away, left the point's gradient off by 1e-8). Such
    # points keep the plain derivatives unless they are within the band of that smaller reach.
    from torchcage.cage import Cage
    from torchcage.geometry import distance_to_cage

    rows = torch.nonzero(on_line).flatten()
    reach = L.clone()
    reach[rows] = torch.minimum(L[rows], distance_to_cage(x[rows], Cage._from_faces(P, faces)))
    on_line = on_line & (rk < EDGE_LINE_BAND * reach)
    if not bool(on_line.any()):
        return None
    k = k.clamp_min(0)
    dirn = torch.nn.functional.normalize(u[k], dim=-1)
    generic = x.new_tensor([0.5773, -0.6711, 0.4654])
    side = torch.linalg.cross(dirn, generic.expand_as(dirn), dim=-1)
    side = torch.where(
        (side.norm(dim=-1, keepdim=True) > 0.1),
        side,
        torch.linalg.cross(dirn, x.new_tensor([1.0, 0.0, 0.0]).expand_as(dirn), dim=-1),
    )
    side = torch.nn.functional.normalize(side, dim=-1)
    return torch.where(on_line[:, None], EDGE_LINE_STEP * reach[:, None] * side, 0.0)
