"""Green coordinates of a batch of polygons with one topology by the torch kernel vectorised over
the batch (:func:`.kernel2d.green2d_batch`): one set of tensor operations per chunk of points for
every polygon, on any device, instead of one call per polygon."""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchcage._core.alloc import empty_output
from torchcage._core.batch import broadcast_batch, check_finite_batch
from torchcage._core.common import chunks, default_chunk, on_cage_tolerances, records_graph, result_dtype, unit_sum
from torchcage.backends import select
from torchcage.cage import Cage
from torchcage.families.green.dispatch import GC
from torchcage.families.green.exterior import extend_outside
from torchcage.families.green.kernel2d import green2d_batch

__all__ = ["polygons_batch"]

#: Point–edge pairs per chunk (as the single polygon's torch kernel: ``dispatch.green_flat``).
_PAIRS = 1 << 17


def polygons_batch(
    points: torch.Tensor,
    cage: Cage,
    chunk_size: int | None = None,
    dtype: torch.dtype | None = None,
    progress: bool | Callable[[int, int], None] = False,
    backend: str = "auto",
    exterior: str = "extend",
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Green coordinates ``(phi (*B', N, V), psi (*B', N, E))`` of points ``(N, 2)`` or
    ``(*Bp, N, 2)`` for a batch of polygons with one topology (batch shape ``B``, ``B'`` the
    broadcast shape), without an autograd graph: element by element the numbers of the public
    function on ``cage[b]`` to rounding (the same centring, kernel, exterior continuation for the
    elements that have points outside, and unit sum; a vectorised ``log`` may round apart).

    ``None`` where this does not serve (3D cages, an autograd graph or a ``torch.func`` transform,
    points of another device or not floating point, a backend other than the torch kernel): the
    caller then computes element by element, which also raises the errors of those paths.

    Raises:
        PointsError: points that do not broadcast with the cages, or points holding NaN or inf; the
            batch element is named.

    Examples:
        >>> import torch, torchcage
        >>> square = torch.tensor([[0.0, 0], [1, 0], [1, 1], [0, 1]], dtype=torch.float64)
        >>> cage = torchcage.Cage(torch.stack([square, 2 * square]), torch.tensor([[0, 1], [1, 2], [2, 3], [3, 0]]))
        >>> phi, psi = polygons_batch(torch.tensor([[0.5, 0.25]], dtype=torch.float64), cage)
        >>> phi.shape, torch.allclose(phi.sum(-1), torch.ones(2, 1, dtype=torch.float64))
        (torch.Size([2, 1, 4]), True)
    """
    if cage.dim != 2 or records_graph(points, cage.vertices):
        return None
    pts, verts, batch = broadcast_batch(points, cage)
    if not pts.is_floating_point() or pts.device != verts.device:
        return None
    compute, out_dtype = result_dtype(pts, cage, dtype)
    # each polygon and its points about the middle of its bounding box (as ``api.centred``)
    v = verts.detach().to(compute)
    c = ((v.amax(dim=-2) + v.amin(dim=-2)) / 2)[:, None, :]  # (B, 1, 2)
    x, vc = pts.detach().to(compute) - c, v - c
    if select(GC, backend, x[:, :0], vc, graph=False).kind != "torch":
        return None
    check_finite_batch(pts, batch)
    B, N, V, E = vc.shape[0], x.shape[1], vc.shape[1], cage.edges.shape[0]
    # (B,): each centred polygon's, as the single call's (computed on the CPU for MPS: no float64 there)
    tol = on_cage_tolerances(vc if vc.device.type != "mps" else vc.cpu()).to(x.device, compute)
    edges = cage.edges.to(x.device)
    size = chunk_size if chunk_size is not None else default_chunk(B * E, _PAIRS)
    phi = empty_output(B, N, V, dtype=compute, device=x.device)
    psi = empty_output(B, N, E, dtype=compute, device=x.device)
    for sl in chunks(N, size, progress, desc="Green coordinates"):
        phi[:, sl], psi[:, sl] = green2d_batch(x[:, sl], vc, edges, tol)
    if exterior == "extend":  # the elements with points outside (a winding number below 1/2)
        for b in torch.nonzero((phi.sum(dim=-1) < 0.5).any(dim=1)).flatten().tolist():
            extend_outside(x[b], cage._like(vc[b]), phi[b], psi[b], inplace=True)
    # (the sum made 1 where the caller multiplies by the vertices: about the origin)
    phi = unit_sum(phi, pts.detach().to(compute), v)
    return phi.to(out_dtype).reshape(*batch, N, V), psi.to(out_dtype).reshape(*batch, N, E)
