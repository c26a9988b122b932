"""Mean value coordinates of checked points without an autograd graph: the one place that picks a
kernel (native C, Triton or torch) and runs it over chunks of points. Both the public function
(:mod:`.api`) and the autograd Functions (:mod:`.ops`) import it;
it imports neither. A batch of cages with one topology (3D triangle cages or polygons) is one
native call (CPU) or one Triton launch (CUDA) per chunk of points (:func:`coordinates_batch`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import cast

import torch

from torchcage._core.alloc import empty_output
from torchcage._core.batch import broadcast_batch, check_finite_batch
from torchcage._core.centre import centred_batch
from torchcage._core.common import (
    chunks,
    default_chunk,
    far_unity,
    may_be_far,
    normalise_weights,
    on_cage_tolerance,
    on_cage_tolerances,
    records_graph,
    result_dtype,
    triangle_geometry,
)
from torchcage.backends import Op, select
from torchcage.cage import Cage, _batch_name
from torchcage.errors import PointsError
from torchcage.families.mean_value import native2d as _mvc2d_native
from torchcage.families.mean_value import native3d as _mvc3d_native
from torchcage.families.mean_value.kernel2d import mvc2d_chunk, polygon_data
from torchcage.families.mean_value.kernel3d import TRIANGLE_CAGE_HINT, mvc3d_chunk, triangle_cage_data, triangle_data

__all__ = ["MVC", "coordinates_batch", "coordinates_flat", "native_batch"]

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
    if cage.dim == 3 and lib is not None:
        # (the native kernel's tables alone, as a batch of one: the torch kernel's far-field nodes
        # and thin-face list, 3 ms of a 100 ms call on a 300-face cage, are not needed)
        triangle_geometry(cage, x.dtype, TRIANGLE_CAGE_HINT)
        nf, glue, torch_chunk = cage.triangles.shape[0], _mvc3d_native, mvc3d_chunk
        tol = torch.tensor([on_cage_tolerance(cage)], dtype=torch.float64)
        tables = glue.batch_tables(cage.vertices.to(torch.float64)[None], cage.triangles, tol)
    elif cage.dim == 3:
        data = triangle_cage_data(cage, x.dtype)
        nf, glue, torch_chunk = data.tri.shape[0], _mvc3d_native, mvc3d_chunk
        tables = {}
        if use_triton:
            from torchcage.families.mean_value.triton.mvc3d import triton_tables

            tables = triton_tables(data)
    else:
        data = polygon_data(cage, x.dtype)
        nf, glue, torch_chunk = data.edges.shape[0], _mvc2d_native, mvc2d_chunk
        tol = torch.tensor([on_cage_tolerance(cage)], dtype=torch.float64)  # (a batch of one)
        tables = glue.batch_tables(cage.vertices[None], cage.edges, tol) if lib is not None else {}
        if use_triton:
            from torchcage.families.mean_value.triton.mvc2d import triton_tables

            tables = triton_tables(cage, x.dtype)

    def kernel(c: torch.Tensor, out: torch.Tensor) -> torch.Tensor | None:
        """Writes the chunk's coordinates into ``out``; returns the rows that are not finite
        where the kernel marks them (native: flag 2), else ``None`` (the caller checks)."""
        if lib is not None:
            return glue.native_chunk(c, tables, lib, out) == 2
        if use_triton and cage.dim == 2:
            from torchcage.families.mean_value.triton.mvc2d import mvc2d_triton

            out.copy_(mvc2d_triton(c, tables)[0])
            return None
        if use_triton:
            from torchcage.families.mean_value.triton.mvc3d import mvc3d_triton

            W, flags = mvc3d_triton(c, tables)
            redo = torch.nonzero(flags == 2).flatten()
            if redo.numel():  # thin faces seen from a few widths: the torch kernel's swept form
                cr = c.index_select(0, redo)
                Wr, onr = torch_chunk(cr, data)
                W = W.index_copy(0, redo, normalise_weights(Wr.T, onr, verts, cr))
            out.copy_(W)
            return None
        # With a graph, the weights' 1/h next to a face (an edge in 2D) is divided out before
        # autograd sees it (see mvc3d_chunk); the values are the same once normalised.
        Wc, onc = torch_chunk(c, data, scaled=graph)
        out.copy_(normalise_weights(Wc.T, onc, verts, c))
        return None

    # The native kernel needs no temporaries beyond its output: chunks only pace the progress bar.
    # Pairs per chunk, measured on 2 cores: ~130k (3D torch) and ~250k (2D) amortise the per-op
    # overhead while the temporaries stay in cache.
    target = 1 << 23 if lib is not None or use_triton else (1 << 17 if cage.dim == 3 else 1 << 18)
    size = chunk_size if chunk_size is not None else default_chunk(nf, target)
    out = empty_output(x.shape[0], cage.num_vertices, dtype=x.dtype, device=x.device)
    for sl in chunks(x.shape[0], size, progress, desc="mean value coordinates"):
        bad = kernel(x[sl], out[sl])
        if bad is None:
            bad = ~torch.isfinite(out[sl].sum(dim=1))  # a row sum is finite iff every entry is
        if bool(bad.any()):
            idx = (torch.nonzero(bad).flatten()[:10] + sl.start).tolist()
            raise PointsError(
                f"mean value coordinates are undefined at points {idx} (the total weight vanishes there, "
                "which happens only outside the cage); move these points"
            )
    return out


def coordinates_batch(
    points: torch.Tensor,
    cage: Cage,
    chunk_size: int | None = None,
    dtype: torch.dtype | None = None,
    progress: bool | Callable[[int, int], None] = False,
    backend: str = "auto",
) -> torch.Tensor | None:
    """Mean value coordinates ``(*B', N, V)`` of points ``(N, D)`` or ``(*Bp, N, D)`` for a batch
    of 3D triangle cages or polygons with one topology (batch shape ``B``, ``B'`` the broadcast
    shape) by the native kernel (CPU) or the Triton kernel (CUDA, or ``backend="triton"``):
    one call per chunk of points for every cage at once, the per-cage tables built by one set of
    tensor operations. Element by element the numbers of the public function on ``cage[b]`` (the
    same tables, the same kernel, the same far-field correction).

    ``None`` where neither serves (the torch kernel, an autograd graph, quad cages, another
    device or compute dtype, no native build): the caller then computes element by element
    (``_batch.over_cage_batch``), which also raises the errors of those paths.
    The cages' geometry is checked by the caller (``as_inputs``: ``Cage.check_geometry``, vectorised
    over the batch, naming the element).

    Raises:
        PointsError: points that do not broadcast with the cages, points holding NaN or inf, or
            points where the coordinates are undefined (the total weight vanishes); the batch
            element is named.
    """
    if cage.has_quads or backend == "torch" or records_graph(points, cage.vertices):
        return None
    pts, verts, batch = broadcast_batch(points, cage)
    if not pts.is_floating_point() or pts.device != cage.device:
        return None  # (the per-element path raises the errors that name these)
    compute, out_dtype = result_dtype(pts, cage, dtype, backend)
    if pts.device.type == "cpu" and backend != "triton" and compute != torch.float64:
        return None
    check_finite_batch(pts, batch)
    # relative to each cage's centre, as the single-cage function does (module _centre)
    x, v = centred_batch(pts, verts, compute)
    choice = select(MVC, backend, x, v, graph=False)
    if choice.kind == "triton":
        faces = cage.triangles if cage.dim == 3 else cage.edges
        out = _triton_batch(x, v, faces, chunk_size, progress, batch)
        return out.to(out_dtype).reshape(*batch, x.shape[1], v.shape[1])
    lib = choice.lib
    if lib is None:
        return None
    B, N, V, D = v.shape[0], x.shape[1], v.shape[1], v.shape[2]
    out = native_batch(x, v, cage.triangles if D == 3 else cage.edges, lib, chunk_size, progress, batch)
    if may_be_far(v, x):  # (else far_unity leaves every row as it is: a pass over the points spared)
        out = cast(torch.Tensor, far_unity(out, x.expand(B, N, D), v)[0])
    return out.to(out_dtype).reshape(*batch, N, V)


def native_batch(
    x: torch.Tensor,
    v: torch.Tensor,
    tri: torch.Tensor,
    lib: object,
    chunk_size: int | None = None,
    progress: bool | Callable[[int, int], None] = False,
    batch: torch.Size | None = None,
) -> torch.Tensor:
    """The native kernel's coordinates ``(B, N, V)`` (before the far field's normalisation) of
    centred float64 CPU points ``x`` ``(B or 1, N, D)`` for the centred cages ``v`` ``(B, V, D)``
    with triangles ``tri`` (3D) or directed edges (2D, polygons): one call per chunk of points for
    every cage at once (chunks only pace the progress bar), the per-cage tables built by one set
    of tensor operations.

    Raises:
        PointsError: points where the coordinates are undefined, naming the batch element (of
            ``batch``, the caller's batch shape).
    """
    B, N, V = v.shape[0], x.shape[1], v.shape[1]
    glue = _mvc3d_native if v.shape[2] == 3 else _mvc2d_native
    tables = glue.batch_tables(v, tri, on_cage_tolerances(v))
    size = chunk_size if chunk_size is not None else default_chunk(B * tri.shape[0], 1 << 23)
    out = empty_output(B, N, V, dtype=torch.float64)
    flags = torch.empty((B, N), dtype=torch.uint8)
    for sl in chunks(N, size, progress, desc="mean value coordinates"):
        if sl.start == 0 and sl.stop == N:
            flags = glue.native_chunk(x, tables, lib, out)
        else:
            part = torch.empty((B, sl.stop - sl.start, V), dtype=torch.float64)
            flags[:, sl] = glue.native_chunk(x[:, sl], tables, lib, part)
            out[:, sl] = part
    bad = flags == 2  # (B, N): rows whose sum is not finite (the kernel checks them, sparing a pass here)
    _refuse_undefined(bad, torch.Size([B]) if batch is None else batch)
    return out


def _triton_batch(
    x: torch.Tensor,
    v: torch.Tensor,
    tri: torch.Tensor,
    chunk_size: int | None,
    progress: bool | Callable[[int, int], None],
    batch: torch.Size,
) -> torch.Tensor:
    """:func:`coordinates_batch` by the Triton kernel: centred points ``x`` ``(B or 1, N, D)`` and
    vertices ``v`` ``(B, V, D)`` in the compute dtype (float64, or float32 when asked) on the
    kernel's device, ``tri`` the triangles (3D) or the directed edges (2D) -> ``(B, N, V)``; one
    launch per chunk of points for every cage, the tables of the batch built by one set of tensor
    operations. 3D points that see a thin face from a few widths are redone by the torch kernel (a
    loop over the cages that have such points, as :func:`coordinates_flat` does for one), then the
    far points' sums are restored (``far_unity``). Element by element the numbers of the
    single-cage Triton path.

    Raises:
        PointsError: points where the coordinates are undefined, naming the batch element.
    """
    from torchcage.families.mean_value.triton import mvc2d, mvc3d

    B, N, V, D = v.shape[0], x.shape[1], v.shape[1], v.shape[2]
    tol = on_cage_tolerances(v)  # (B,) float64, as on_cage_tolerance of each centred cage
    tables = (mvc3d.batch_tables if D == 3 else mvc2d.batch_tables)(v, tri, tol)
    launch = mvc3d.mvc3d_triton if D == 3 else mvc2d.mvc2d_triton
    size = chunk_size if chunk_size is not None else default_chunk(B * tri.shape[0], 1 << 23)
    out = torch.empty((B, N, V), dtype=x.dtype, device=x.device)
    flags = torch.empty((B, N), dtype=torch.int32, device=x.device)
    for sl in chunks(N, size, progress, desc="mean value coordinates"):
        Wc, fc = launch(x[:, sl], tables)
        out[:, sl] = Wc
        flags[:, sl] = fc
    redo = flags == 2  # (B, N): a thin face seen from a few widths (3D: the torch kernel's swept form)
    if bool(redo.any()):
        for b in torch.nonzero(redo.any(dim=1)).flatten().tolist():
            idx = torch.nonzero(redo[b]).flatten()
            cr = x[b if x.shape[0] > 1 else 0].index_select(0, idx)
            data = triangle_data(v[b], tri.to(v.device), float(tol[b]))
            Wr, onr = mvc3d_chunk(cr, data)
            out[b, idx] = normalise_weights(Wr.T, onr, v[b], cr)
    bad = ~torch.isfinite(out.sum(dim=-1))  # (B, N): a row sum is finite iff every entry is
    _refuse_undefined(bad, batch)
    if may_be_far(v, x):  # (else far_unity leaves every row as it is)
        out = cast(torch.Tensor, far_unity(out, x.expand(B, N, D), v)[0])
    return out


def _refuse_undefined(bad: torch.Tensor, batch: torch.Size) -> None:
    """Raise for the rows ``bad`` ``(B, N)`` whose coordinates are undefined, naming the first batch
    element that has some.

    Raises:
        PointsError: the points (first ten) and the batch element.
    """
    if bool(bad.any()):
        b = int(torch.nonzero(bad.any(dim=1))[0])
        idx = torch.nonzero(bad[b]).flatten()[:10].tolist()
        raise PointsError(
            f"mean value coordinates are undefined at points {idx}{_batch_name(torch.tensor(b), batch)} (the total "
            "weight vanishes there, which happens only outside the cage); move these points"
        )
