r"""Analytic gradients and Hessians of mean value coordinates (3D triangle cages, 2D polygons).

With the raw weights ``w`` and ``W = sum_i w_i``, the coordinates ``lam = w / W`` have

.. math::
    \nabla\lambda_i = \frac{\nabla w_i - \lambda_i \nabla W}{W},\qquad
    H\lambda_i = \frac{H w_i - \lambda_i H W - \nabla\lambda_i \nabla W^T - \nabla W \nabla\lambda_i^T}{W}.

The weights' derivatives are closed-form (Thiery, Tierny, Boubekeur 2014 give one derivation;
torchcage uses its own, stable one). In 3D each point–face pair takes one of three evaluations,
all exact up to rounding:

* **direct**: from ``sum_j w_j a_j = m`` (``a_j = p_j - x``, ``m`` the face's mean vector)
  follow ``U dw = dm + W e_c`` and ``U d2w = d2m + dW e_c + dW e_d`` with ``U = [a_1 a_2 a_3]``;
  the cross products ``N_e`` in ``m`` are affine in ``x``, so only the scalars
  ``theta_e / (2|N_e|)`` need derivatives (by the chain rule, through
  ``G(t) = atan(sqrt t)/sqrt t``, smooth through the edges' support lines);
* **near the face's support plane** (``|h| < DERIVATIVE_SPLIT_FORM_RATIO min |a_i|``, the published formulas' weak spot:
  the ratio of two vanishing quantities), the split form of the coordinates (see ``kernel3d``), in
  which every term carries its power of the distance ``h`` explicitly, is differentiated as it
  stands; where an edge is seen under a small angle its two large terms are combined through a
  divided difference of ``G``, so the form stays exact through the edge's support line;
* **far field** (longest edge below ``DERIVATIVE_FAR_FIELD_RATIO`` times the distance): the
  defining integral ``h int phi_i / |p - x|^4 dA`` by a collapsed Gauss rule, differentiated under the integral (the
  vector form loses ``(r / edge)^k`` digits there).

In 2D each edge adds ``tan(alpha/2) / r`` to its two vertices, with ``tan(alpha/2)`` in one of two
cancellation-free forms. The kernels are native C (``backends/native/mvcd3d.c``, ``mvcd2d.c``, glue and
thresholds in ``derivatives_native``), with a small second-order jet type doing the chain rule; for
CUDA points the Triton kernels ``families/mean_value/triton/mvcd3d.py`` and ``mvcd2d.py`` evaluate the same formulas.
Where none serves (no C compiler, no triton), ``derivatives_torch`` differentiates the torch kernel of
the coordinates instead.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch._C._functorch import is_functorch_wrapped_tensor

from torchcage._core.alloc import empty_output
from torchcage._core.batch import broadcast_batch, check_finite_batch, native_batch_inputs, over_cage_batch
from torchcage._core.centre import centred, centred_batch, extent_of, keep_extent
from torchcage._core.common import (
    as_inputs,
    check_points,
    chunks,
    far_unity,
    on_cage_tolerances,
    triangle_geometry,
)
from torchcage._core.compiled import DerivativesOp
from torchcage.backends import Op, resolve, select
from torchcage.cage import Cage, _batch_name
from torchcage.errors import PointsError
from torchcage.families.mean_value import derivatives_native as _mvcd_native
from torchcage.families.mean_value.derivatives_torch import torch_derivatives

__all__ = ["derivatives_flat", "mean_value_derivatives", "mean_value_gradients", "mean_value_hessians"]


#: The kernels of the analytic mean value derivatives: the native one takes CPU points of any
#: dtype (cast to float64) and serves calls inside autograd Functions (it computes derivatives).
MVC_DERIVATIVES = Op(
    "mean value derivatives", native_dims=(2, 3), native_float64_only=False, triton=True, triton_dims=(2, 3)
)


def _eager(
    points: torch.Tensor, cage: Cage, order: int, chunk_size: int | None, extend: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    return mean_value_derivatives(points, cage, order, chunk_size=chunk_size)


def _tails(v: torch.Tensor, t: torch.Tensor, q: torch.Tensor, e: torch.Tensor, order: int) -> list[list[int] | None]:
    V, D = v.shape[-2], v.shape[-1]
    return [[V], [V, D], [V, D, D] if order == 2 else None]


#: The function as one opaque custom op under ``torch.compile`` (:mod:`torchcage._core.compiled`).
COMPILED = DerivativesOp("mvc_derivatives", _eager, _tails, MVC_DERIVATIVES, promote=False)


def derivatives_flat(
    x: torch.Tensor,
    cage: Cage,
    order: int,
    chunk_size: int | None = None,
    progress: bool | Callable[[int, int], None] = False,
    backend: str = "auto",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The kernel on checked points ``x`` ``(n, D)``: float64 tensors ``lam (n, V)``,
    ``grad (n, V, D)``, ``hess (n, V, D, D)`` (empty for ``order=1``) and the ``(n,)`` bool mask of
    points on the cage (their rows hold the interpolant and its derivatives: see mvcd3d.c). The
    native kernel (CPU) or, where it cannot serve, autograd of the torch kernel
    (:mod:`.derivatives_torch`, on the points' device).

    The derivatives of every row sum to zero over the vertices (the coordinates sum to 1): their
    mean over the vertices, the kernels' rounding, is taken out. Left in, it multiplied the
    cage's distance from the origin in ``sum_v grad_v V_v^T = I`` (a translated cage) and the
    centred identity is unchanged by it (``sum_v (V_v - m) = 0`` for the vertices' mean ``m``).

    Raises:
        PointsError: points where the coordinates are undefined (the total weight vanishes).
    """
    lam, grad, hess, on = _derivatives_flat(x, cage, order, chunk_size, progress, backend)
    if is_functorch_wrapped_tensor(grad):
        grad = grad - grad.mean(dim=1, keepdim=True)
        if order == 2:
            hess = hess - hess.mean(dim=1, keepdim=True)
    else:  # (the kernels' fresh outputs, without a graph: in place, sparing an allocation of each)
        grad.sub_(grad.mean(dim=1, keepdim=True))
        if order == 2:
            hess.sub_(hess.mean(dim=1, keepdim=True))
    return lam, grad, hess, on


