"""The autograd Functions of Green coordinates: values by the fastest kernel; derivatives with
respect to the points by the closed-form gradients (Hessians on double backward), and with
respect to the rest cage's vertices by a native reverse pass or by recomputing chunk by chunk.

``GreenFunction`` computes ``(phi, psi)`` without a graph (the native kernel where it serves). Its
first-order ``backward`` on the CPU runs the native kernel of the hand-derived reverse mode
(:mod:`.vjp3d_native`, ``gc3d_vjp.c``) for the points whose every face takes the closed forms or the
far-field rule; the other points (on or near a face's plane or a corner, beside a thin face), and
every point under double backward, on other devices or with ``backend="torch"``, run the torch
kernel again over chunks of points under autograd, one chunk at a time: the derivatives are exact
(autograd of the same closed forms) and the memory of a backward pass is that of one chunk's
intermediates, not of every point's (plain autograd of the forward kept them all: 1.8 GB for the
FireHydrant model). Double backward works: with ``create_graph`` the chunks' graphs are kept.

For the points alone (the rest cage constant), ``backward`` contracts the closed-form gradients
(:func:`torchcage.functional.green_derivatives`, native where it loads) with the incoming
cotangents instead: ``GreenGradFunction`` computes them, and its own derivative with respect to the
points is the closed-form Hessian (``GreenHessFunction``), so double backward is analytic too.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchcage._core.common import (
    GRADIENT_TABLE_ENTRIES,
    no_vertex_tangent,
    on_cage_tolerance,
    on_cage_tolerances,
    result_dtype,
)
from torchcage.backends import select
from torchcage.cage import Cage
from torchcage.families.green.derivatives_flat import bare_derivatives
from torchcage.families.green.dispatch import GC, batch_integrals, green_flat
from torchcage.families.green.vjp3d_native import native_vjp, native_vjp_batch

__all__ = ["GreenBatchFunction", "GreenFunction", "GreenGradFunction", "GreenHessFunction", "green_function"]

#: Point-face pairs per chunk of the backward pass (about 1 KB of autograd state each).
_PAIRS = 1 << 17


def _cage(vertices: Tensor, faces: Tensor) -> Cage:
    return Cage._from_faces(vertices, faces)


def _derivatives(points: Tensor, vertices: Tensor, faces: Tensor, order: int) -> tuple[Tensor, Tensor]:
    """Closed-form gradients (order 1) or Hessians (order 2) of the bare Green integrals at the
    points, in the points' dtype: ``(d phi (N, V, D...), d psi (N, T, D...))``."""
    cage = _cage(vertices.detach(), faces)
    compute, _ = result_dtype(points, cage, None)
    out = bare_derivatives(points.detach().to(compute), cage.to(compute), order)
    d_phi, d_psi = (out[0], out[1]) if order == 1 else (out[2], out[3])
    # (sum phi is constant: its derivatives vanish exactly, as in green_derivatives)
    d_phi = d_phi - d_phi.mean(dim=1, keepdim=True)
    return d_phi.to(points.dtype), d_psi.to(points.dtype)


class GreenHessFunction(torch.autograd.Function):
    """``(points (N, D), vertices (V, D), faces) -> (H phi (N, V, D, D), H psi (N, T, D, D))``."""

    @staticmethod
    def forward(points: Tensor, vertices: Tensor, faces: Tensor) -> tuple[Tensor, Tensor]:
        return _derivatives(points, vertices, faces, 2)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        pass

    @staticmethod
    def backward(ctx, gh_phi: Tensor, gh_psi: Tensor):
        raise RuntimeError("third derivatives of Green coordinates are not implemented (gradients and Hessians are)")


