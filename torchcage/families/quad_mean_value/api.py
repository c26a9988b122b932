r"""Quad mean value coordinates (QMVC) for quad and triquad cages: the public function. The torch
kernel (any device, differentiable) is ``kernel``; ``backends/native/qmvc3d.c`` is the CPU float64 one."""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable
from typing import Any, NamedTuple

import torch
from torch._C._functorch import is_functorch_wrapped_tensor

from torchcage._core.alloc import cat_output
from torchcage._core.batch import broadcast_batch, check_finite_batch, native_batch_inputs, over_cage_batch
from torchcage._core.centre import centre_of, centred_batch
from torchcage._core.common import (
    as_inputs,
    check_points,
    chunks,
    far_unity,
    may_be_far,
    normalise_weights,
    on_cage_tolerance,
    on_cage_tolerances,
    outside_point,
    records_graph,
    result_dtype,
)
from torchcage._core.compiled import CompiledOp, through_op
from torchcage.backends import Op, check, resolve, select
from torchcage.cage import Cage, _batch_name
from torchcage.errors import CageError, PointsError
from torchcage.families.mean_value.kernel3d import TriangleCageData, mvc3d_chunk, triangle_data
from torchcage.families.quad_mean_value.kernel import QuadData, project, qmvc3d_chunk, quad_data
from torchcage.families.quad_mean_value.native import native_coordinates

__all__ = ["quad_mean_value_coordinates"]


#: The largest grid parameter ``n`` the quad functions take (their kernels index ``(2n+1)^2`` samples
#: with C ints; past it, ``tol=`` is the way to accuracy).
MAX_GRID = 10_000


def check_quads(cage: Cage, allow_invalid: bool, what: str = "quad mean value coordinates") -> None:
    """Refuse (or, with ``allow_invalid``, warn about) quads that fail the validity predicate.

    Raises:
        CageError: a 2D cage (``what`` names the method), or invalid quads when ``allow_invalid``
            is False.
    """
    if cage.dim != 3:
        other = "mean_value_coordinates" if "mean value" in what else "green_coordinates"
        raise CageError(f"{what} need a 3D cage; use {other} for polygons")
    bad = cage.invalid_quads()
    if bad.numel():
        where = ""
        if cage.is_batched:  # (the first element that holds some, its quads; the others counted)
            mask = cage._invalid_quad_mask().reshape(-1, cage.quads.shape[0])  # (B, Q)
            elements = torch.nonzero(mask.any(dim=1)).flatten()
            bad = torch.nonzero(mask[elements[0]]).flatten()
            more = elements.numel() - 1
            where = _batch_name(elements[0], cage.batch_shape)
            where += f" (and some in {more} other element(s))" if more else ""
        msg = (
            f"{bad.numel()} quad(s) of the cage are not valid{where} (Thiery et al. 2018, Definition 1: the "
            f"projection of a quad onto the planes of its corner triangles must be convex), e.g. quads "
            f"{bad[:10].tolist()} (indices into cage.quads)"
        )
        if not allow_invalid:
            raise CageError(msg + "; fix the cage, split these quads, or pass allow_invalid=True to proceed")
        warnings.warn(msg + "; proceeding as asked (allow_invalid=True): the projection may leave those quads",
                      stacklevel=3)  # fmt: skip


def check_tol(tol: float | None) -> float | None:
    """Check the ``tol`` argument of the quad coordinates (``None``: the paper's Riemann sum).

    Raises:
        ValueError: ``tol`` is not a number in ``[1e-14, 0.1]``.
    """
    if tol is None:
        return None
    if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not (MIN_TOL <= tol <= 0.1):
        raise ValueError(
            f"tol must be a number in [{MIN_TOL:g}, 0.1] (the relative error of the defining integrals), got {tol!r}; "
            "pass tol=None for the paper's Riemann sum of resolution n"
        )
    return float(tol)


#: The smallest ``tol`` accepted: below it float64 rounding, not the quadrature, sets the error.
MIN_TOL = 1e-14


