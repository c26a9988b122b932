"""Green coordinates of checked points without an autograd Function: the one place that picks a
kernel (native C, Triton or torch) and runs it over chunks of points. Both the public function
(:mod:`.green`) and the autograd Function (:mod:`.ops`) import it."""

from __future__ import annotations

import ctypes
from collections.abc import Callable

import torch

from torchcage._core.alloc import empty_output
from torchcage._core.common import (
    chunks,
    default_chunk,
    on_cage_tolerances,
    records_graph,
)
from torchcage.backends import Op, select
from torchcage.cage import Cage
from torchcage.families.green.kernel2d import green2d_coordinates
from torchcage.families.green.kernel3d import TriangleGreenData, green3d_coordinates, triangle_green_data
from torchcage.families.green.native3d import batch_chunk, batch_tables, native_chunk, native_tables

__all__ = ["batch_integrals", "green_flat"]


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


def batch_integrals(
    x: torch.Tensor,
    vertices: torch.Tensor,
    faces: torch.Tensor,
    lib: ctypes.CDLL,
    chunk_size: int | None = None,
    progress: bool | Callable[[int, int], None] = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The bare Green integrals ``(phi (B, N, V), psi (B, N, T))`` of points ``x`` ``(B, N, 3)``
    (snapped) for cages ``vertices`` ``(B, V, 3)`` (both centred, float64 CPU, no graph) by the
    native kernel: the tables built once for the batch, one call per chunk of points for every cage
    at once."""
    B, N, V, T = vertices.shape[0], x.shape[1], vertices.shape[1], faces.shape[0]
    tables = batch_tables(vertices, faces, on_cage_tolerances(vertices))
    # The kernel needs no temporaries beyond its outputs: chunks only pace the progress bar.
    size = chunk_size if chunk_size is not None else default_chunk(B * T, 1 << 23)
    phi = empty_output(B, N, V, dtype=x.dtype)
    psi = empty_output(B, N, T, dtype=x.dtype)
    for sl in chunks(N, size, progress, desc="Green coordinates"):
        if sl.start == 0 and sl.stop == N:
            batch_chunk(x, tables, lib, phi, psi)
        else:
            part_phi, part_psi = (
                torch.empty((B, sl.stop - sl.start, V), dtype=x.dtype),
                torch.empty((B, sl.stop - sl.start, T), dtype=x.dtype),
            )
            batch_chunk(x[:, sl], tables, lib, part_phi, part_psi)
            phi[:, sl], psi[:, sl] = part_phi, part_psi
    return phi, psi
