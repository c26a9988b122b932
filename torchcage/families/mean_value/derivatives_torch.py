"""Mean value coordinates with their gradients and Hessians by autograd of the torch kernel: the
derivatives wherever the native kernel (``derivatives_native``) cannot serve (any device, no C
compiler, ``TORCHCAGE_NATIVE=0``). The torch kernel is finite under autograd everywhere (see
docs/accuracy.md), its far-field and split forms included, so these are the derivatives of the
same coordinates: they agree with the native analytic ones to about 1e-12 (gradients) and 1e-10
(Hessians) relative, next to faces included (both divide the weights' 1/h out there first;
docs/accuracy.md has the figures). On the line of an edge outside it, where the split form is not
differentiable term by term, the derivatives are the mean of those beside the line
(:mod:`.edge_line`; plain autograd there was off by up to 7 absolute)."""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchcage._core.common import chunks, jacobian_rows
from torchcage.cage import Cage
from torchcage.families.mean_value.dispatch import coordinates_flat
from torchcage.families.mean_value.edge_line import edge_line_offsets
from torchcage.families.mean_value.kernel2d import mvc2d_chunk, polygon_data
from torchcage.families.mean_value.kernel3d import mvc3d_chunk, triangle_cage_data

__all__ = ["torch_derivatives"]


def torch_derivatives(
    x: torch.Tensor,
    cage: Cage,
    order: int,
    chunk_size: int | None = None,
    progress: bool | Callable[[int, int], None] = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """As :func:`torchcage.families.mean_value.derivatives.derivatives_flat`, on the points'
    device: float64 ``lam (n, V)``, ``grad (n, V, D)``, ``hess (n, V, D, D)`` (empty for
    ``order=1``) and the ``(n,)`` bool mask of points on the cage (there: the derivatives of the
    interpolant, as the native kernel gives them, Hessians 0)."""
    lam, grad, hess, on = _plain(x, cage, order, chunk_size, progress)
    if cage.dim != 3 or x.shape[0] == 0:
        return lam, grad, hess, on
    off = edge_line_offsets(x.detach().to(torch.float64), cage.vertices.detach().to(torch.float64), cage.triangles)
    if off is None:
        return lam, grad, hess, on
    rows = torch.nonzero(off.abs().sum(dim=1) > 0).flatten()
    xr, o = x.detach().to(torch.float64).index_select(0, rows), off.index_select(0, rows)
    _, gp, hp, _ = _plain(xr + o, cage, order, chunk_size, False)
    _, gm, hm, _ = _plain(xr - o, cage, order, chunk_size, False)
    grad[rows] = 0.5 * (gp + gm)
    if order == 2:
        hess[rows] = 0.5 * (hp + hm)
    return lam, grad, hess, on


def _plain(
    x: torch.Tensor, cage: Cage, order: int, chunk_size: int | None, progress: bool | Callable[[int, int], None]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`torch_derivatives` without the edge-line rule."""
    D, V = cage.dim, cage.num_vertices
    rest = Cage._from_faces(cage.vertices.detach().to(torch.float64), cage.triangles if D == 3 else cage.edges)
    x = x.detach().to(torch.float64)
    n = x.shape[0]
    lam = x.new_empty((n, V))
    grad = x.new_empty((n, V, D))
    hess = x.new_empty((n, V, D, D) if order == 2 else (0,))
    on = torch.zeros(n, dtype=torch.bool, device=x.device)
    if n == 0:
        return lam, grad, hess, on
    size = chunk_size or 1024
    # (the on-cage flags come from one plain pass of the kernel, on data built once)
    data = triangle_cage_data(rest, torch.float64) if D == 3 else polygon_data(rest, torch.float64)
    flags = mvc3d_chunk if D == 3 else mvc2d_chunk
    for sl in chunks(n, size, progress, desc="mean value derivatives"):
        xc = x[sl].clone().requires_grad_()
        with torch.enable_grad():
            lc = coordinates_flat(xc, rest, backend="torch")
            gc = jacobian_rows(lc, xc, create_graph=order == 2)
            if order == 2:
                hess[sl] = torch.stack([torch.stack(jacobian_rows(g, xc, False), dim=-1) for g in gc], dim=2)
        lam[sl], grad[sl] = lc.detach(), torch.stack(gc, dim=-1).detach()
        with torch.no_grad():
            on[sl] = flags(x[sl], data)[1]
    if order == 2 and bool(on.any()):
        hess[on] = 0.0
    return lam, grad, hess, on