def check_grid(n: int) -> None:
    """Refuse a grid parameter ``n`` the quad functions do not take.

    Raises:
        ValueError: ``n`` not an integer in ``[1, MAX_GRID]``.
    """
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    if n > MAX_GRID:
        raise ValueError(
            f"n = {n} is past {MAX_GRID}: the cost grows like n^2 per point and quad while the error falls "
            "slowly (docs/qmvc.md); for accuracy pass tol= (the integrals to a tolerance) instead"
        )


def prepare_quad_call(
    points: torch.Tensor,
    cage: Cage,
    n: int,
    dtype: torch.dtype | None,
    allow_invalid: bool,
    what: str = "quad mean value coordinates",
) -> tuple[torch.Tensor, torch.dtype, torch.Tensor, float]:
    """Shared checks of the quad coordinate functions: ``n``, the points, the quads' validity.

    Returns:
        ``(x (N, 3), out_dtype, vertices (V, 3), tol)``: the flattened points and the cage's
        vertices in the compute dtype, the dtype to return, and the absolute on-cage tolerance.
    """
    check_grid(n)
    if cage.dim != 3:
        check_quads(cage, allow_invalid, what)
    flat = check_points(points, cage)
    check_quads(cage, allow_invalid, what)
    compute, out_dtype = result_dtype(flat, cage, dtype)
    return flat.to(compute), out_dtype, cage.vertices.to(compute), on_cage_tolerance(cage)


#: The kernels of quad mean value coordinates: on CUDA, ``"auto"`` takes the Triton kernel (the
#: paper's Riemann sum; ``tol=`` runs on torch): it passed every test of tests/test_triton_qmvc.py
#: compiled on an H200 (docs/gpu.md).
QMVC = Op("quad mean value coordinates", triton=True)


#: The function as one opaque custom op under ``torch.compile`` (:mod:`torchcage._core.compiled`).
COMPILED = CompiledOp(
    "qmvc",
    lambda points, cage, options: (quad_mean_value_coordinates(points, cage, **options),),
    lambda vertices, triangles, quads, edges: [vertices.shape[-2]],
    QMVC,
)