def _derivatives_flat(
    x: torch.Tensor,
    cage: Cage,
    order: int,
    chunk_size: int | None,
    progress: bool | Callable[[int, int], None],
    backend: str,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`derivatives_flat` before the derivatives' mean over the vertices is taken out."""
    choice = select(MVC_DERIVATIVES, backend, x, graph=False)  # (the kernels record no graph)
    if choice.kind == "triton":
        return _triton_derivatives(x, cage, order, chunk_size, progress)
    if choice.lib is None:
        return torch_derivatives(x, cage, order, chunk_size, progress)
    lib = choice.lib
    x = x.detach().to("cpu", torch.float64)
    tables = _mvcd_native.native_tables(cage)
    lam, grad, hess, flags = native_batch(x[None], tables, lib, order, chunk_size, progress)  # (a batch of one)
    _refuse(flags, torch.Size([]))
    return lam[0], grad[0], hess[0] if order == 2 else hess, flags[0] == 1


def native_batch(
    x: torch.Tensor,
    tables: dict[str, object],
    lib: object,
    order: int,
    chunk_size: int | None = None,
    progress: bool | Callable[[int, int], None] = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The native kernel on a batch of cages of dimension ``D`` with one topology: centred float64
    CPU points ``x`` ``(B or 1, N, D)``, the tables of :func:`derivatives_native.batch_tables` (3D)
    or :func:`derivatives_native.polygon_tables` (2D) -> float64 ``lam (B, N, V)``, ``grad (B, N,
    V, D)``, ``hess (B, N, V, D, D)`` (empty for ``order=1``) and the uint8
    flags ``(B, N)`` (1 on the cage, 2 where the total weight vanishes). The kernel writes into the
    outputs: one call for every cage and point, or with ``chunk_size`` (or a progress bar: chunks
    of ``4096 / B`` points) one call per chunk of points for every cage, through temporaries
    copied into place (a chunk's rows are not contiguous in a batch).

    Raises:
        MemoryError: the kernel could not allocate its per-thread scratch.
    """
    B, V, N, D = int(tables["B"]), int(tables["V"]), x.shape[1], x.shape[2]  # type: ignore[call-overload]
    lam = empty_output(B, N, V, dtype=torch.float64)
    grad = empty_output(B, N, V, D, dtype=torch.float64)
    hess = empty_output(*((B, N, V, D, D) if order == 2 else (0,)), dtype=torch.float64)
    flags = torch.empty((B, N), dtype=torch.uint8)
    size = chunk_size if chunk_size is not None else (max(64, 4096 // B) if progress else max(N, 1))
    for sl in chunks(N, size, progress, desc="mean value derivatives"):
        direct = B == 1 or (sl.start == 0 and sl.stop == N)  # (the slices are contiguous: written in place)
        outs = [lam[:, sl], grad[:, sl], hess[:, sl] if order == 2 else None, flags[:, sl]]
        parts = (
            outs
            if direct
            else [None if o is None else torch.empty_like(o, memory_format=torch.contiguous_format) for o in outs]
        )
        _mvcd_native.native_chunk(x[:, sl], tables, lib, order, *parts)  # type: ignore[arg-type]
        if not direct:
            for o, part in zip(outs, parts, strict=True):
                if o is not None:
                    o.copy_(part)  # type: ignore[arg-type]
    return lam, grad, hess, flags


def _refuse(flags: torch.Tensor, batch: torch.Size) -> None:
    """Raise for the points whose total weight vanishes (flag 2 in ``flags`` ``(B, N)``), naming
    the first batch element that has some (of ``batch``; none for one cage).

    Raises:
        PointsError: the points (first ten) and the batch element.
    """
    bad = flags == 2
    if bool(bad.any()):
        b = int(torch.nonzero(bad.any(dim=1))[0])
        idx = torch.nonzero(bad[b]).flatten()[:10].tolist()
        raise PointsError(
            f"mean value coordinates are undefined at points {idx}{_batch_name(torch.tensor(b), batch)} (the total "
            "weight vanishes there); move these points"
        )


def _triton_derivatives(
    x: torch.Tensor, cage: Cage, order: int, chunk_size: int | None, progress: bool | Callable[[int, int], None]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`derivatives_flat` by the Triton kernel (float64, on the points' device)."""
    if cage.dim == 2:
        from torchcage.families.mean_value.triton.mvcd2d import mvcd2d_triton as kernel
    else:
        from functools import partial

        from torchcage.families.mean_value.triton.mvcd3d import derivative_tables, mvcd3d_triton

        kernel = partial(mvcd3d_triton, tables=derivative_tables(cage, x.device))  # (built once for all chunks)

    n, V, D = x.shape[0], cage.num_vertices, cage.dim
    lam = x.new_empty((n, V), dtype=torch.float64)
    grad = x.new_empty((n, V, D), dtype=torch.float64)
    hess = x.new_empty((n, V, D, D) if order == 2 else (0,), dtype=torch.float64)
    flags = torch.zeros(n, dtype=torch.uint8, device=x.device)
    for sl in chunks(n, chunk_size if chunk_size is not None else 4096, progress, desc="mean value derivatives"):
        lam[sl], grad[sl], h, flags[sl] = kernel(x[sl], cage, order)
        if order == 2:
            hess[sl] = h
    bad = torch.nonzero(flags == 2).flatten()[:10].tolist()
    if bad:
        raise PointsError(
            f"mean value coordinates are undefined at points {bad} (the total weight vanishes there); move these points"
        )
    return lam, grad, hess, flags == 1


def mean_value_derivatives(
    points: torch.Tensor,
    cage: Cage,
    order: int = 2,
    *,
    chunk_size: int | None = None,
    progress: bool | Callable[[int, int], None] = False,
    backend: str = "auto",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Mean value coordinates with their analytic gradients and (``order=2``) Hessians.

    Args:
        points: ``(*, D)`` query points off the cage, ``D = cage.dim``.
        cage: a closed triangle cage (3D) or a closed polygon (2D).
            Or a batch of cages ``(*B, V, D)`` with one topology: then ``points`` are
            ``(*B, N, D)`` (or ``(N, D)``, shared) and every result gains the batch shape in front
            (``(*B, N, V)``); each element equals the call on ``cage[b]`` (docs/learning.md).
        order: 1 (gradients) or 2 (gradients and Hessians).
        chunk_size: points per chunk (memory grows with ``chunk_size x V x D^2``, times ``B`` for
            a batch of ``B`` cages). Default: 4096 (on the native kernel: every point in one call,
            written into the outputs; with a progress bar, and on the Triton kernels, chunks of
            ``4096 / B`` points for a batch of ``B`` cages).
        progress: ``True`` for a progress bar, or a callable ``progress(done, total)``.
        backend: ``"auto"`` (default): the native kernel for CPU points when it is loadable; for
            points on CUDA the Triton kernel where triton is installed; else autograd of the
            torch kernel on the points' device (the same values to about 1e-10). ``"native"``,
            ``"torch"`` or ``"triton"`` to force one.

    Computed in float64, returned in the points' dtype and device.
    These values are plain tensors (no autograd graph): to differentiate through the coordinates,
    call :func:`mean_value_coordinates` on points that require grad.

    Returns:
        ``(lam (*, V), grad (*, V, D), hess (*, V, D, D) or None)``: ``grad[..., i, c]`` is
        ``d lam_i / d x_c``, ``hess[..., i, c, d]`` is ``d^2 lam_i / d x_c d x_d``.

    Raises:
        PointsError: points on the cage (the coordinates are not differentiable there), points where
            the coordinates are undefined, NaN/inf, or points of the wrong shape.
        ValueError: ``order`` not 1 or 2.

    Examples:
        >>> import torch, torchcage
        >>> from torchcage import functional as F
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> x = torch.tensor([[0.1, 0.2, -0.3]], dtype=torch.float64)
        >>> lam, grad, hess = F.mean_value_derivatives(x, cube)
        >>> grad.shape, hess.shape
        (torch.Size([1, 8, 3]), torch.Size([1, 8, 3, 3]))
        >>> torch.allclose(torch.einsum("nvc,vd->ncd", grad, cube.vertices), torch.eye(3, dtype=torch.float64))
        True
    """
    if order not in (1, 2):
        raise ValueError(f"order must be 1 or 2, got {order}")
    if torch.compiler.is_compiling():  # one opaque op: the checks and kernels below are not traceable
        return COMPILED(points, cage, order, chunk_size, backend)  # type: ignore[return-value]
    backend = resolve(backend)
    points, cage = as_inputs(points, cage)
    if cage.is_batched:
        out = _derivatives_batch(points, cage, order, chunk_size, progress, backend)
        if out is not None:
            return out
        # (the torch kernel, torch.func transforms: one call per element)
        return over_cage_batch(
            mean_value_derivatives, points, cage, order=order, chunk_size=chunk_size, progress=progress, backend=backend
        )
    flat = check_points(points, cage)
    if cage.dim == 3:
        triangle_geometry(cage, torch.float64, "use cage.triangulated() to split quads")
    x, rel = centred(flat.detach(), cage, torch.float64)  # (relative to the cage's centre: translation invariant)
    with keep_extent(extent_of(cage.vertices)):
        lam, grad, hess, on = derivatives_flat(x, rel, order, chunk_size, progress, backend)
    idx = torch.nonzero(on).flatten()[:10].tolist()
    if idx:
        raise PointsError(
            f"points {idx} lie on the cage, where mean value coordinates are not differentiable; move them off the cage"
        )
    lam, grad, hess = far_unity(lam, x.to(lam), rel.vertices.to(lam), grad, hess if order == 2 else None)
    dt = flat.dtype
    lead, D, V = points.shape[:-1], cage.dim, cage.num_vertices
    out_l = lam.to(flat.device, dt).reshape(*lead, V)
    out_g = grad.to(flat.device, dt).reshape(*lead, V, D)
    out_h = hess.to(flat.device, dt).reshape(*lead, V, D, D) if order == 2 else None
    return out_l, out_g, out_h


def _derivatives_batch(
    points: torch.Tensor,
    cage: Cage,
    order: int,
    chunk_size: int | None,
    progress: bool | Callable[[int, int], None],
    backend: str,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None] | None:
    """:func:`mean_value_derivatives` of a batch of cages with one topology in one kernel call per
    chunk of points for every cage: the native kernel (CPU) or the Triton kernels (CUDA, or CPU
    under ``TRITON_INTERPRET=1``), 3D triangle cages and polygons, the tables of the batch
    built by one set of tensor operations; element by element the numbers of the single-cage call
    (the native kernel: bitwise; Triton: to rounding). ``None`` where neither serves (quads, another
    backend or device, ``torch.func`` transforms, no native build): the caller then
    loops over the cages.

    Raises:
        PointsError: points that do not broadcast with the cages, NaN or inf, points on the cage or
            where the coordinates are undefined, naming the batch element.
    """
    D = cage.dim
    lib = None
    inputs = native_batch_inputs(points, cage, backend, planar=True)
    if inputs is not None:
        check_finite_batch(inputs[0], inputs[2])  # (naming the element on every CPU path, the loop's too)
        probe = inputs[0].new_empty((0, D), dtype=torch.float64)
        lib = select(MVC_DERIVATIVES, backend, probe, graph=False).lib
        inputs = inputs if lib is not None else None
    if inputs is None:
        inputs = _triton_batch_inputs(points, cage, backend)
        if inputs is None:
            return None
        check_finite_batch(inputs[0], inputs[2])
    pts, verts, batch = inputs
    tols = on_cage_tolerances(verts)  # (the uncentred cages', as the single-cage call's)
    x, v = centred_batch(pts.detach(), verts.detach(), torch.float64)  # (each relative to its centre)
    if lib is None:
        faces = cage.edges if D == 2 else cage.triangles
        lam, grad, hess, flags = _triton_batch(x, v, faces, tols, order, chunk_size, progress, verts)
    else:
        if D == 2:
            tables = _mvcd_native.polygon_tables(v, cage.edges, tols)
        else:
            tables = _mvcd_native.batch_tables(v, cage.triangles.cpu(), tols)
        lam, grad, hess, flags = native_batch(x, tables, lib, order, chunk_size, progress)
    _refuse(flags, batch)
    grad.sub_(grad.mean(dim=2, keepdim=True))  # (as derivatives_flat: the kernels' rounding of the sum)
    if order == 2:
        hess.sub_(hess.mean(dim=2, keepdim=True))
    on = flags == 1
    if bool(on.any()):
        b = int(torch.nonzero(on.any(dim=1))[0])
        idx = torch.nonzero(on[b]).flatten()[:10].tolist()
        raise PointsError(
            f"points {idx}{_batch_name(torch.tensor(b), batch)} lie on the cage, where mean value coordinates are not "
            "differentiable; move them off the cage"
        )
    B, N, V = v.shape[0], x.shape[1], v.shape[1]
    lam, grad, h = far_unity(lam, x.expand(B, N, D), v, grad, hess if order == 2 else None)
    dt = pts.dtype
    out_h = h.to(dt).reshape(*batch, N, V, D, D) if h is not None else None
    return lam.to(dt).reshape(*batch, N, V), grad.to(dt).reshape(*batch, N, V, D), out_h  # type: ignore[union-attr]


def _triton_batch_inputs(
    points: torch.Tensor, cage: Cage, backend: str
) -> tuple[torch.Tensor, torch.Tensor, torch.Size] | None:
    """:func:`broadcast_batch` of a batched call (polygons, 3D triangle cages) that the Triton
    kernels serve (``backend`` ``"auto"`` or ``"triton"``, points where :func:`select` takes them),
    else ``None``.

    Raises:
        RuntimeError: ``backend="triton"`` where the kernel cannot serve (as the loop's calls raise).
    """
    if cage.has_quads or backend not in ("auto", "triton"):
        return None
    if is_functorch_wrapped_tensor(points) or is_functorch_wrapped_tensor(cage.vertices):
        return None
    pts, verts, batch = broadcast_batch(points, cage)
    if not pts.is_floating_point() or pts.device != verts.device:
        return None
    probe = pts.new_empty((0, cage.dim), dtype=torch.float64)
    if select(MVC_DERIVATIVES, backend, probe, graph=False).kind != "triton":
        return None
    return pts, verts, batch


def _triton_batch(
    x: torch.Tensor,
    v: torch.Tensor,
    faces: torch.Tensor,
    tol: torch.Tensor,
    order: int,
    chunk_size: int | None,
    progress: bool | Callable[[int, int], None],
    uncentred: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The Triton kernels on a batch of cages (``mvcd2d``: polygons, ``mvcd3d``: triangle cages):
    centred float64 points ``x`` ``(B or 1, N, D)`` and vertices ``v`` ``(B, V, D)`` on the
    kernel's device, ``faces`` the edges or triangles, ``tol`` ``(B,)``, the ``uncentred`` vertices
    (the extents of the 3D redo's tolerances) -> as :func:`native_batch` (on the points' device);
    one launch per chunk of points for every cage (default ``4096 / B`` points: a chunk's jets are
    ``B x chunk x V x 10`` float64)."""
    B, N, V, D = v.shape[0], x.shape[1], v.shape[1], v.shape[2]
    if D == 2:
        from torchcage.families.mean_value.triton.mvcd2d import batch_tables, mvcd2d_triton_batch

        tables = batch_tables(v, faces, tol)

        def launch(c: torch.Tensor) -> tuple[torch.Tensor, ...]:
            return mvcd2d_triton_batch(c, tables, order)
    else:
        from torchcage.families.mean_value.triton import mvcd3d

        tables = mvcd3d.batch_tables(v, faces, tol)
        cages = [Cage._from_faces(v[b], faces.to(v.device)) for b in range(B)]  # (the rare redo's)
        extents = uncentred.detach().abs().amax(dim=(1, 2))

        def launch(c: torch.Tensor) -> tuple[torch.Tensor, ...]:
            return mvcd3d.mvcd3d_triton_batch(c, tables, order, cages, extents=extents)

    lam = x.new_empty((B, N, V))
    grad = x.new_empty((B, N, V, D))
    hess = x.new_empty((B, N, V, D, D) if order == 2 else (0,))
    flags = torch.empty((B, N), dtype=torch.uint8, device=x.device)
    size = chunk_size if chunk_size is not None else max(64, 4096 // B)
    for sl in chunks(N, size, progress, desc="mean value derivatives"):
        lam[:, sl], grad[:, sl], h, flags[:, sl] = launch(x[:, sl])
        if order == 2:
            hess[:, sl] = h
    return lam, grad, hess, flags


def mean_value_gradients(points: torch.Tensor, cage: Cage, **kwargs: object) -> torch.Tensor:
    """Analytic gradients ``(*, V, D)`` of the mean value coordinates: ``[..., i, c] = d lam_i / d x_c``.

    Same arguments as :func:`mean_value_derivatives` (without ``order``).

    Examples:
        >>> import torch, torchcage
        >>> from torchcage import functional as F
        >>> square = torchcage.Cage(torch.tensor([[0., 0], [1, 0], [1, 1], [0, 1]], dtype=torch.float64),
        ...                         torch.tensor([[0, 1], [1, 2], [2, 3], [3, 0]]))
        >>> g = F.mean_value_gradients(torch.tensor([[0.3, 0.6]], dtype=torch.float64), square)
        >>> torch.allclose(g.sum(dim=1), torch.zeros(1, 2, dtype=torch.float64))
        True
    """
    return mean_value_derivatives(points, cage, 1, **kwargs)[1]  # type: ignore[arg-type]


def mean_value_hessians(points: torch.Tensor, cage: Cage, **kwargs: object) -> torch.Tensor:
    """Analytic Hessians ``(*, V, D, D)`` of the mean value coordinates:
    ``[..., i, c, d] = d^2 lam_i / d x_c d x_d``.

    Same arguments as :func:`mean_value_derivatives` (without ``order``).

    Examples:
        >>> import torch, torchcage
        >>> from torchcage import functional as F
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> H = F.mean_value_hessians(torch.tensor([[0.1, 0.2, -0.3]], dtype=torch.float64), cube)
        >>> torch.einsum("nvcd,ve->necd", H, cube.vertices).abs().max() < 1e-12  # linear precision
        tensor(True)
    """
    return mean_value_derivatives(points, cage, 2, **kwargs)[2]  # type: ignore[return-value]
