"""Batched rest cages in the functional API: one call per batch element, results stacked (where no
batched kernel serves: mean value, Green, quad mean value and quad Green coordinates and the
mean value derivatives on the native kernels take a batch in one call).

A batched cage ``(*B, V, D)`` takes points ``(*Bp, N, D)`` whose batch shape broadcasts with
``B`` (``(N, D)``: one point set shared by every cage) and gives ``(*B', N, ...)`` with ``B'`` the
broadcast shape. The work inside each element is vectorised and chunked over points as for one
cage; the loop runs over batch elements only (a Python loop per cage, never per point).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch._C._functorch import is_functorch_wrapped_tensor

from torchcage.cage import Cage, _batch_name
from torchcage.errors import PointsError

__all__ = ["broadcast_batch", "check_finite_batch", "native_batch_inputs", "over_cage_batch"]


def over_cage_batch(fn: Callable[..., Any], points: torch.Tensor, cage: Cage, **kwargs: Any) -> Any:
    """``fn(points_b, cage_b, **kwargs)`` for every element ``b`` of the broadcast batch, stacked.

    Args:
        fn: an unbatched functional (points ``(N, D)``, one cage) returning a tensor or a tuple of
            tensors (``None`` entries stay ``None``), each with the points on its first axis.
        points: ``(N, D)`` or ``(*Bp, N, D)``.
        cage: a batched cage, batch shape ``B``.

    Returns:
        ``fn``'s outputs with the broadcast batch shape in front: ``(*B', N, ...)``.

    Raises:
        PointsError: points without a point axis, or a batch shape that does not broadcast.
    """
    pts, verts, batch = broadcast_batch(points, cage)
    pts = pts.expand(verts.shape[0], *pts.shape[1:])
    results = [fn(pts[b], cage._like(verts[b]), **kwargs) for b in range(verts.shape[0])]
    if isinstance(results[0], tuple):
        return tuple(_stack([r[k] for r in results], batch) for k in range(len(results[0])))
    return _stack(results, batch)


def native_batch_inputs(
    points: torch.Tensor, cage: Cage, backend: str, quads: bool = False, planar: bool = False
) -> tuple[torch.Tensor, torch.Tensor, torch.Size] | None:
    """:func:`broadcast_batch` of a call that a batched native kernel may serve: a 3D cage (with
    quads only where ``quads``) or a polygon (only where ``planar``), ``backend`` ``"auto"`` or
    ``"native"``, floating-point points and vertices on the CPU, no ``torch.func`` transform.
    ``None`` otherwise: the caller then loops over the cages, whose path raises the errors that
    name what does not serve.

    Raises:
        PointsError: points without a point axis, or a batch shape that does not broadcast.
    """
    if cage.dim != 3 and not (planar and cage.dim == 2):
        return None
    if (cage.has_quads and not quads) or backend not in ("auto", "native"):
        return None
    if is_functorch_wrapped_tensor(points) or is_functorch_wrapped_tensor(cage.vertices):
        return None
    pts, verts, batch = broadcast_batch(points, cage)
    if not pts.is_floating_point() or pts.device.type != "cpu" or verts.device.type != "cpu":
        return None
    return pts, verts, batch


def broadcast_batch(points: Any, cage: Cage) -> tuple[torch.Tensor, torch.Tensor, torch.Size]:
    """The points and a batched cage's vertices over their broadcast batch shape ``B'``, flattened.

    Args:
        points: ``(N, D)`` or ``(*Bp, N, D)``.
        cage: a batched cage, batch shape ``B``.

    Returns:
        ``(points (1, N, D)`` when one set is shared by every cage, else ``(prod B', N, D)``;
        ``vertices (prod B', V, D)``; ``B')``. Views where no copy is needed.

    Raises:
        PointsError: points without a point axis, or a batch shape that does not broadcast.
    """
    if not isinstance(points, torch.Tensor):
        points = torch.as_tensor(points, dtype=torch.float64)
    if points.ndim < 2 or points.shape[-1] != cage.dim:
        raise PointsError(
            f"with a batch of cages (batch shape {tuple(cage.batch_shape)}) points must have shape "
            f"(*B, N, {cage.dim}) or (N, {cage.dim}), got {tuple(points.shape)}"
        )
    try:
        batch = torch.broadcast_shapes(points.shape[:-2], cage.batch_shape)
    except RuntimeError as err:
        raise PointsError(
            f"points of batch shape {tuple(points.shape[:-2])} do not broadcast with the cages' batch shape "
            f"{tuple(cage.batch_shape)}; give one point set per cage (*B, N, {cage.dim}) or one shared (N, {cage.dim})"
        ) from err
    if batch.numel() == 0:
        raise PointsError(f"the batch of cages and points is empty (batch shape {tuple(batch)})")
    N, V, D = points.shape[-2], cage.num_vertices, cage.dim
    shared = points.shape[:-2].numel() == 1
    nb = batch.numel()  # (not -1 in reshape: ambiguous for N = 0 points)
    pts = points.reshape(1, N, D) if shared else points.expand(*batch, N, D).reshape(nb, N, D)
    verts = cage.vertices.expand(*batch, V, D).reshape(nb, V, D)
    return pts, verts, batch


def check_finite_batch(pts: torch.Tensor, batch: torch.Size) -> None:
    """Raise for points ``pts`` ``(B or 1, N, D)`` (from :func:`broadcast_batch`) holding NaN or inf,
    naming the first ten and the batch element (a NaN or an inf anywhere shows in the points' box:
    one pass, and the full test only then).

    Raises:
        PointsError: points that are not finite.
    """
    pts = pts.detach()  # (values only: no graph, and no forward-mode tangent, which aminmax lacks in torch 2.5)
    if pts.shape[-2] and not bool(torch.isfinite(torch.stack(torch.aminmax(pts, dim=-2))).all()):
        bad = ~torch.isfinite(pts).all(dim=-1)  # (1 or B, N)
        b = int(torch.nonzero(bad.any(dim=1))[0])
        idx = torch.nonzero(bad[b]).flatten()[:10].tolist()
        where = _batch_name(torch.tensor(b), batch) if pts.shape[0] > 1 else ""
        raise PointsError(f"points contain NaN or inf (flattened indices {idx}{where}); remove or fix them")


def _stack(parts: list[torch.Tensor | None], batch: torch.Size) -> torch.Tensor | None:
    if parts[0] is None:
        return None
    out = torch.stack(parts)
    return out.reshape(*batch, *out.shape[1:])
