"""Autograd Functions of mean value coordinates.

* ``MeanValueFunction``: ``lam = mvc(points, vertices)``. Its derivative with respect to the points
  is the analytic gradient (``MeanValueGradFunction``), whose own derivative is the analytic Hessian
  (``MeanValueHessFunction``): first and second order, double backward included, finite wherever
  the points are off the cage (autograd through the coordinate formula gives NaN or inf on the
  faces' support planes). Derivatives with respect to the rest cage's vertices are exact too:
  autograd through the torch kernel of the coordinates (twice, for the mixed second derivatives).
* Forward mode (``jvp``) is implemented for tangents of the points, so ``torch.func.jacfwd`` and
  ``torch.func.hessian`` work; every Function sets ``generate_vmap_rule = True`` and calls its
  kernel through a ``torch.library`` custom op with a batching rule (a vmapped batch of points is
  folded into one kernel call), so ``torch.func.vmap`` and ``jacrev`` work too.
* Third derivatives are not implemented (``MeanValueHessFunction.backward`` raises).
* Points on the cage: the coordinates interpolate there and are not differentiable across it;
  there the derivatives are those of the interpolant (barycentric in the largest face holding the
  point, its gradient in the face's plane; linear along a polygon's edge; zero at a vertex),
  Hessians zero.

Derivations: ``torchcage/families/mean_value/derivatives.py`` and ``backends/native/mvcd3d.c``.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch._C._functorch import is_functorch_wrapped_tensor

from torchcage._core.common import (
    GRADIENT_TABLE_ENTRIES,
    check_finite,
    no_vertex_tangent,
    on_cage_tolerance,
    on_cage_tolerances,
    result_dtype,
)
from torchcage.backends import check, preferred, use
from torchcage.backends import native as _native
from torchcage.backends import triton as _triton
from torchcage.cage import Cage
from torchcage.families.mean_value.derivatives import derivatives_flat
from torchcage.families.mean_value.dispatch import MVC, coordinates_flat, native_batch
from torchcage.families.mean_value.edge_line import edge_line_offsets as _edge_line_offsets
from torchcage.families.mean_value.kernel3d import _stable_face_weights
from torchcage.families.mean_value.vjp3d import direct_vjp
from torchcage.families.mean_value.vjp3d_native import native_vjp, native_vjp_batch, native_vjp_near

__all__ = [
    "MeanValueBatchFunction",
    "MeanValueFunction",
    "MeanValueGradFunction",
    "MeanValueHessFunction",
    "mean_value_function",
]


_cage = Cage._from_faces  # (vertices, faces of a validated cage) -> Cage


def _torch_coordinates(points: Tensor, vertices: Tensor, faces: Tensor) -> Tensor:
    """Coordinates by the torch kernel, recording autograd with respect to points and vertices."""
    compute, out = result_dtype(points, _cage(vertices, faces), None)
    return coordinates_flat(points.to(compute), _cage(vertices.to(compute), faces), None, False, "torch").to(out)


# ----------------------------------------------------------------------------------- custom ops
@torch.library.custom_op("torchcage::mean_value_coordinates", mutates_args=())
def _coordinates_op(points: Tensor, vertices: Tensor, faces: Tensor, chunk_size: int) -> Tensor:
    """The coordinates by the kernel that :func:`torchcage.backends.select` takes for the points'
    device and the backend in force (:func:`torchcage.backends.use`: no backend in the schema)."""
    check_finite(points)
    cage = _cage(vertices, faces)
    compute, out = result_dtype(points, cage, None)
    with torch.no_grad():
        lam = coordinates_flat(points.to(compute), cage, chunk_size if chunk_size > 0 else None, False, preferred())
    return lam.to(out)


@_coordinates_op.register_fake
def _(points, vertices, faces, chunk_size):
    dt = torch.promote_types(points.dtype, vertices.dtype)
    return points.new_empty((points.shape[0], vertices.shape[0]), dtype=dt)


@torch.library.custom_op("torchcage::mean_value_derivatives", mutates_args=())
def _derivatives_op(points: Tensor, vertices: Tensor, faces: Tensor, order: int) -> Tensor:
    check_finite(points)
    _, grad, hess, _ = derivatives_flat(points, _cage(vertices.detach(), faces), order)
    out = grad if order == 1 else hess
    return out.to(points.device, torch.promote_types(points.dtype, vertices.dtype))


def _derivatives(points: Tensor, vertices: Tensor, faces: Tensor, order: int) -> Tensor:
    """The analytic gradients (``order=1``) or Hessians (2) through the custom op, or where the
    native kernel cannot serve, autograd of the torch kernel (it needs autograd, which a custom
    op's body does not have)."""
    if _analytic(points):
        return _derivatives_op(points, vertices, faces, order)
    if is_functorch_wrapped_tensor(points):
        raise NotImplementedError(
            "forward-mode derivatives (torch.func.jvp, jacfwd, hessian) of mean value coordinates need the "
            f"native CPU kernel, which is unavailable here ({_native.failure_reason() or 'points not on the CPU'}); "
            "reverse mode (backward, double backward) works on any device"
        )
    check_finite(points)
    _, grad, hess, _ = derivatives_flat(points, _cage(vertices.detach(), faces), order, backend="torch")
    return (grad if order == 1 else hess).to(torch.promote_types(points.dtype, vertices.dtype))


@_derivatives_op.register_fake
def _(points, vertices, faces, order):
    D = points.shape[-1]
    shape = (points.shape[0], vertices.shape[0], D) + ((D,) if order == 2 else ())
    return points.new_empty(shape, dtype=torch.promote_types(points.dtype, vertices.dtype))


def _fold(points: Tensor, vertices: Tensor, pdim: int | None, vdim: int | None) -> tuple[Tensor, int]:
    """Fold a vmapped batch of points into the point axis (vertices unbatched)."""
    if vdim is not None:
        raise NotImplementedError("vmap over the rest cage's vertices is not supported; vmap over the points")
    x = points.movedim(pdim, 0) if pdim is not None else points[None]
    return x.reshape(-1, x.shape[-1]), x.shape[0]


def _coordinates_vmap(info, in_dims, points, vertices, faces, chunk_size):
    x, B = _fold(points, vertices, in_dims[0], in_dims[1])
    lam = _coordinates_op(x, vertices, faces, chunk_size)
    return lam.reshape(B, -1, lam.shape[-1]), 0


def _derivatives_vmap(info, in_dims, points, vertices, faces, order):
    x, B = _fold(points, vertices, in_dims[0], in_dims[1])
    out = _derivatives_op(x, vertices, faces, order)
    return out.reshape(B, -1, *out.shape[1:]), 0


torch.library.register_vmap("torchcage::mean_value_coordinates", _coordinates_vmap)
torch.library.register_vmap("torchcage::mean_value_derivatives", _derivatives_vmap)


# ----------------------------------------------------------------------------------- Functions
#: Points per chunk of the autograd fallbacks below: their saved intermediates, not the points,
#: bound the memory of a backward pass (about 1 KB per point-face pair).
_VJP_PAIRS = 1 << 17


def _row_chunks(points: Tensor, faces: Tensor) -> list[slice]:
    size = max(64, _VJP_PAIRS // max(1, faces.shape[0]))
    return [slice(s, s + size) for s in range(0, points.shape[0], size)]


def _vertex_vjp(points: Tensor, vertices: Tensor, faces: Tensor, g: Tensor) -> Tensor:
    """``sum g * d lam / d vertices`` by autograd of the torch kernel, chunk by chunk of points (kept
    differentiable when the caller records a graph: double backward). Points on an edge's line
    outside the edge take the mean of the derivatives at two points beside the line
    (:func:`_edge_line_offsets`)."""
    off = _edge_line_offsets(points, vertices, faces) if points.shape[-1] == 3 else None
    if off is not None:
        rows = torch.nonzero(off.abs().sum(dim=1) > 0).flatten()
        rest = torch.nonzero(off.abs().sum(dim=1) == 0).flatten()
        xr, gr, o = points.index_select(0, rows), g.index_select(0, rows), off.index_select(0, rows)
        mean = 0.5 * (_vertex_vjp_plain(xr + o, vertices, faces, gr) + _vertex_vjp_plain(xr - o, vertices, faces, gr))
        if rest.numel() == 0:
            return mean
        return mean + _vertex_vjp_plain(points.index_select(0, rest), vertices, faces, g.index_select(0, rest))
    return _vertex_vjp_plain(points, vertices, faces, g)


def _vertex_vjp_plain(points: Tensor, vertices: Tensor, faces: Tensor, g: Tensor) -> Tensor:
    """:func:`_vertex_vjp` without the edge-line rule."""
    create = torch.is_grad_enabled()
    total = torch.zeros_like(vertices)
    for sl in _row_chunks(points, faces):
        with torch.enable_grad():
            P = vertices if create and vertices.requires_grad else vertices.detach().requires_grad_()
            lam = _torch_coordinates(points[sl] if create else points[sl].detach(), P, faces)
            (gP,) = torch.autograd.grad(lam, P, g[sl], create_graph=create)
        total = total + gP
    return total


def _analytic(points: Tensor) -> bool:
    """Whether analytic derivatives serve points ``(N, D)``: the native kernel (CPU, library
    loadable) or, for points on CUDA, the Triton kernel; else the point derivatives come from
    autograd of the torch kernel, on any device."""
    if points.device.type == "cpu":
        return _native.library() is not None
    return points.device.type == "cuda" and _triton.available(points)


def _point_vjp(points: Tensor, vertices: Tensor, faces: Tensor, g: Tensor) -> Tensor:
    """``sum g * d lam / d points`` by autograd of the torch kernel, chunk by chunk: where the native
    derivatives cannot serve (a GPU, no C compiler). Kept differentiable when the caller records a
    graph. Points on an edge's line outside the edge take the mean of the derivatives beside the
    line, as in :func:`_vertex_vjp` (autograd of the split form was 6x off there)."""
    off = _edge_line_offsets(points, vertices, faces) if points.shape[-1] == 3 else None
    if off is None:
        return _point_vjp_plain(points, vertices, faces, g)
    line = off.abs().sum(dim=1) > 0
    rows = torch.nonzero(line).flatten()
    xr, gr, o = points.index_select(0, rows), g.index_select(0, rows), off.index_select(0, rows)
    mean = 0.5 * (_point_vjp_plain(xr + o, vertices, faces, gr) + _point_vjp_plain(xr - o, vertices, faces, gr))
    out = _point_vjp_plain(points, vertices, faces, g)  # (only the line rows are replaced)
    return out.index_copy(0, rows, mean.to(out.dtype))


def _point_vjp_plain(points: Tensor, vertices: Tensor, faces: Tensor, g: Tensor) -> Tensor:
    """:func:`_point_vjp` without the edge-line rule."""
    create = torch.is_grad_enabled()
    parts = []
    for sl in _row_chunks(points, faces):
        with torch.enable_grad():
            x = points[sl] if create and points.requires_grad else points[sl].detach().requires_grad_()
            lam = _torch_coordinates(x, vertices if create else vertices.detach(), faces)
            (gx,) = torch.autograd.grad(lam, x, g[sl], create_graph=create)
        parts.append(gx)
    return torch.cat(parts) if parts else torch.zeros_like(points)


def _point_grad(x: Tensor, P: Tensor, faces: Tensor, g: Tensor) -> Tensor:
    """``sum g * d lam / d points``: the analytic gradients where the native kernel serves, else
    autograd of the torch kernel."""
    if _analytic(x):  # (chunk by chunk of points: the gradient tables are (n, V, D))
        size = max(64, GRADIENT_TABLE_ENTRIES // max(1, P.shape[0] * x.shape[-1]))
        parts = [
            torch.einsum("nv,nvc->nc", g[s : s + size], MeanValueGradFunction.apply(x[s : s + size], P, faces))
            for s in range(0, x.shape[0], size)
        ]
        return torch.cat(parts) if len(parts) != 1 else parts[0]
    return _point_vjp(x, P, faces, g)


def _joint_vjp(x: Tensor, P: Tensor, faces: Tensor, g: Tensor, need_x: bool) -> tuple[Tensor | None, Tensor]:
    """First-order products with respect to the points and the rest vertices of a 3D cage at once:
    the hand-derived reverse mode of the direct form (``vjp3d``) for the regular points, chunk
    by chunk; with the native kernel, those near a support plane split per face
    (:func:`_split_vjp`) and those on the cage in closed form; the others (near an
    edge's line, thin faces, far outside) as in :meth:`MeanValueFunction.backward`'s general path,
    restricted to them."""
    dt = torch.float64 if x.device.type != "mps" else x.dtype
    x64, P64, g64 = x.detach().to(dt), P.detach().to(dt), g.to(dt)
    tol = on_cage_tolerance(_cage(P64, faces))
    gx = torch.zeros_like(x64)
    gP = torch.zeros_like(P64)
    lib = _native.library() if x.device.type == "cpu" and dt == torch.float64 else None
    if lib is not None:  # one pass over all points: the kernel needs no temporaries beyond its outputs
        gx, gP, reg = native_vjp(lib, x64, P64, faces, g64, tol)
        _irregular_vjp(lib, x, P, faces, g, torch.nonzero(~reg).flatten(), tol, gx, gP, need_x)
        return (gx.to(x.dtype) if need_x else None), gP.to(P.dtype)
    size = max(64, (1 << 16) // max(1, faces.shape[0]))
    irregular = []
    for s in range(0, x.shape[0], size):
        gxc, gPc, reg = direct_vjp(x64[s : s + size], P64, faces, g64[s : s + size], tol)
        gx[s : s + size] = gxc
        gP += gPc
        irregular.append(torch.nonzero(~reg).flatten() + s)
    idx = torch.cat(irregular) if irregular else torch.zeros(0, dtype=torch.long, device=x.device)
    if idx.numel():
        xi, gi = x.index_select(0, idx), g.index_select(0, idx)
        gP += _vertex_vjp(xi, P, faces, gi).to(dt)
        if need_x:
            gx[idx] = _point_grad(xi, P, faces, gi).to(dt)
    return (gx.to(x.dtype) if need_x else None), gP.to(P.dtype)


def _irregular_vjp(
    lib: object,
    x: Tensor,
    P: Tensor,
    faces: Tensor,
    g: Tensor,
    idx: Tensor,
    tol: float,
    gx: Tensor,
    gP: Tensor,
    need_x: bool,
) -> None:
    """:func:`_joint_vjp`'s products for the points ``idx`` the native direct form left (not
    regular), added into ``gx`` ``(N, 3)`` and ``gP`` ``(V, 3)`` (float64): those near a support
    plane split per face, those on the cage in closed form, the others by autograd of
    the torch kernel."""
    if idx.numel() == 0:
        return
    dt = gP.dtype
    x64, P64, g64 = x.detach().to(dt), P.detach().to(dt), g.to(dt)
    # near a support plane: the careful form on the pairs that need it only
    gxs, gPs, split = _split_vjp(lib, x64.index_select(0, idx), P64, faces, g64.index_select(0, idx), tol)
    gP += gPs
    gx[idx[split]] = gxs[split]
    idx = idx[~split]
    if idx.numel() == 0:
        return
    xi, gi = x.index_select(0, idx), g.index_select(0, idx)
    gxi, lam_i, inside = _on_face_vjp(xi, P, faces, gi)
    if bool(inside.any()):
        # On the cage (a face, an edge, a vertex) the coordinates are the interpolant's, and
        # d lam_v / d p_j = -lam_j d lam_v / dx (barycentric coordinates are affine
        # invariant; zero at a vertex): no autograd of the torch kernel for those points.
        gP -= lam_i[inside].T.to(dt) @ gxi[inside].to(dt)
        rest = torch.nonzero(~inside).flatten()
        xi, gi = xi.index_select(0, rest), gi.index_select(0, rest)
    if xi.shape[0]:
        gP += _vertex_vjp(xi, P, faces, gi).to(dt)
    if need_x:
        gx[idx] = gxi.to(dt)


def _split_vjp(
    lib, x: Tensor, P: Tensor, faces: Tensor, g: Tensor, tol: float, in_kernel: bool = True
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_joint_vjp`'s products for points ``x`` ``(n, 3)`` near a face's support plane (float64,
    CPU), split per face: the native kernel (:func:`native_vjp_near`) computes each point's weights
    (the stable split form where the direct one is not accurate), ``wbar`` and the products over
    the faces regular for the point, and over the others (*careful* pairs) forward-mode derivatives
    of the split form; with ``in_kernel=False`` it leaves those to autograd of the torch split
    form (:func:`kernel3d._stable_face_weights`) here, over those point–face pairs only, all at
    once (the same operations: the tests compare them). Points on the cage take the
    interpolant's closed form in the kernel (the values of :func:`_on_face_vjp`).

    Where a face holds the point's foot point its weights carry a term ``c_i / h``, whose
    derivative ``-c_i dh / h^2`` times ``wbar ~ h`` cancels to ``O(1)`` (autograd of it lost
    ``eps / h``): the coefficient of ``dh`` is taken instead from ``sum_v wbar_v w_v = 0`` as
    ``-(wbar . c) / h^2 = (sum over the other faces of wbar . w + wbar . r) / h``, ``r`` that face's
    weights less ``c / h`` (no cancellation), as the torch kernel's ``scaled`` form does.

    Returns:
        ``(gx (n, 3), gP (V, 3), split (n,) bool)``: the products over the points that took this
        path (``split``; the others' rows of ``gx`` are zero and they add nothing to ``gP``).
    """
    # (chunks of points: the kernel's per-point outputs wbar (n, V) and pair (n, T) stay bounded)
    size = max(64, (1 << 22) // (P.shape[0] + faces.shape[0]))
    gx, gP, split = torch.zeros_like(x), torch.zeros_like(P), torch.zeros(x.shape[0], dtype=torch.bool)
    for s in range(0, x.shape[0], size):
        gxc, gPc, split[s : s + size] = _split_chunk(lib, x[s : s + size], P, faces, g[s : s + size], tol, in_kernel)
        gx[s : s + size] = gxc
        gP += gPc
    return gx, gP, split


def _split_chunk(
    lib, x: Tensor, P: Tensor, faces: Tensor, g: Tensor, tol: float, in_kernel: bool
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_split_vjp` on one chunk of points."""
    gx, gP, split, pair, wbar, sn, hs = native_vjp_near(lib, x, P, faces, g, tol, in_kernel)
    p_idx, f_idx = torch.nonzero(pair, as_tuple=True)
    if p_idx.numel() == 0:
        return gx, gP, split
    corners = faces.index_select(0, f_idx)  # (M, 3)
    kind = pair[p_idx, f_idx]
    star = kind == 2  # the nearest face around the point's foot
    other = kind == 3  # another face around it (near an edge): its c / h as it is
    h0 = torch.where(star, hs.index_select(0, p_idx), 1.0)
    wb = wbar[p_idx[:, None], corners]  # (M, 3)
    with torch.enable_grad():
        xp = x.index_select(0, p_idx).requires_grad_()
        pf = P[corners].requires_grad_()  # (M, 3, 3)
        a = [pf[:, i] - xp for i in range(3)]
        E = [pf[:, (i + 1) % 3] - pf[:, (i + 2) % 3] for i in range(3)]
        cr = torch.linalg.cross(pf[:, 1] - pf[:, 0], pf[:, 2] - pf[:, 0], dim=-1)
        two_area = cr.norm(dim=-1)
        nrm = cr / two_area[:, None]
        h = (nrm * a[0]).sum(-1)
        s = [(nrm * torch.linalg.cross(a[(e + 1) % 3], a[(e + 2) % 3], dim=-1)).sum(-1) for e in range(3)]
        dots = [(a[(e + 1) % 3] * a[(e + 2) % 3]).sum(-1) for e in range(3)]
        R = [a[i].norm(dim=-1) for i in range(3)]
        ell = [E[e].norm(dim=-1) for e in range(3)]
        gram = [[(E[i] * E[e]).sum(-1) for e in range(3)] for i in range(3)]
        c: list[Tensor] = []
        r = _stable_face_weights(h, s, dots, R, ell, gram, two_area, c)
        wr = wb[:, 0] * r[0] + wb[:, 1] * r[1] + wb[:, 2] * r[2]
        wc = wb[:, 0] * c[0] + wb[:, 1] * c[1] + wb[:, 2] * c[2]
        beta = (sn.index_select(0, p_idx) + wr.detach()) / h0
        safe_h = torch.where(other, h, 1.0)
        loss = wr + torch.where(star, wc / h0 + beta * h, torch.where(other, wc / safe_h, 0.0))
        gxp, gpf = torch.autograd.grad(loss.sum(), (xp, pf))
    gx.index_add_(0, p_idx, gxp)
    gP.index_add_(0, corners.reshape(-1), gpf.reshape(-1, 3))
    return gx, gP, split


def _on_face_vjp(x: Tensor, P: Tensor, faces: Tensor, g: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The native analytic ``sum g * d lam / d points`` ``(n, 3)`` (as :func:`_point_grad`), the
    coordinates ``(n, V)`` (float64) and the ``(n,)`` mask of the points on the cage (in a face, on
    an edge or at a vertex; off every edge's line outside the edge: :func:`_edge_line_offsets`).
    There the gradient is the interpolant's in the largest face that holds the point (``tc_mvcd3d``'s
    choice, as the torch kernel's; on an edge, where the coordinates have a kink, the rest vertices'
    products ``-lam_j gx`` are that face's too)."""
    lam, grad, _, on = derivatives_flat(x, _cage(P.detach(), faces), 1)
    grad = grad.to(x.device, torch.promote_types(x.dtype, P.dtype))
    gx = torch.einsum("nv,nvc->nc", g, grad)
    inside = on.to(x.device)
    if bool(inside.any()):
        off = _edge_line_offsets(x, P, faces)
        if off is not None:
            inside = inside & (off.abs().sum(dim=1) == 0)
    return gx, lam, inside


def _vertex_grad_vjp(points: Tensor, vertices: Tensor, faces: Tensor, G: Tensor) -> Tensor:
    """``sum G * d(grad_x lam) / d vertices``: the mixed second derivatives, by double autograd of
    the torch kernel (``d lam / d x_c`` as the derivative of a vector-Jacobian product), chunk by
    chunk of points. Points on an edge's line outside the edge take the mean beside the line, as in
    :func:`_vertex_vjp` (double autograd of the split form was 27x off there)."""
    off = _edge_line_offsets(points, vertices, faces) if points.shape[-1] == 3 else None
    if off is None:
        return _vertex_grad_vjp_plain(points, vertices, faces, G)
    line = off.abs().sum(dim=1) > 0
    rows, rest = torch.nonzero(line).flatten(), torch.nonzero(~line).flatten()
    xr, Gr, o = points.index_select(0, rows), G.index_select(0, rows), off.index_select(0, rows)
    total = 0.5 * (
        _vertex_grad_vjp_plain(xr + o, vertices, faces, Gr) + _vertex_grad_vjp_plain(xr - o, vertices, faces, Gr)
    )
    if rest.numel():
        total = total + _vertex_grad_vjp_plain(points.index_select(0, rest), vertices, faces, G.index_select(0, rest))
    return total


def _vertex_grad_vjp_plain(points: Tensor, vertices: Tensor, faces: Tensor, G: Tensor) -> Tensor:
    """:func:`_vertex_grad_vjp` without the edge-line rule."""
    create = torch.is_grad_enabled()
    total_gP = torch.zeros_like(vertices)
    for sl in _row_chunks(points, faces):
        with torch.enable_grad():
            P = vertices if create and vertices.requires_grad else vertices.detach().requires_grad_()
            x = points[sl].detach().requires_grad_()
            lam = _torch_coordinates(x, P, faces)
            Z = torch.zeros_like(lam, requires_grad=True)
            (r,) = torch.autograd.grad(lam, x, Z, create_graph=True)
            total = lam.new_zeros(())
            for c in range(x.shape[1]):
                (dl,) = torch.autograd.grad(r[:, c].sum(), Z, create_graph=True)
                total = total + (G[sl][..., c] * dl).sum()
            (gP,) = torch.autograd.grad(total, P, create_graph=create)
        total_gP = total_gP + gP
    return total_gP


def _save_points_and_vertices(ctx, inputs, output) -> None:
    """``setup_context`` of the Functions below: the points and vertices (for backward and for
    forward mode) and the faces."""
    ctx.save_for_backward(inputs[0], inputs[1])
    ctx.save_for_forward(inputs[0], inputs[1])
    ctx.faces = inputs[2]


class MeanValueHessFunction(torch.autograd.Function):
    """``(points (N, D), vertices (V, D), faces) -> d^2 lam / dx^2 (N, V, D, D)``, analytic."""

    generate_vmap_rule = True

    @staticmethod
    def forward(points: Tensor, vertices: Tensor, faces: Tensor) -> Tensor:
        return _derivatives(points, vertices, faces, 2)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        pass

    @staticmethod
    def backward(ctx, grad: Tensor):
        raise RuntimeError(
            "third derivatives of mean value coordinates are not implemented (gradients and Hessians are)"
        )


class MeanValueGradFunction(torch.autograd.Function):
    """``(points (N, D), vertices (V, D), faces) -> d lam / dx (N, V, D)``, analytic; its derivative
    with respect to the points is the analytic Hessian."""

    generate_vmap_rule = True

    @staticmethod
    def forward(points: Tensor, vertices: Tensor, faces: Tensor) -> Tensor:
        return _derivatives(points, vertices, faces, 1)

    setup_context = staticmethod(_save_points_and_vertices)

    @staticmethod
    def backward(ctx, G: Tensor):
        x, P = ctx.saved_tensors
        gx = gP = None
        if ctx.needs_input_grad[0]:
            gx = torch.einsum("nvc,nvcd->nd", G, MeanValueHessFunction.apply(x, P, ctx.faces))
        if ctx.needs_input_grad[1]:  # (sum_v grad_v = 0 whatever x and P: see MeanValueFunction)
            gP = _vertex_grad_vjp(x, P, ctx.faces, G - G.mean(dim=1, keepdim=True))
        return gx, gP, None

    @staticmethod
    def jvp(ctx, dx: Tensor | None, dP: Tensor | None, _df: None) -> Tensor:
        x, P = ctx.saved_tensors
        no_vertex_tangent(dP)
        return torch.einsum("nvcd,nd->nvc", MeanValueHessFunction.apply(x, P, ctx.faces), dx)


class MeanValueFunction(torch.autograd.Function):
    """``(points (N, D), vertices (V, D), faces, chunk_size, backend) -> lam (N, V)``; derivatives
    with respect to the points through the analytic gradients (and Hessians on double backward)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(points: Tensor, vertices: Tensor, faces: Tensor, chunk_size: int, backend: str) -> Tensor:
        with use(backend):  # (the op reads it: no backend in its schema)
            return _coordinates_op(points, vertices, faces, chunk_size)

    setup_context = staticmethod(_save_points_and_vertices)

    @staticmethod
    def backward(ctx, g: Tensor):
        x, P = ctx.saved_tensors
        need_x, need_P = ctx.needs_input_grad[:2]
        # The coordinates sum to 1 whatever the points and vertices: the mean of g over the vertices
        # contributes nothing but the kernels' rounding, which a translated cage's identities
        # multiplied by its distance from the origin (the analytic point gradients have their
        # mean taken out already: derivatives_flat).
        g0 = g - g.mean(dim=-1, keepdim=True)
        if need_P and x.shape[-1] == 3 and not torch.is_grad_enabled():
            # first order (no double backward) with respect to the rest cage: one fused pass
            return *_joint_vjp(x, P, ctx.faces, g0, need_x), None, None, None
        return *_separate_vjp(x, P, ctx.faces, g, g0, need_x, need_P), None, None, None

    @staticmethod
    def jvp(ctx, dx: Tensor | None, dP: Tensor | None, *_: None) -> Tensor:
        x, P = ctx.saved_tensors
        no_vertex_tangent(dP)
        return torch.einsum("nvc,nc->nv", MeanValueGradFunction.apply(x, P, ctx.faces), dx)


def _separate_vjp(
    x: Tensor, P: Tensor, faces: Tensor, g: Tensor, g0: Tensor, need_x: bool, need_P: bool
) -> tuple[Tensor | None, Tensor | None]:
    """:class:`MeanValueFunction`'s backward where it is not one fused pass (the points alone,
    double backward, 2D): the analytic point gradients (``g``, or ``g0 = g`` less its mean over the
    vertices where autograd of the torch kernel stands in) and the vertex products, each
    differentiable when the caller records a graph."""
    gx = _point_grad(x, P, faces, g if _analytic(x) else g0) if need_x else None
    gP = _vertex_vjp(x, P, faces, g0) if need_P else None
    return gx, gP


class MeanValueBatchFunction(torch.autograd.Function):
    """``(points (B, N, 3), vertices (B, V, 3), faces, chunk_size, progress, batch) -> lam (B, N, V)``
    for a batch of 3D triangle cages with one topology, centred float64 CPU tensors, the native
    kernel: the values by one native call for the whole batch (:func:`.dispatch.native_batch`), the
    first-order products with respect to the points and the vertices by one native VJP call
    (:func:`native_vjp_batch`), the points it leaves (not regular) by :func:`_joint_vjp`'s forms
    element by element. Element by element the numbers of :class:`MeanValueFunction`; where the
    rest cage needs no gradient, on double backward and in forward mode (points' tangents), its
    derivatives are taken element by element, by the same formulas."""

    @staticmethod
    def forward(points: Tensor, vertices: Tensor, faces: Tensor, chunk_size, progress, batch) -> Tensor:
        lib = _native.library()
        return native_batch(points.detach(), vertices.detach(), faces, lib, chunk_size, progress, batch)

    setup_context = staticmethod(_save_points_and_vertices)

    @staticmethod
    def backward(ctx, g: Tensor):
        x, P = ctx.saved_tensors
        need_x, need_P = ctx.needs_input_grad[:2]
        faces = ctx.faces
        g0 = g - g.mean(dim=-1, keepdim=True)  # (as MeanValueFunction.backward)
        if not need_P or torch.is_grad_enabled():  # element by element, as MeanValueFunction.backward
            parts = [_separate_vjp(x[b], P[b], faces, g[b], g0[b], need_x, need_P) for b in range(P.shape[0])]
            gx, gP = (torch.stack(t) if t[0] is not None else None for t in zip(*parts, strict=True))
            return gx, gP, None, None, None, None
        lib = _native.library()
        tol = on_cage_tolerances(P)  # (B,): element by element on_cage_tolerance
        gx, gP, reg = native_vjp_batch(lib, x.detach(), P.detach(), faces, g0, tol)
        for b in torch.nonzero((~reg).any(dim=1)).flatten().tolist():
            idx = torch.nonzero(~reg[b]).flatten()
            _irregular_vjp(lib, x[b], P[b], faces, g0[b], idx, float(tol[b]), gx[b], gP[b], need_x)
        return (gx if need_x else None), gP, None, None, None, None

    @staticmethod
    def jvp(ctx, dx: Tensor | None, dP: Tensor | None, *_: None) -> Tensor:
        x, P = ctx.saved_tensors
        no_vertex_tangent(dP)
        if dx is None:
            return torch.zeros(P.shape[0], x.shape[1], P.shape[1], dtype=x.dtype, device=x.device)
        # (element by element, as MeanValueFunction.jvp)
        return torch.stack(
            [
                torch.einsum("nvc,nc->nv", MeanValueGradFunction.apply(x[b], P[b], ctx.faces), dx[b])
                for b in range(P.shape[0])
            ]
        )


def mean_value_function(points: Tensor, cage: Cage, chunk_size: int | None = None, backend: str = "auto") -> Tensor:
    """Mean value coordinates ``(N, V)`` of checked points ``(N, D)``, differentiable with respect to
    the points and ``cage.vertices``: through :class:`MeanValueFunction` (analytic derivatives)
    where the native kernel serves, else by plain autograd of the torch kernel (any device; the
    same values, derivatives to about 1e-12 relative; see docs/accuracy.md). The one place that
    chooses between them."""
    check(MVC, backend)  # (before MeanValueFunction sets it in force: the family's error text)
    faces = cage.triangles if cage.dim == 3 else cage.edges
    if not _analytic(points) and is_functorch_wrapped_tensor(points):
        # torch.func transforms without the native kernel: autograd of the torch kernel throughout
        return _torch_coordinates(points, cage.vertices, faces)
    return MeanValueFunction.apply(points, cage.vertices, faces, chunk_size or 0, backend)
