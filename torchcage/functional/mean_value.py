r"""Mean value coordinates for closed triangle cages (3D) and closed polygons (2D): the public
function. The kernels live beside it: ``_mvc3d`` (torch, 3D: the formulation and its numerical
care are described there), ``_mvc3d_native`` (the native CPU kernel's glue), ``_mvc2d`` (2D).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from .. import _native
from ..cage import Cage
from ..errors import PointsError
from ._common import check_points, chunks, default_chunk, normalise_weights, records_graph, result_dtype
from ._mvc2d import mvc2d_chunk, polygon_data
from ._mvc3d import mvc3d_chunk, triangle_cage_data
from ._mvc3d_native import native_chunk, native_tables

__all__ = ["mean_value_coordinates"]


def _coordinates_flat(
    x: torch.Tensor,
    cage: Cage,
    chunk_size: int | None,
    progress: bool | Callable[[int, int], None],
    backend: str,
) -> torch.Tensor:
    """Mean value coordinates ``(N, V)`` of checked points ``x`` ``(N, D)`` in their dtype."""
    lib = _native.select(backend, x, cage.vertices, dims=(2, 3))
    if cage.dim == 3:
        data3 = triangle_cage_data(cage, x.dtype)
        tables = native_tables(data3) if lib is not None else {}
        nf = data3.tri.shape[0]

        def kernel(c: torch.Tensor, out: torch.Tensor) -> None:
            if lib is not None:
                native_chunk(c, data3, tables, lib, out)
                return
            Wc, onc = mvc3d_chunk(c, data3)
            out.copy_(normalise_weights(Wc.T, onc, cage.vertices.to(c.dtype), c))
    else:
        data2 = polygon_data(cage, x.dtype)
        nf = data2.edges.shape[0]

        edges32 = cage.edges.to(torch.int32).contiguous()
        verts = cage.vertices.to(x.dtype).contiguous()

        def kernel(c: torch.Tensor, out: torch.Tensor) -> None:
            if lib is not None:
                c = c.contiguous()
                on = torch.empty(c.shape[0], dtype=torch.uint8)
                args = [verts, verts.shape[0], edges32, edges32.shape[0], c, c.shape[0], data2.tol,
                        torch.get_num_threads(), out, on]  # fmt: skip
                _native.call(lib.tc_mvc2d, args)  # type: ignore[union-attr]
                return
            Wc, onc = mvc2d_chunk(c, data2)
            out.copy_(normalise_weights(Wc.T, onc, cage.vertices.to(c.dtype), c))

    # The native kernel needs no temporaries beyond its output: chunks only pace the progress bar.
    # Pairs per chunk, measured on 2 cores: ~130k (3D torch) and ~250k (2D) amortise the per-op
    # overhead while the temporaries stay in cache.
    target = 1 << 23 if lib is not None else (1 << 17 if cage.dim == 3 else 1 << 18)
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


def mean_value_coordinates(
    points: torch.Tensor,
    cage: Cage,
    *,
    chunk_size: int | None = None,
    dtype: torch.dtype | None = None,
    progress: bool | Callable[[int, int], None] = False,
    backend: str = "auto",
) -> torch.Tensor:
    """Mean value coordinates of points with respect to a closed triangle cage or a closed polygon.

    The coordinates reproduce constants and linear functions (``W @ V = X``), interpolate linearly
    on the cage (barycentric on faces, linearly on edges, Lagrange at vertices) and extend smoothly
    to the whole space, outside the cage included. Each row sums to one.

    Args:
        points: ``(*, D)`` query points, ``D = cage.dim``.
        cage: a closed triangle cage (3D) or a closed polygon (2D). Quad cages are refused: use
            :func:`torchcage.functional.quad_mean_value_coordinates` or ``cage.triangulated()``.
        chunk_size: points per chunk; peak memory grows with ``chunk_size x faces``. Default: about
            130k (3D) or 260k (2D) point–face pairs per chunk in the torch kernel.
        dtype: dtype of the result (default: that of the inputs). The kernels compute in float64
            whatever it is (float32 would lose accuracy near the cage: see docs/accuracy.md).
        progress: ``True`` for a progress bar, or a callable ``progress(done, total)``.
        backend: ``"auto"`` (default): for float64 on the CPU, torchcage's native C kernel
            (compiled on first use, about a second) when a C compiler is present and no autograd
            graph is needed, else the torch kernel; ``"torch"`` forces the torch kernel (any
            device and dtype); ``"native"`` requires the native one.

    Gradients: when the points or ``cage.vertices`` require grad (or under ``torch.func``
    transforms), the call goes through :class:`torchcage.autograd.MeanValueFunction`: derivatives
    with respect to the points are the analytic gradients, and on double backward the analytic
    Hessians (:func:`mean_value_derivatives`), finite everywhere off the cage; derivatives with
    respect to the cage's vertices come from autograd of the torch kernel. ``gradcheck`` and
    ``gradgradcheck`` pass in float64; ``torch.func.jacrev``, ``vmap`` and ``hessian`` work with
    respect to the points.

    Returns:
        Coordinates of shape ``(*, V)``.

    Raises:
        CageError: a quad cage.
        PointsError: points of the wrong dimension or device, NaN or inf in the points, or points
            where the coordinates are undefined (outside the cage, where the total weight vanishes).

    Example:
        >>> import torch, torchcage
        >>> from torchcage import functional as F
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> x = torch.tensor([[0.1, 0.2, -0.3], [0.0, 0.0, 1.0]], dtype=torch.float64)
        >>> w = F.mean_value_coordinates(x, cube)
        >>> w.shape, torch.allclose(w.sum(-1), torch.ones(2, dtype=torch.float64))
        (torch.Size([2, 8]), True)
        >>> torch.allclose(w @ cube.vertices, x)
        True
    """
    flat = check_points(points, cage)
    compute, out_dtype = result_dtype(flat, cage, dtype)
    if records_graph(flat, cage.vertices):
        from ..autograd.mean_value import mean_value_function

        if cage.dim == 3:  # the same checks as the plain path (a triangle cage)
            triangle_cage_data(cage, compute)
        lam = mean_value_function(flat, cage, chunk_size, backend)
    else:
        lam = _coordinates_flat(flat.to(compute), cage, chunk_size, progress, backend)
    return lam.to(out_dtype).reshape(*points.shape[:-1], cage.num_vertices)
