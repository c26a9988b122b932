"""Points outside a cage: which, how many and how far (the outside warnings of every family)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchcage.cage import Cage

__all__ = ["OUTSIDE_TOLERANCE", "Outside", "find_outside"]


#: Points farther outside the cage than this fraction of its size (bounding-box diagonal), beyond
#: the rounding of their coordinates, are reported by :func:`find_outside` (and warn in
#: :func:`deform` and ``torchcage deform``, for every family).
OUTSIDE_TOLERANCE = 1e-6


@dataclass(frozen=True)
class Outside:
    """Points outside a cage (:func:`find_outside`).

    Attributes:
        count: how many points lie outside (over the batch, for a batched cage).
        total: how many points were checked (over the batch).
        max_distance: the largest distance outside, relative to the cage's size (its bounding-box
            diagonal; per batch element); 0 when none lies outside.
        mask: ``(*B, N)`` bool, True for the points outside.
    """

    count: int
    total: int
    max_distance: float
    mask: torch.Tensor

    def message(self, effect: str = "") -> str:
        """One line: the count, how far, and ``effect`` (what the coordinates do with them)."""
        text = (
            f"{self.count:,} of {self.total:,} points lie outside the cage, up to {self.max_distance:.3g} of its "
            "size (bounding-box diagonal) away from it"
        )
        return f"{text}: {effect}" if effect else text


def find_outside(points: torch.Tensor, cage: Cage, tolerance: float = OUTSIDE_TOLERANCE) -> Outside:
    """The points that lie outside a cage by more than ``tolerance`` times its size (plus the
    rounding of the coordinates), and how far: the winding number (3D; quads split along
    ``q0-q2``) or the crossing rule (2D) picks the candidates, their distance to the boundary
    decides. Vectorised and chunked over points (:func:`torchcage.geometry.winding_number`,
    :func:`torchcage.geometry.distance_to_cage`); no graph.

    Args:
        points: ``(N, D)``, or ``(*B, N, D)`` with a batched cage (``(N, D)`` is shared).
        cage: the cage, ``(V, D)`` or batched ``(*B, V, D)``.
        tolerance: the distance outside, relative to the cage's size, that still counts as on it.

    Returns:
        :class:`Outside`: the count, the total, the largest distance relative to the size and
        the ``(*B, N)`` mask.

    Examples:
        >>> import torch, torchcage
        >>> from torchcage.functional.deform import find_outside
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))  # [-1, 1]^3, size 2 sqrt(3)
        >>> r = find_outside(torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0]]), cube)
        >>> r.count, r.total, round(r.max_distance * 12**0.5, 6), r.mask.tolist()
        (1, 3, 2.0, [False, False, True])
    """
    from torchcage.geometry import distance_to_cage, inside_cage

    x = points.detach()
    B = cage.batch_shape
    x = x.expand(*B, *x.shape[-2:]) if B else x
    still = cage.with_vertices(cage.vertices.detach())  # (a predicted cage: no graph, no grad)
    cages = still.unbind() if still.is_batched else [still]
    flat = x.reshape(len(cages), *x.shape[-2:])
    dtype = torch.float64 if x.device.type != "mps" else torch.float32
    masks, count, worst = [], 0, 0.0
    for c, p in zip(cages, flat, strict=True):
        c = c.to(dtype=dtype, device=x.device)
        p = p.to(dtype)
        v = c.vertices
        size = c.scale
        # the rounding of the coordinates as given (float32 points on the cage round to just outside it)
        rounding = 8 * torch.finfo(x.dtype).eps * float(v.abs().max()) if v.numel() else 0.0
        mask = torch.zeros(p.shape[0], dtype=torch.bool, device=x.device)
        if p.shape[0] and size > 0:
            candidates = torch.nonzero(~inside_cage(p, c)).flatten()
            if candidates.numel():
                d = distance_to_cage(p[candidates], c)
                far = d > tolerance * size + rounding
                mask[candidates[far]] = True
                if bool(far.any()):
                    worst = max(worst, float(d[far].max()) / size)
        count += int(mask.sum())
        masks.append(mask)
    mask = torch.stack(masks).reshape(*x.shape[:-1]) if masks else torch.zeros(x.shape[:-1], dtype=torch.bool)
    return Outside(count, int(mask.numel()), worst, mask)