class GreenGradFunction(torch.autograd.Function):
    """``(points (N, D), vertices (V, D), faces) -> (grad phi (N, V, D), grad psi (N, T, D))``,
    closed form; its derivative with respect to the points is the closed-form Hessian (the rest
    cage is a constant here: :class:`GreenFunction` takes this path only then)."""

    @staticmethod
    def forward(points: Tensor, vertices: Tensor, faces: Tensor) -> tuple[Tensor, Tensor]:
        return _derivatives(points, vertices, faces, 1)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        ctx.save_for_backward(inputs[0], inputs[1])
        ctx.faces = inputs[2]

    @staticmethod
    def backward(ctx, g_phi: Tensor, g_psi: Tensor):
        x, P = ctx.saved_tensors
        if ctx.needs_input_grad[1]:
            raise RuntimeError("GreenGradFunction differentiates with respect to the points only")
        h_phi, h_psi = GreenHessFunction.apply(x, P, ctx.faces)
        gx = torch.einsum("nvc,nvcd->nd", g_phi, h_phi) + torch.einsum("ntc,ntcd->nd", g_psi, h_psi)
        return gx, None, None


class GreenFunction(torch.autograd.Function):
    """``(points (N, D), vertices (V, D), faces, chunk_size, backend) -> (phi (N, V), psi (N, T))``."""

    @staticmethod
    def forward(points: Tensor, vertices: Tensor, faces: Tensor, chunk_size: int, backend: str):
        cage = _cage(vertices, faces)
        compute, out = result_dtype(points, cage, None)
        phi, psi = green_flat(points.to(compute), cage.to(compute), chunk_size or None, False, backend)
        return phi.to(out), psi.to(out)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        ctx.save_for_backward(inputs[0], inputs[1])
        ctx.save_for_forward(inputs[0], inputs[1])
        ctx.faces, ctx.backend = inputs[2], inputs[4]

    @staticmethod
    def backward(ctx, gphi: Tensor | None, gpsi: Tensor | None):
        x, P = ctx.saved_tensors
        gx, gP = _backward(x, P, ctx.faces, gphi, gpsi, *ctx.needs_input_grad[:2], ctx.backend)
        return gx, gP, None, None, None

    @staticmethod
    def jvp(ctx, dx: Tensor | None, dP: Tensor | None, *_: None) -> tuple[Tensor, Tensor]:
        x, P = ctx.saved_tensors
        return _points_jvp(x, P, ctx.faces, dx, dP)


class GreenBatchFunction(torch.autograd.Function):
    """``(points (B, N, 3), vertices (B, V, 3), faces, chunk_size, progress, backend) -> (phi (B, N,
    V), psi (B, N, T))``: the bare integrals of a batch of 3D triangle cages with one topology,
    float64 CPU points and vertices (centred and snapped, as :class:`GreenFunction` takes one), by
    one native call for the values (:func:`.dispatch.batch_integrals`) and one for the first-order
    backward pass (:func:`.vjp3d_native.native_vjp_batch`); the points that call leaves, the points
    alone (the closed-form gradients) and double backward go element by element as
    :class:`GreenFunction`'s backward."""

    @staticmethod
    def forward(points: Tensor, vertices: Tensor, faces: Tensor, chunk_size: int, progress, backend: str):
        lib = _native_library(points, vertices, backend)
        if lib is None:
            raise RuntimeError("GreenBatchFunction takes float64 CPU points where the native kernel loads")
        return batch_integrals(points.detach(), vertices.detach(), faces, lib, chunk_size or None, progress)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        ctx.save_for_backward(inputs[0], inputs[1])
        ctx.save_for_forward(inputs[0], inputs[1])
        ctx.faces, ctx.backend = inputs[2], inputs[5]

    @staticmethod
    def jvp(ctx, dx: Tensor | None, dP: Tensor | None, *_: None) -> tuple[Tensor, Tensor]:
        x, P = ctx.saved_tensors
        no_vertex_tangent(dP)
        parts = [_points_jvp(x[b], P[b], ctx.faces, None if dx is None else dx[b], None) for b in range(P.shape[0])]
        return torch.stack([p for p, _ in parts]), torch.stack([q for _, q in parts])

    @staticmethod
    def backward(ctx, gphi: Tensor | None, gpsi: Tensor | None):
        x, P = ctx.saved_tensors
        need_x, need_P = ctx.needs_input_grad[:2]
        B, faces = x.shape[0], ctx.faces
        points_only = need_x and not need_P and not P.requires_grad
        lib = None if torch.is_grad_enabled() or points_only else _native_library(x, P, ctx.backend)
        if lib is None:  # element by element, as GreenFunction
            parts = [
                _backward(x[b], P[b], faces, None if gphi is None else gphi[b], None if gpsi is None else gpsi[b],
                          need_x, need_P, ctx.backend)
                for b in range(B)
            ]  # fmt: skip
            gx = torch.stack([g for g, _ in parts]) if need_x else None
            gP = torch.stack([g for _, g in parts]) if need_P else None
            return gx, gP, None, None, None, None
        gphi = gphi if gphi is not None else x.new_zeros(B, x.shape[1], P.shape[1])
        gpsi = gpsi if gpsi is not None else x.new_zeros(B, x.shape[1], faces.shape[0])
        gx, gP, reg = native_vjp_batch(lib, x, P, faces, gphi, gpsi, on_cage_tolerances(P.detach()))
        for b in torch.nonzero(~reg.all(dim=1)).flatten().tolist():  # the points the kernel left
            rows = torch.nonzero(~reg[b]).flatten()
            gx_rows, gP_rows = _autograd_backward(
                x[b].index_select(0, rows), P[b], faces, gphi[b].index_select(0, rows),
                gpsi[b].index_select(0, rows), need_x, need_P, False,
            )  # fmt: skip
            if gx_rows is not None:
                gx[b, rows] = gx_rows.to(gx.dtype)
            if gP_rows is not None:
                gP[b] += gP_rows.to(gP.dtype)
        return (gx if need_x else None), (gP if need_P else None), None, None, None, None


