"""Green coordinates of checked points without an autograd Function: the one place that picks a
kernel (native C, Triton or torch) and runs it over chunks of points. Both the public function
(:mod:`.green`) and the autograd Function (:mod:`.ops`) import it."""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchcage._core.alloc import empty_output
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
from torchcage.backends import Op, select
from torchcage.cage import Cage
from torchcage.families.green.exterior import extend_outside
from torchcage.families.green.kernel2d import green2d_coordinates
from torchcage.families.green.kernel3d import TriangleGreenData, green3d_coordinates, triangle_green_data
from torchcage.families.green.native3d import batch_chunk, batch_tables, native_chunk, native_tables

__all__ = ["coordinates_batch", "green_flat"]


#: The kernels of Green coordinates (:func:`torchcage.backends.select` chooses).
GC = Op("Green coordinates", triton=True)


def green_flat(
    x: torch.Tensor,
    cage: Cage,
    chunk_size: int | None = None,
    progress: bool | Callable[[int, int], None] = False,
    backend: str = "auto",
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(phi (N, V), psi (N, T))`` of checked points ``x`` ``(N, D)`` in their dtype, chunk by chunk
    (the torch kernel records autograd when its inputs require grad; the native one never does)."""
    compute = x.dtype
    graph = records_graph(x, cage.vertices)
    choice = select(GC, backend, x, cage.vertices, graph=graph)
    use_triton, lib = choice.kind == "triton", choice.lib
    if cage.dim == 3:
        data = triangle_green_data(cage, compute)
        T = data.tri.shape[0]
        tables = native_tables(data, cage.vertices.to(compute)) if lib is not None else {}
        if use_triton:
            from torchcage.families.green.triton.gc3d import triton_tables

            tables = triton_tables(data, cage.vertices.to(compute))

        def kernel(c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            if use_triton:
                return _triton_chunk(c, tables, data, cage.num_vertices)
            return green3d_coordinates(c, data, cage.num_vertices)
    else:
        T = cage.edges.shape[0]
        poly = cage.to(compute)

        def kernel(c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            return green2d_coordinates(c, poly)

    # The native kernel needs no temporaries beyond its outputs: chunks only pace the progress bar.
    target = 1 << 23 if lib is not None or use_triton else 1 << 17
    size = chunk_size if chunk_size is not None else default_chunk(T, target)
    phi = empty_output(x.shape[0], cage.num_vertices, dtype=compute, device=x.device)
    psi = empty_output(x.shape[0], T, dtype=compute, device=x.device)
    for sl in chunks(x.shape[0], size, progress, desc="Green coordinates"):
        if lib is not None:  # writes straight into the row blocks (contiguous): no copies
            native_chunk(x[sl], tables, lib, phi[sl], psi[sl])
        else:
            phi[sl], psi[sl] = kernel(x[sl])
    return phi, psi


def _triton_chunk(
    c: torch.Tensor, tables: dict[str, object], data: TriangleGreenData, num_vertices: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The Triton kernel on a chunk, the points it flags (thin faces seen from a few widths) redone
    by the torch kernel's swept form."""
    from torchcage.families.green.triton.gc3d import gc3d_triton

    phi, psi, flags = gc3d_triton(c, tables)
    redo = torch.nonzero(flags == 2).flatten()
    if redo.numel():
        pr, sr = green3d_coordinates(c.index_select(0, redo), data, num_vertices)
        phi, psi = phi.index_copy(0, redo, pr), psi.index_copy(0, redo, sr)
    return phi, psi


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
    the broadcast shape) by the native kernel: one call per chunk of points for every cage at once,
    the per-cage tables built by one set of tensor operations. Element by element the numbers of
    the public function on ``cage[b]``: the same centring, vertex snap, tables and kernel, the
    exterior continuation (for the elements that have points outside) and the unit sum.

    ``None`` where the native kernel does not serve (another backend, an autograd graph, 2D or quad
    cages, another device or compute dtype, no native build): the caller then computes element by
    element (``_batch.over_cage_batch``), which also raises the errors of those paths. The cages'
    geometry is checked by the caller (``as_inputs``).

    Raises:
        PointsError: points that do not broadcast with the cages, or points holding NaN or inf; the
            batch element is named.
    """
    if cage.dim != 3 or cage.has_quads or backend not in ("auto", "native") or records_graph(points, cage.vertices):
        return None
    pts, verts, batch = broadcast_batch(points, cage)
    if not pts.is_floating_point() or pts.device.type != "cpu" or verts.device.type != "cpu":
        return None
    compute, out_dtype = result_dtype(pts, cage, dtype)
    if compute != torch.float64:
        return None
    check_finite_batch(pts, batch)
    # Each cage and its points about the middle of its bounding box (as ``api.centred``).
    v = verts.detach().to(compute)
    c = ((v.amax(dim=-2) + v.amin(dim=-2)) / 2)[:, None, :]  # (B, 1, 3)
    x, vc = pts.detach().to(compute) - c, v - c
    choice = select(GC, backend, x, vc, graph=False)
    if choice.kind != "native" or choice.lib is None:
        return None
    B, N, V, T = vc.shape[0], x.shape[1], vc.shape[1], cage.triangles.shape[0]
    scale = (v.amax(dim=-2) - v.amin(dim=-2)).norm(dim=-1)  # (B,): each element's Cage.scale
    x = snap_to_vertices_batch(x, vc, VERTEX_SNAP * ON_CAGE_TOLERANCE * scale)
    tables = batch_tables(vc, cage.triangles, on_cage_tolerances(vc))
    # The kernel needs no temporaries beyond its outputs: chunks only pace the progress bar.
    size = chunk_size if chunk_size is not None else default_chunk(B * T, 1 << 23)
    phi = empty_output(B, N, V, dtype=compute)
    psi = empty_output(B, N, T, dtype=compute)
    for sl in chunks(N, size, progress, desc="Green coordinates"):
        if sl.start == 0 and sl.stop == N:
            batch_chunk(x, tables, choice.lib, phi, psi)
        else:
            part_phi, part_psi = (
                torch.empty((B, sl.stop - sl.start, V), dtype=compute),
                torch.empty((B, sl.stop - sl.start, T), dtype=compute),
            )
            batch_chunk(x[:, sl], tables, choice.lib, part_phi, part_psi)
            phi[:, sl], psi[:, sl] = part_phi, part_psi
    if exterior == "extend":  # the elements with points outside (a winding number below 1/2)
        for b in torch.nonzero((phi.sum(dim=-1) < 0.5).any(dim=1)).flatten().tolist():
            phi[b], psi[b], _ = extend_outside(x[b], cage._like(vc[b]), phi[b], psi[b])
    # (the sum made 1 where the caller multiplies by the vertices: about the origin)
    phi = unit_sum(phi, pts.to(compute), v)
    return phi.to(out_dtype).reshape(*batch, N, V), psi.to(out_dtype).reshape(*batch, N, T)
