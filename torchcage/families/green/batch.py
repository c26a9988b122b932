"""Green coordinates of a batch of 3D triangle cages with one topology in native calls (CPU): one
call for the values of every cage (chunk by chunk of points) and, when the call records an autograd
graph, one for the first-order backward pass (:class:`.ops.GreenBatchFunction`); or, without a
graph, in Triton launches (CUDA, or ``backend="triton"``): one per chunk of points for every cage."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch._C._functorch import is_functorch_wrapped_tensor

from torchcage._core.batch import broadcast_batch, check_finite_batch
from torchcage._core.common import (
    ON_CAGE_TOLERANCE,
    VERTEX_SNAP,
    chunks,
    default_chunk,
    on_cage_tolerances,
    records_graph,
    result_dtype,
    snap_to_vertices_batch,
    unit_sum,
)
from torchcage.backends import select
from torchcage.cage import Cage
from torchcage.families.green.dispatch import GC, batch_integrals
from torchcage.families.green.exterior import extend_outside
from torchcage.families.green.kernel3d import green3d_coordinates, triangle_green_data
from torchcage.families.green.ops import GreenBatchFunction

__all__ = ["coordinates_batch"]


def coordinates_batch(
    points: torch.Tensor,
    cage: Cage,
    chunk_size: int | None = None,
    dtype: torch.dtype | None = None,
    progress: bool | Callable[[int, int], None] = False,
    backend: str = "auto",
    exterior: str = "extend",
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Green coordinates ``(phi (*B', N, V), psi (*B', N, T))`` of points ``(N, 3)`` or
    ``(*Bp, N, 3)`` for a batch of 3D triangle cages with one topology (batch shape ``B``, ``B'``
    the broadcast shape) by the native kernel (CPU) or, without an autograd graph, the Triton kernel
    (CUDA, or ``backend="triton"``): one call per chunk of points for every cage at once, the
    per-cage tables built by one set of tensor operations, and with an autograd graph (points or
    rest vertices that require grad) one native call for the first-order backward pass. Element by
    element the numbers of the public function on ``cage[b]``: the same centring, vertex snap,
    tables and kernels, the exterior continuation (for the elements that have points outside) and
    the unit sum.

    ``None`` where neither serves (the torch kernel, a torch.func transform, 2D or quad cages, a
    graph off the native kernel, another compute dtype, no native build): the caller then computes element
    by element (``_batch.over_cage_batch``), which also raises the errors of those paths. The cages'
    geometry is checked by the caller (``as_inputs``).

    Raises:
        PointsError: points that do not broadcast with the cages, or points holding NaN or inf; the
            batch element is named.
    """
    if cage.dim != 3 or cage.has_quads or backend == "torch":
        return None
    if is_functorch_wrapped_tensor(points) or is_functorch_wrapped_tensor(cage.vertices):
        return None
    pts, verts, batch = broadcast_batch(points, cage)
    if not pts.is_floating_point() or pts.device != verts.device:
        return None  # (the per-element path raises the errors that name these)
    compute, out_dtype = result_dtype(pts, cage, dtype)
    if compute != torch.float64:
        return None
    graph = records_graph(pts, verts)
    check_finite_batch(pts, batch)
    # Each cage and its points about the middle of its bounding box (a constant, as ``api.centred``).
    v = verts.to(compute)
    with torch.no_grad():
        c = ((v.amax(dim=-2) + v.amin(dim=-2)) / 2)[:, None, :]  # (B, 1, 3)
        scale = (v.amax(dim=-2) - v.amin(dim=-2)).norm(dim=-1)  # (B,): each element's Cage.scale
    x, vc = pts.to(compute) - c, v - c
    if not graph:
        x, vc, v = x.detach(), vc.detach(), v.detach()
    choice = select(GC, backend, x.detach(), vc.detach(), graph=False)
    triton = choice.kind == "triton" and not graph
    if not triton and (choice.kind != "native" or choice.lib is None):
        return None
    N, V, T = x.shape[1], vc.shape[1], cage.triangles.shape[0]
    x = snap_to_vertices_batch(x, vc, VERTEX_SNAP * ON_CAGE_TOLERANCE * scale)
    if triton:
        phi, psi = _triton_integrals(x, vc, cage, chunk_size, progress)
    elif graph:
        phi, psi = GreenBatchFunction.apply(x, vc, cage.triangles, chunk_size or 0, progress, backend)
    else:
        phi, psi = batch_integrals(x, vc, cage.triangles, choice.lib, chunk_size, progress)
    if exterior == "extend":  # the elements with points outside (a winding number below 1/2)
        outside = torch.nonzero((phi.detach().sum(dim=-1) < 0.5).any(dim=1)).flatten().tolist()
        if outside and graph:  # (a graph: the elements joined again, not written in place)
            parts = [(phi[b], psi[b]) for b in range(phi.shape[0])]
            for b in outside:
                parts[b] = extend_outside(x[b], cage._like(vc[b]), phi[b], psi[b])[:2]
            phi, psi = torch.stack([p for p, _ in parts]), torch.stack([s for _, s in parts])
        else:  # (no graph: each element's rows continued in place)
            for b in outside:
                extend_outside(x[b], cage._like(vc[b]), phi[b], psi[b], inplace=True)
    # (the sum made 1 where the caller multiplies by the vertices: about the origin)
    phi = unit_sum(phi, pts.to(compute), v)
    return phi.to(out_dtype).reshape(*batch, N, V), psi.to(out_dtype).reshape(*batch, N, T)


def _triton_integrals(
    x: torch.Tensor,
    v: torch.Tensor,
    cage: Cage,
    chunk_size: int | None,
    progress: bool | Callable[[int, int], None],
) -> tuple[torch.Tensor, torch.Tensor]:
    """The bare Green integrals ``(phi (B, N, V), psi (B, N, T))`` of centred, snapped points ``x``
    ``(B, N, 3)`` for the centred cages ``v`` ``(B, V, 3)`` (the compute dtype, the kernel's device)
    by the Triton kernel: one launch per chunk of points for every cage, the tables of the batch
    built by one set of tensor operations. Points that see a thin face from a few widths are redone
    by the torch kernel's swept form (a loop over the cages that have such points, as the
    single-cage path does for one). Element by element the numbers of the single-cage Triton path."""
    from torchcage.families.green.triton.gc3d import batch_tables, gc3d_triton

    B, N, V, T = v.shape[0], x.shape[1], v.shape[1], cage.triangles.shape[0]
    tables = batch_tables(v, cage.triangles, on_cage_tolerances(v))  # (each centred cage's tolerance)
    size = chunk_size if chunk_size is not None else default_chunk(B * T, 1 << 23)
    phi = torch.empty((B, N, V), dtype=x.dtype, device=x.device)
    psi = torch.empty((B, N, T), dtype=x.dtype, device=x.device)
    flags = torch.empty((B, N), dtype=torch.int32, device=x.device)
    for sl in chunks(N, size, progress, desc="Green coordinates"):
        phi[:, sl], psi[:, sl], flags[:, sl] = gc3d_triton(x[:, sl], tables)
    redo = flags == 2  # (B, N): a thin face seen from a few widths (the torch kernel's swept form)
    if bool(redo.any()):
        for b in torch.nonzero(redo.any(dim=1)).flatten().tolist():
            idx = torch.nonzero(redo[b]).flatten()
            data = triangle_green_data(cage._like(v[b]), x.dtype)
            pr, sr = green3d_coordinates(x[b].index_select(0, idx), data, V)
            phi[b, idx], psi[b, idx] = pr, sr
    return phi, psi