def _points_jvp(x: Tensor, P: Tensor, faces: Tensor, dx: Tensor | None, dP: Tensor | None) -> tuple[Tensor, Tensor]:
    """Forward mode of one cage's bare integrals: ``(d phi (N, V), d psi (N, T))`` along the points'
    tangent ``dx`` ``(N, D)`` by the closed-form gradients (tangents of the rest cage's vertices
    raise, as for mean value coordinates)."""
    no_vertex_tangent(dP)
    if dx is None:
        zeros = x.new_zeros
        return zeros(x.shape[0], P.shape[0]), zeros(x.shape[0], faces.shape[0])
    d_phi, d_psi = GreenGradFunction.apply(x, P, faces)
    return torch.einsum("nvc,nc->nv", d_phi, dx.to(d_phi.dtype)), torch.einsum("ntc,nc->nt", d_psi, dx.to(d_psi.dtype))


def _backward(
    x: Tensor,
    P: Tensor,
    faces: Tensor,
    gphi: Tensor | None,
    gpsi: Tensor | None,
    need_x: bool,
    need_P: bool,
    backend: str,
) -> tuple[Tensor | None, Tensor | None]:
    """``(dL/dx (N, D), dL/dP (V, D))`` (None where not needed) of one cage's bare integrals for the
    cotangents ``gphi`` ``(N, V)`` and ``gpsi`` ``(N, T)`` (None: zero): the closed-form gradients
    for the points alone; else the native reverse pass where it serves (first order, CPU); else
    autograd of the torch kernel, chunk by chunk (kept for double backward)."""
    if need_x and not need_P and not P.requires_grad:
        # the points alone: the closed-form gradients (Hessians on double backward), chunk by
        # chunk of points (the gradient tables are (n, V + T, D))
        size = max(64, GRADIENT_TABLE_ENTRIES // max(1, (P.shape[0] + faces.shape[0]) * x.shape[-1]))
        parts = []
        for s in range(0, x.shape[0], size):
            d_phi, d_psi = GreenGradFunction.apply(x[s : s + size], P, faces)
            gx = torch.zeros_like(x[s : s + size])
            if gphi is not None:
                gx = gx + torch.einsum("nv,nvc->nc", gphi[s : s + size].to(d_phi.dtype), d_phi)
            if gpsi is not None:
                gx = gx + torch.einsum("nt,ntc->nc", gpsi[s : s + size].to(d_psi.dtype), d_psi)
            parts.append(gx)
        return (torch.cat(parts) if len(parts) != 1 else parts[0]) if parts else torch.zeros_like(x), None
    gphi = gphi if gphi is not None else torch.zeros(x.shape[0], P.shape[0], dtype=x.dtype, device=x.device)
    gpsi = gpsi if gpsi is not None else torch.zeros(x.shape[0], faces.shape[0], dtype=x.dtype, device=x.device)
    create = torch.is_grad_enabled()
    lib = None if create else _native_library(x, P, backend)
    if lib is not None:
        return _native_backward(lib, x, P, faces, gphi, gpsi, need_x, need_P)
    return _autograd_backward(x, P, faces, gphi, gpsi, need_x, need_P, create)


def _native_library(x: Tensor, P: Tensor, backend: str):
    """The native library when it serves the first-order backward pass of float64-computed 3D
    points on the CPU under ``backend``, else None."""
    if x.shape[-1] != 3 or backend not in ("auto", "native") or x.device.type != "cpu" or P.device.type != "cpu":
        return None
    # (the kernel computes in float64: select sees a float64 stand-in of no rows, not a copy of x)
    choice = select(GC, backend, x.new_empty((0, 3), dtype=torch.float64), graph=False)
    return choice.lib if choice.kind == "native" else None


def _native_backward(lib, x: Tensor, P: Tensor, faces: Tensor, gphi: Tensor, gpsi: Tensor, need_x: bool, need_P: bool):
    """The first-order products by the native kernel (:func:`.vjp3d_native.native_vjp`), the points it
    leaves (on or near the cage, thin faces) by :func:`_autograd_backward`."""
    tol = on_cage_tolerance(_cage(P.detach(), faces))
    gx, gP, reg = native_vjp(lib, x, P, faces, gphi, gpsi, tol)
    rows = torch.nonzero(~reg).flatten()
    if rows.numel():
        gx_rows, gP_rows = _autograd_backward(
            x.index_select(0, rows),
            P,
            faces,
            gphi.index_select(0, rows),
            gpsi.index_select(0, rows),
            need_x,
            need_P,
            False,
        )
        if gx_rows is not None:
            gx = gx.index_copy(0, rows, gx_rows.to(gx.dtype))
        if gP_rows is not None:
            gP = gP + gP_rows.to(gP.dtype)
    return (gx.to(x.dtype) if need_x else None), (gP.to(P.dtype) if need_P else None)


def _autograd_backward(
    x: Tensor, P: Tensor, faces: Tensor, gphi: Tensor, gpsi: Tensor, need_x: bool, need_P: bool, create: bool
) -> tuple[Tensor | None, Tensor | None]:
    """``(dL/dx, dL/dP)`` (None where not needed) by autograd of the torch kernel, recomputed chunk
    by chunk of points (the graph kept with ``create``)."""
    size = max(64, _PAIRS // max(1, faces.shape[0]))
    gx_parts, gP = [], torch.zeros_like(P) if need_P else None
    for s in range(0, x.shape[0], size):
        sl = slice(s, s + size)
        with torch.enable_grad():
            xc = x[sl] if create and x.requires_grad else x[sl].detach().requires_grad_(need_x)
            Pc = P if create and P.requires_grad else P.detach().requires_grad_(need_P)
            cage = _cage(Pc, faces)
            compute, _ = result_dtype(xc, cage, None)
            phi, psi = green_flat(xc.to(compute), cage.to(compute), None, False, "torch")
            wrt = [t for t, need in ((xc, need_x), (Pc, need_P)) if need]
            cot = (gphi[sl].to(compute), gpsi[sl].to(compute))
            grads = torch.autograd.grad((phi, psi), wrt, cot, create_graph=create, allow_unused=True)
        grads = [torch.zeros_like(t) if gr is None else gr.to(t.dtype) for t, gr in zip(wrt, grads, strict=True)]
        if need_x:
            gx_parts.append(grads[0])
        if need_P:
            gP = gP + grads[-1]
    gx = (torch.cat(gx_parts) if gx_parts else torch.zeros_like(x)) if need_x else None
    return gx, gP


def green_function(points: Tensor, cage: Cage, chunk_size: int | None = None, backend: str = "auto"):
    """Green coordinates ``(phi (N, V), psi (N, T))`` of checked points ``(N, D)``, differentiable
    with respect to the points and ``cage.vertices`` through :class:`GreenFunction`."""
    faces = cage.triangles if cage.dim == 3 else cage.edges
    return GreenFunction.apply(points, cage.vertices, faces, chunk_size or 0, backend)