def quad_mean_value_coordinates(
    points: torch.Tensor,
    cage: Cage,
    n: int = 4,
    *,
    chunk_size: int | None = None,
    dtype: torch.dtype | None = None,
    progress: bool | Callable[[int, int], None] = False,
    backend: str = "auto",
    allow_invalid: bool = False,
    tol: float | None = None,
) -> torch.Tensor:
    """Quad mean value coordinates (Thiery, Memari, Boubekeur 2018) for quad and triquad cages.

    Quads are treated as bilinear patches (not split into triangles): the coordinates reproduce
    constants and linear functions exactly, interpolate bilinearly on quads (linearly on
    triangles), respect the cage's symmetries, and equal :func:`mean_value_coordinates` on a
    triangle-only cage. The part of a quad's weights that the mean value identity leaves free is
    estimated by an adaptive Riemann sum on a ``(2n+1) x (2n+1)`` grid of the quad centred on the
    point's smooth projection; ``n = 4`` is the paper's default.

    Args:
        points: ``(*, 3)`` query points.
        cage: a closed 3D cage of triangles and/or quads, all quads valid (see
            :meth:`Cage.invalid_quads`).
            Or a batch of cages ``(*B, V, D)`` with one topology: then ``points`` are
            ``(*B, N, D)`` (or ``(N, D)``, shared) and every result gains the batch shape in front
            (``(*B, N, V)``); each element equals the call on ``cage[b]`` (docs/learning.md).
        n: grid parameter, ``n >= 1``; the cost grows like ``(2n+1)^2`` per point and quad.
        chunk_size: points per chunk (peak memory of the torch kernel grows with
            ``chunk_size x quads x (2n+1)^2``).
        dtype: dtype of the result (default: that of the inputs). The kernels compute in float64
            whatever it is (float32 would lose accuracy near the cage: see docs/accuracy.md).
        progress: ``True`` for a progress bar, or a callable ``progress(done, total)``.
        backend: ``"auto"`` (default): the native C kernel for float64 CPU points when no autograd
            graph is needed, the Triton kernel for CUDA points (triton installed, no graph,
            ``tol=None``; docs/gpu.md), else the torch kernel; ``"torch"``, ``"native"`` or
            ``"triton"`` to force one.
        allow_invalid: compute even if some quads are invalid (with a warning) instead of raising.
        tol: if given (in ``[1e-14, 0.1]``), the exact coordinates: the quads' defining integrals
            to this relative tolerance by an error-controlled Gauss quadrature (``n`` is then
            unused), projected onto the weights that reproduce linear functions exactly. Each
            coordinate of a point inside the cage is then within about ``tol`` of the exact QMVC,
            whatever the cage's size (docs/qmvc.md: tol = 1e-8 measured within 1e-11).

    Gradients: the torch kernel is differentiable with respect to the points (the scheme is
    smooth off the cage) and the cage vertices; ``"auto"`` picks it when either requires grad.

    Returns:
        Coordinates ``(*, V)``; rows sum to one.

    Raises:
        CageError: a 2D cage, or invalid quads (unless ``allow_invalid``).
        PointsError: points of the wrong shape or device, NaN or inf, or points outside the cage
            where the total weight vanishes.
        ValueError: an unknown ``backend``, or ``"triton"`` with ``tol`` (the Triton kernel computes
            the Riemann sum).
        RuntimeError: ``backend="triton"`` or ``"native"`` where that kernel cannot serve.

    Examples:
        >>> import torch, torchcage
        >>> from torchcage import functional as F
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))   # 6 quads
        >>> x = torch.tensor([[0.1, 0.2, -0.3], [0.0, 0.0, 2.0]], dtype=torch.float64)
        >>> w = F.quad_mean_value_coordinates(x, cube)
        >>> torch.allclose(w @ cube.vertices, x), torch.allclose(w.sum(-1), torch.ones(2, dtype=torch.float64))
        (True, True)
        >>> exact = F.quad_mean_value_coordinates(x, cube, tol=1e-8)  # the integrals themselves
        >>> torch.allclose(exact @ cube.vertices, x), bool((exact - w).abs().max() < 1e-2)
        (True, True)
    """
    if through_op(points, cage) and not allow_invalid:  # one opaque op (compile, vmap: :mod:`_core.compiled`)
        (lam,) = COMPILED(points, cage, chunk_size, backend, n, check_tol(tol), dtype=dtype)
        return lam
    backend = resolve(backend)
    points, cage = as_inputs(points, cage)
    if cage.is_batched:
        lam = _native_batch(points, cage, n, chunk_size, dtype, progress, backend, allow_invalid, tol)
        if lam is None:
            lam = _triton_batch(points, cage, n, chunk_size, dtype, progress, backend, allow_invalid, tol)
        if lam is not None:
            return lam
        # (the torch kernel, graphs, torch.func transforms: one call per element,
        # invalid quads refused first for the batch, naming the element)
        if not allow_invalid:
            check_quads(cage, False)
        return over_cage_batch(
            quad_mean_value_coordinates,
            points,
            cage,
            n=n,
            chunk_size=chunk_size,
            dtype=dtype,
            progress=progress,
            backend=backend,
            allow_invalid=allow_invalid,
            tol=tol,
        )
    quad_tol = check_tol(tol)
    x, out_dtype, verts, tol = prepare_quad_call(points, cage, n, dtype, allow_invalid)
    # relative to the cage's centre (exact; the coordinates are translation invariant, module _centre;
    # the on-cage tolerance stays the uncentred cage's: points within their rounding of a quad are on it)
    c = centre_of(verts, verts.dtype)
    x, verts = x - c, verts - c
    check(QMVC, backend)
    if backend == "triton" and quad_tol is not None:
        raise ValueError(
            "backend='triton' computes the paper's Riemann sum (tol=None); the exact integrals (tol=...) run on "
            "backend='torch' or 'native'"
        )
    choice = select(QMVC, backend, x, cage.vertices)
    use_triton, lib = choice.kind == "triton" and quad_tol is None, choice.lib  # (tol: torch on CUDA)
    if lib is not None:
        tols = torch.tensor([tol], dtype=torch.float64)
        out = native_coordinates(
            lib, x[None], verts[None], cage.triangles, cage.quads, tols, n, quad_tol, chunk_size, progress
        )[0]
        _refuse_undefined(out[None], torch.Size([]))
        (out,) = far_unity(out, x, verts)
        return out.to(out_dtype).reshape(*points.shape[:-1], cage.num_vertices)
    T, Q = cage.triangles.shape[0], cage.quads.shape[0]
    tdata = triangle_data(verts, cage.triangles, tol) if T else None
    qdata = quad_data(verts, cage.quads, tol) if Q else None
    if use_triton:
        kernel = _triton_kernel(verts, tdata, qdata, n)
        size = chunk_size or max(256, (1 << 23) // cage.num_vertices)
    else:
        kernel = functools.partial(_torch_chunk, verts=verts, tdata=tdata, qdata=qdata, n=n, quad_tol=quad_tol)
        samples = (2 * n + 1) ** 2 if quad_tol is None else 256
        size = chunk_size or max(16, (1 << 19) // (max(Q, 1) * samples) + 1)
    parts = [kernel(x[sl]) for sl in chunks(x.shape[0], size, progress, desc="quad mean value coordinates")]
    out = cat_output(parts) if parts else x.new_zeros((0, cage.num_vertices))
    _refuse_undefined(out.detach()[None], torch.Size([]))
    (out,) = far_unity(out, x, verts)
    return out.to(out_dtype).reshape(*points.shape[:-1], cage.num_vertices)


def _native_batch(
    points: torch.Tensor,
    cage: Cage,
    n: int,
    chunk_size: int | None,
    dtype: torch.dtype | None,
    progress: bool | Callable[[int, int], None],
    backend: str,
    allow_invalid: bool,
    tol: float | None,
) -> torch.Tensor | None:
    """Quad mean value coordinates ``(*B', N, V)`` of a batch of cages with one topology by the
    native kernel: one call per chunk of points for every cage, the cages' tables built by one set
    of tensor operations; element by element the numbers of the single-cage call. ``None`` where it
    does not serve (another backend or device, a compute dtype other than float64, an autograd
    graph or a ``torch.func`` transform, no native build): the caller then loops over the cages.

    Raises:
        ValueError: a wrong ``n``, ``tol`` or ``backend``.
        CageError: invalid quads (unless ``allow_invalid``).
        PointsError: points that do not broadcast with the cages, NaN or inf, or points where the
            coordinates are undefined, naming the batch element.
    """
    call = quad_batch_call(QMVC, points, cage, n, dtype, backend, allow_invalid, tol, "quad mean value coordinates")
    if call is None:
        return None
    pts, verts, batch, out_dtype, lib, quad_tol = call
    compute = torch.float64
    tols = on_cage_tolerances(verts)  # (the uncentred cages', as the single-cage call)
    x, v = centred_batch(pts, verts, compute)  # (each cage relative to its centre: module _core.centre)
    out = native_coordinates(lib, x, v, cage.triangles, cage.quads, tols, n, quad_tol, chunk_size, progress)
    _refuse_undefined(out, batch)
    if may_be_far(v, x):  # (else far_unity leaves every row as it is)
        (out,) = far_unity(out, x.expand(v.shape[0], *x.shape[1:]), v)
    return out.to(out_dtype).reshape(*batch, x.shape[1], cage.num_vertices)


def _triton_batch(
    points: torch.Tensor,
    cage: Cage,
    n: int,
    chunk_size: int | None,
    dtype: torch.dtype | None,
    progress: bool | Callable[[int, int], None],
    backend: str,
    allow_invalid: bool,
    tol: float | None,
) -> torch.Tensor | None:
    """Quad mean value coordinates ``(*B', N, V)`` of a batch of cages with one topology by the
    Triton kernels (CUDA, or CPU under ``TRITON_INTERPRET=1``): per chunk of points, one launch of
    the triangle kernel (raw weights) and one of the quad kernel for every cage, the cages' tables
    built by one set of tensor operations; the weights normalised for the batch at once; points
    that see a thin triangle from a few widths redone by the torch kernel, cage by cage (as the
    single-cage call redoes them). Element by element the numbers of the single-cage Triton call,
    to rounding. ``None`` where it does not serve (another backend or device, ``tol=`` (exact
    integrals: the torch kernel), a compute dtype other than float64, an autograd graph or a
    ``torch.func`` transform): the caller then loops over the cages.

    Raises:
        ValueError: a wrong ``n``, ``tol`` or ``backend``.
        CageError: invalid quads (unless ``allow_invalid``).
        PointsError: points that do not broadcast with the cages, NaN or inf, or points where the
            coordinates are undefined, naming the batch element.
    """
    check_grid(n)
    check(QMVC, backend)
    if check_tol(tol) is not None or backend not in ("auto", "triton") or cage.dim != 3:
        return None
    if records_graph(points, cage.vertices) or any(map(is_functorch_wrapped_tensor, (points, cage.vertices))):
        return None
    pts, verts, batch = broadcast_batch(points, cage)
    if not pts.is_floating_point() or pts.device != verts.device:
        return None
    compute, out_dtype = result_dtype(pts, cage, dtype)
    if compute != torch.float64 or select(QMVC, backend, pts.new_empty((0, 3), dtype=compute)).kind != "triton":
        return None
    from torchcage.families.mean_value.triton.mvc3d import mvc3d_triton, part_batch_tables
    from torchcage.families.quad_mean_value.triton.qmvc3d import batch_tables, qmvc3d_triton

    check_quads(cage, allow_invalid, "quad mean value coordinates")
    check_finite_batch(pts, batch)
    tols = on_cage_tolerances(verts)  # (the uncentred cages', as the single-cage call)
    x, v = centred_batch(pts, verts, compute)  # (each cage relative to its centre: module _core.centre)
    B, N, V = v.shape[0], x.shape[1], v.shape[1]
    tri, quads = cage.triangles.to(v.device), cage.quads.to(v.device)
    tri_tables = part_batch_tables(v, tri, tols) if tri.shape[0] else None
    quad_tables = batch_tables(v, quads, tols, n) if quads.shape[0] else None
    out = torch.empty((B, N, V), dtype=compute, device=v.device)
    flags = torch.empty((B, N), dtype=torch.int32, device=v.device)
    size = chunk_size or max(256, (1 << 23) // (B * V))
    for sl in chunks(N, size, progress, desc="quad mean value coordinates"):
        c = x[:, sl]
        m = c.shape[1]
        if tri_tables is not None:
            W, f = mvc3d_triton(c, tri_tables, normalize=quad_tables is None)
        else:
            W = torch.zeros((B, m, V), dtype=compute, device=v.device)
            f = torch.zeros((B, m), dtype=torch.int32, device=v.device)
        if quad_tables is not None:
            qmvc3d_triton(c, quad_tables, W, f)
            W = normalise_weights(W, f == 1, v, c)
        out[:, sl], flags[:, sl] = W, f
    redo = flags == 2  # (B, N): a thin triangle seen from a few widths (the torch kernel's swept form)
    for b in torch.nonzero(redo.any(dim=1)).flatten().tolist():
        idx = torch.nonzero(redo[b]).flatten()
        tb = float(tols[b])
        tdata = triangle_data(v[b], tri, tb) if tri.shape[0] else None
        qdata = quad_data(v[b], quads, tb) if quads.shape[0] else None
        out[b, idx] = _torch_chunk(x[b if x.shape[0] > 1 else 0].index_select(0, idx), v[b], tdata, qdata, n)
    _refuse_undefined(out, batch)
    if may_be_far(v, x):  # (else far_unity leaves every row as it is)
        (out,) = far_unity(out, x.expand(B, N, 3), v)
    return out.to(out_dtype).reshape(*batch, N, V)


class QuadBatchCall(NamedTuple):
    """What :func:`quad_batch_call` found: the broadcast points ``(B' or 1, N, 3)`` and cages
    ``(B', V, 3)`` (views), the caller's batch shape, the output dtype, the native library and the
    quadrature's tolerance (``None``: the Riemann sum)."""

    points: torch.Tensor
    vertices: torch.Tensor
    batch: torch.Size
    out_dtype: torch.dtype
    lib: Any
    quad_tol: float | None


def quad_batch_call(
    op: Op,
    points: torch.Tensor,
    cage: Cage,
    n: int,
    dtype: torch.dtype | None,
    backend: str,
    allow_invalid: bool,
    tol: float | None,
    what: str,
) -> QuadBatchCall | None:
    """The checks of a quad family's batched native call (``op``: QMVC or QGC): ``n``, ``tol`` and
    ``backend`` first (they raise whichever path serves), then whether the native kernel serves (a
    3D cage on the CPU, float64 compute, no graph or ``torch.func`` transform, a native build; else
    ``None``: the caller loops over the cages), then the quads and the points.

    Raises:
        ValueError: a wrong ``n``, ``tol`` or ``backend``.
        CageError: invalid quads (unless ``allow_invalid``).
        PointsError: points that do not broadcast with the cages, NaN or inf, naming the element.
    """
    check_grid(n)
    quad_tol = check_tol(tol)
    check(op, backend)
    inputs = None if records_graph(points, cage.vertices) else native_batch_inputs(points, cage, backend, quads=True)
    if inputs is None:
        return None
    pts, verts, batch = inputs
    compute, out_dtype = result_dtype(pts, cage, dtype)
    if compute != torch.float64:
        return None
    lib = select(op, backend, pts.new_empty((0, 3), dtype=compute), graph=False).lib
    if lib is None:
        return None
    check_quads(cage, allow_invalid, what)
    check_finite_batch(pts, batch)
    return QuadBatchCall(pts, verts, batch, out_dtype, lib, quad_tol)


def _refuse_undefined(out: torch.Tensor, batch: torch.Size) -> None:
    """Raise for rows of ``out`` ``(B, N, V)`` that are not finite (the total weight vanishes),
    naming the first batch element that has some (of ``batch``; none for one cage).

    Raises:
        PointsError: the points (first ten) and the batch element.
    """
    bad = ~torch.isfinite(out.sum(dim=-1))  # (B, N): a row sum is finite iff every entry is
    if bool(bad.any()):
        b = int(torch.nonzero(bad.any(dim=1))[0])
        idx = torch.nonzero(bad[b]).flatten()[:10].tolist()
        where = _batch_name(torch.tensor(b), batch)
        raise PointsError(
            f"quad mean value coordinates are undefined at points {idx}{where} (the total weight vanishes there, "
            "which happens only outside the cage); move these points"
        )


def _triton_kernel(
    verts: torch.Tensor, tdata: TriangleCageData | None, qdata: QuadData | None, n: int
) -> Callable[[torch.Tensor], torch.Tensor]:
    """The Triton kernels (triangles: raw mean value weights; quads: ``_triton.qmvc3d``) as a chunk
    function ``x (m, 3) -> coordinates (m, V)``, normalised on the device; points the triangle
    kernel flags (a thin face seen from a few widths) are redone by the torch kernel."""
    from torchcage.families.mean_value.triton.mvc3d import mvc3d_triton, part_tables
    from torchcage.families.quad_mean_value.triton.qmvc3d import qmvc3d_triton, triton_tables

    tri_tables = part_tables(tdata) if tdata is not None else None
    quad_tables = triton_tables(verts, qdata, n) if qdata is not None else None

    def kernel(c: torch.Tensor) -> torch.Tensor:
        c = c.contiguous()
        if tri_tables is not None:
            W, flags = mvc3d_triton(c, tri_tables, normalize=quad_tables is None)
            if quad_tables is None:  # a triangle cage: normalised by the triangle kernel
                return _redo(W, flags, c, verts, tdata, qdata, n)
        else:
            W = torch.zeros((c.shape[0], verts.shape[0]), dtype=c.dtype, device=c.device)
            flags = torch.zeros(c.shape[0], dtype=torch.int32, device=c.device)
        qmvc3d_triton(c, quad_tables, W, flags)
        W = normalise_weights(W, flags == 1, verts, c)
        return _redo(W, flags, c, verts, tdata, qdata, n)

    return kernel


def _redo(
    W: torch.Tensor,
    flags: torch.Tensor,
    c: torch.Tensor,
    verts: torch.Tensor,
    tdata: TriangleCageData | None,
    qdata: QuadData | None,
    n: int,
) -> torch.Tensor:
    """``W`` with the rows flagged 2 by the Triton triangle kernel computed by the torch kernel."""
    redo = torch.nonzero(flags == 2).flatten()
    if redo.numel():
        W = W.index_copy(0, redo, _torch_chunk(c.index_select(0, redo), verts, tdata, qdata, n))
    return W


def _torch_chunk(
    c: torch.Tensor,
    verts: torch.Tensor,
    tdata: TriangleCageData | None,
    qdata: QuadData | None,
    n: int,
    quad_tol: float | None = None,
) -> torch.Tensor:
    """Normalised coordinates ``(m, V)`` of a chunk ``c`` ``(m, 3)`` with the torch kernels.

    Points on a quad get the bilinear coordinates of their parameters ``(u, v)`` on it (Lagrange at
    a corner). When a graph is recorded, the regular formula of those points (singular there) is
    evaluated at a point off the cage, and their ``(u, v)`` carry the derivative of the surface's
    inverse parametrisation: one Gauss-Newton step ``(u, v) + J^+ (x - xi(u, v))`` from the detached
    projection, exact in value (the residual is zero on the quad) and differentiable in the point
    and the corners. Corners get constant Lagrange values (derivative 0).
    """
    m, V = c.shape[0], verts.shape[0]
    if tdata is not None:
        # (V, m); columns on a triangle are final. With quads the triangles are part of the cage.
        W, on = mvc3d_chunk(c, tdata, part=qdata is not None)
    else:
        W = torch.zeros((V, m), dtype=c.dtype, device=c.device)
        on = torch.zeros(m, dtype=torch.bool, device=c.device)
    if qdata is None:
        return normalise_weights(W.T, on, verts, c)
    graph = records_graph(c, qdata.corners)
    creg = c
    if graph:
        with torch.no_grad():
            pr = project(c, qdata)
        onq_any = (pr.on & ~on[None, :]).any(dim=0) | on
        if bool(onq_any.any()):
            creg = torch.where(onq_any[:, None], outside_point(verts), c)
    w, onq, u, v, vertex = qmvc3d_chunk(creg, qdata, n, quad_tol)
    if creg is not c:  # the projection of the points themselves (not of their stand-ins)
        onq, u, v, vertex = pr.on, pr.u, pr.v, pr.vertex
    quads = qdata.quads
    for i in range(4):
        W = W.index_add(0, quads[:, i], torch.where(on[None, :], torch.zeros_like(w[i]), w[i]))
    W = normalise_weights(W.T, on, verts, c)
    onq = onq & ~on[None, :]
    has = onq.any(dim=0)
    if bool(has.any()):
        # Points on a quad: the bilinear coordinates of their projection (Lagrange at a corner).
        f = onq.to(torch.int8).argmax(dim=0)
        cols = torch.arange(m, device=c.device)
        uu, vv, vx = u[f, cols], v[f, cols], vertex[f, cols]
        if graph:
            uu, vv = _newton_uv(c, qdata.corners[..., 0][:, :, f], uu.detach(), vv.detach())
        b = torch.stack([(1 - uu) * (1 - vv), uu * (1 - vv), uu * vv, (1 - uu) * vv], dim=1)
        b = torch.where((vx >= 0)[:, None], torch.nn.functional.one_hot(vx.clamp_min(0), 4).to(b.dtype), b)
        Wq = torch.zeros((m, V), dtype=c.dtype, device=c.device).scatter_add(1, quads[f], b)
        W = torch.where(has[:, None], Wq, W)
    return W


def _newton_uv(x: torch.Tensor, q: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """One Gauss-Newton step of the inverse bilinear map: ``(u, v) + J^+ (x - xi(u, v))`` for points
    ``x`` ``(m, 3)`` on the sheets with corners ``q`` ``(3, 4, m)`` at detached parameters ``u, v``
    ``(m,)``; finite where the sheet is degenerate (the step is skipped)."""
    q0, q1, q2, q3 = (q[:, i, :] for i in range(4))  # (3, m)
    xi = (1 - u) * (1 - v) * q0 + u * (1 - v) * q1 + u * v * q2 + (1 - u) * v * q3
    xu = (1 - v) * (q1 - q0) + v * (q2 - q3)
    xv = (1 - u) * (q3 - q0) + u * (q2 - q1)
    r = x.T - xi
    a, b, d = (xu * xu).sum(0), (xu * xv).sum(0), (xv * xv).sum(0)
    det = a * d - b * b
    ok = det > 0
    inv = torch.where(ok, 1.0 / torch.where(ok, det, 1.0), 0.0)
    ru, rv = (xu * r).sum(0), (xv * r).sum(0)
    return u + (d * ru - b * rv) * inv, v + (a * rv - b * ru) * inv
