r"""Mean value coordinates for closed triangle cages (3D) and closed polygons (2D): the public
function. The kernels live beside it: ``kernel3d`` (torch, 3D: the formulation and its numerical
care are described there), ``kernel2d`` (2D), ``native3d`` and ``native2d`` (the native CPU
kernels' glue), chosen in ``dispatch``; with a graph, the call goes through
:mod:`.ops`.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchcage._core.batch import check_finite_batch, native_batch_inputs, over_cage_batch
from torchcage._core.centre import centre_of, centred
from torchcage._core.common import as_inputs, check_points, far_unity, records_graph, result_dtype
from torchcage._core.compiled import CompiledOp
from torchcage.backends import resolve, select
from torchcage.cage import Cage
from torchcage.families.mean_value.dispatch import MVC, coordinates_batch, coordinates_flat
from torchcage.families.mean_value.kernel3d import triangle_cage_data
from torchcage.families.mean_value.ops import MeanValueBatchFunction, mean_value_function

__all__ = ["mean_value_coordinates"]

#: The function as one opaque custom op under ``torch.compile`` (:mod:`torchcage._core.compiled`).
COMPILED = CompiledOp(
    "mvc",
    lambda points, cage, options: (mean_value_coordinates(points, cage, **options),),
    lambda vertices, triangles, quads, edges: [vertices.shape[-2]],
    MVC,
)


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
            Or a batch of cages ``(*B, V, D)`` with one topology: then ``points`` are
            ``(*B, N, D)`` (or ``(N, D)``, shared) and every result gains the batch shape in front
            (``(*B, N, V)``); each element equals the call on ``cage[b]`` (docs/learning.md).
            Without an autograd graph, the whole batch is one native kernel call (CPU) or one
            Triton launch (CUDA), triangle cages and polygons, per chunk of points;
            with a graph, a batch of triangle cages takes one native call forward and one
            backward (CPU); elsewhere, one call per element.
        chunk_size: points per chunk; peak memory grows with ``chunk_size x faces``. Default: about
            130k (3D) or 260k (2D) point–face pairs per chunk in the torch kernel.
        dtype: dtype of the result (default: that of the inputs). The kernels compute in float64
            whatever it is (float32 would lose accuracy near the cage: see docs/accuracy.md).
        progress: ``True`` for a progress bar, or a callable ``progress(done, total)``.
        backend: ``"auto"`` (default): for float64 on the CPU, torchcage's native C kernel
            (built at install time; see the guide) when it loads and no autograd graph is needed
            (with one, values still come from it and derivatives from the autograd Functions),
            else the torch kernel; on CUDA tensors, the Triton kernel when triton is installed
            (values; derivatives through the autograd Function); ``"torch"`` forces the torch
            kernel (any device and dtype); ``"native"`` requires the native one; ``"triton"`` the
            Triton one (CUDA tensors, or CPU tensors with ``TRITON_INTERPRET=1``), which with
            ``dtype=torch.float32`` computes in float32 (docs/gpu.md).

    Gradients: when the points or ``cage.vertices`` require grad (or under ``torch.func``
    transforms), and the native kernel serves (CPU points, a native build), the call goes through
    :class:`torchcage.autograd.MeanValueFunction`: derivatives with respect to the points are the
    analytic gradients, and on double backward the analytic Hessians (:func:`mean_value_derivatives`),
    finite everywhere off the cage; derivatives with respect to the cage's vertices come from
    autograd of the torch kernel. Elsewhere (a GPU, ``TORCHCAGE_NATIVE=0``) every derivative is
    autograd of the torch kernel: finite, equal to the analytic ones to about 1e-12
    (docs/accuracy.md gives the figures). ``gradcheck`` and
    ``gradgradcheck`` pass in float64; ``torch.func.jacrev``, ``jacfwd``, ``vmap`` and ``hessian``
    work with respect to the points.

    Returns:
        Coordinates of shape ``(*, V)``.

    Raises:
        CageError: a quad cage.
        PointsError: points of the wrong dimension or device, NaN or inf in the points, or points
            where the coordinates are undefined (outside the cage, where the total weight vanishes).

    Examples:
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
    if torch.compiler.is_compiling():  # one opaque op: the checks below are not traceable
        (lam,) = COMPILED(points, cage, chunk_size, backend, dtype=dtype)
        return lam
    backend = resolve(backend)
    points, cage = as_inputs(points, cage)
    if cage.is_batched:
        # One native call / Triton launch for the whole batch (triangle cages and polygons without
        # an autograd graph; with a graph, triangle cages on the native kernels forward and
        # backward) ...
        if records_graph(points, cage.vertices):
            lam = _batch_with_graph(points, cage, chunk_size, dtype, progress, backend)
        else:
            lam = coordinates_batch(points, cage, chunk_size, dtype, progress, backend)
        if lam is not None:
            return lam
        # ... elsewhere (the torch kernel, torch.func transforms, 2D with a graph) one call per element for
        # now (_batch.over_cage_batch): those paths have no batched kernel yet.
        return over_cage_batch(
            mean_value_coordinates, points, cage, chunk_size=chunk_size, dtype=dtype, progress=progress, backend=backend
        )
    flat = check_points(points, cage)
    compute, out_dtype = result_dtype(flat, cage, dtype, backend)
    # relative to the cage's centre (exact; the coordinates are translation invariant): module _centre
    x, rel = centred(flat, cage, compute)
    if records_graph(flat, cage.vertices):
        if cage.dim == 3:  # the same checks as the plain path (a triangle cage)
            triangle_cage_data(cage, compute)
        lam = mean_value_function(x, rel, chunk_size, backend)
    else:
        lam = coordinates_flat(x, rel, chunk_size, progress, backend)
    (lam,) = far_unity(lam, x, rel.vertices.to(lam.dtype))
    return lam.to(out_dtype).reshape(*points.shape[:-1], cage.num_vertices)


def _batch_with_graph(
    points: torch.Tensor,
    cage: Cage,
    chunk_size: int | None,
    dtype: torch.dtype | None,
    progress: bool | Callable[[int, int], None],
    backend: str,
) -> torch.Tensor | None:
    """Mean value coordinates ``(*B', N, V)`` of a batch of 3D triangle cages with an autograd
    graph (points or rest vertices that require grad) through :class:`MeanValueBatchFunction`: one
    native call for the values of the whole batch and one for the first-order backward. ``None``
    where it does not serve (another backend or device, a torch.func transform, 2D or quads, no
    native build): the caller then loops over the cages. Element by element the numbers of the
    single-cage call: the same centring, kernels and far-field normalisation."""
    inputs = native_batch_inputs(points, cage, backend)
    if inputs is None:
        return None
    pts, verts, batch = inputs
    compute, out_dtype = result_dtype(pts, cage, dtype, backend)
    if compute != torch.float64 or select(MVC, backend, pts.new_empty((0, 3), dtype=compute), graph=False).lib is None:
        return None
    check_finite_batch(pts, batch)
    # each cage and its points relative to the cage's centre (a constant: module _core.centre)
    c = centre_of(verts, compute)[:, None, :]  # (B, 1, 3)
    x, v = pts.to(compute) - c, verts.to(compute) - c
    lam = MeanValueBatchFunction.apply(x, v, cage.triangles, chunk_size, progress, batch)
    (lam,) = far_unity(lam, x, v)
    return lam.to(out_dtype).reshape(*batch, x.shape[1], cage.num_vertices)
