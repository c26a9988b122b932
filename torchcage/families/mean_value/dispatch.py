"""Mean value coordinates of checked points without an autograd graph: the one place that picks a
kernel (native C, Triton or torch) and runs it over chunks of points. Both the public function
(:mod:`.mean_value`) and the autograd Functions (:mod:`torchcage.families.mean_value.ops`) import it;
it imports neither."""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchcage._core.common import chunks, default_chunk, normalise_weights, records_graph
from torchcage.backends import Op, select
from torchcage.cage import Cage
from torchcage.errors import PointsError
from torchcage.families.mean_value import native2d as _mvc2d_native
from torchcage.families.mean_value import native3d as _mvc3d_native
from torchcage.families.mean_value.kernel2d import mvc2d_chunk, polygon_data
from torchcage.families.mean_value.kernel3d import mvc3d_chunk, triangle_cage_data

__all__ = ["MVC", "coordinates_flat"]

#: The kernels of mean value coordinates (:func:`torchcage.backends.select` chooses).
MVC = Op("mean value coordinates", native_dims=(2, 3), triton=True, triton_dims=(2, 3))


def coordinates_flat(
    x: torch.Tensor,
    cage: Cage,
    chunk_size: int | None = None,
    progress: bool | Callable[[int, int], None] = False,
    backend: str = "auto",
) -> torch.Tensor:
    """Mean value coordinates ``(N, V)`` of checked points ``x`` ``(N, D)`` in their dtype (the
    torch kernel records autograd when its inputs require grad; the native one never does).

    Raises:
        PointsError: points where the coordinates are undefined (the total weight vanishes).
    """
    graph = records_graph(x, cage.vertices)
    choice = select(MVC, backend, x, cage.vertices, graph=graph)
    use_triton, lib = choice.kind == "triton", choice.lib
    verts = cage.vertices.to(x.dtype)
    if cage.dim == 3:
        data = triangle_cage_data(cage, x.dtype)
        nf, glue, torch_chunk = data.tri.shape[0], _mvc3d_native, mvc3d_chunk
        tables = glue.native_tables(data) if lib is not None else {}
        if use_triton:
            from torchcage.families.mean_value.triton.mvc3d import triton_tables

            tables = triton_tables(data)
    else:
        data = polygon_data(cage, x.dtype)
        nf, glue, torch_chunk = data.edges.shape[0], _mvc2d_native, mvc2d_chunk
        tables = glue.native_tables(cage) if lib is not None else {}
        if use_triton:
            from torchcage.families.mean_value.triton.mvc2d import triton_tables

            tables = triton_tables(cage, x.dtype)

    def kernel(c: torch.Tensor, out: torch.Tensor) -> None:
        if lib is not None:
            glue.native_chunk(c, tables, lib, out)
            return
        if use_triton and cage.dim == 2:
            from torchcage.families.mean_value.triton.mvc2d import mvc2d_triton

            out.copy_(mvc2d_triton(c, tables)[0])
            return
        if use_triton:
            from torchcage.families.mean_value.triton.mvc3d import mvc3d_triton

            W, flags = mvc3d_triton(c, tables)
            redo = torch.nonzero(flags == 2).flatten()
            if redo.numel():  # thin faces seen from a few widths: the torch kernel's swept form
                cr = c.index_select(0, redo)
                Wr, onr = torch_chunk(cr, data)
                W = W.index_copy(0, redo, normalise_weights(Wr.T, onr, verts, cr))
            out.copy_(W)
            return
        # With a graph, the weights' 1/h next to a face (an edge in 2D) is divided out before
        # autograd sees it (see mvc3d_chunk); the values are the same once normalised.
        Wc, onc = torch_chunk(c, data, scaled=graph)
        out.copy_(normalise_weights(Wc.T, onc, verts, c))

    # The native kernel needs no temporaries beyond its output: chunks only pace the progress bar.
    # Pairs per chunk, measured on 2 cores: ~130k (3D torch) and ~250k (2D) amortise the per-op
    # overhead while the temporaries stay in cache.
    target = 1 << 23 if lib is not None or use_triton else (1 << 17 if cage.dim == 3 else 1 << 18)
    size = chunk_size if chunk_size is not None else default_chunk(nf, target)
    out = torch.empty((x.shape[0], cage.num_vertices), dtype=x.dtype, device=x.device)
    for sl in chunks(x.shape[0], size, progress, desc="mean value coordinates"):
        kernel(x[sl], out[sl])
        bad = ~torch.isfinite(out[sl].sum(dim=1))  # a row sum is finite iff every entry is
        if bool(bad.any()):
            idx = (torch.nonzero(bad).flatten()[:10] + sl.start).tolist()
            raise PointsError(
                f"mean value coordinates are undefined at points {idx} (the total weight vanishes there, "
                "which happens only outside the cage); move these points"
            )
    return out
