"""Glue to the native CPU kernel of the vector-Jacobian product of 3D Green coordinates
(``torchcage/backends/native/gc3d_vjp.c``, whose comment gives the formulas): the products with
respect to the points and the rest cage for the points whose every face takes the closed forms or
the far-field rule; the caller computes the others."""

from __future__ import annotations

import ctypes

import torch

from torchcage._core.thin_triangle import THIN_ASPECT
from torchcage.backends import native as _native
from torchcage.families.green.far_triangle import FAR_RATIO, far_nodes
from torchcage.families.green.kernel3d import (
    PERPENDICULAR_PLANE_RATIO,
    PERPENDICULAR_VERTEX_RATIO,
    triangle_green_geometry,
)

__all__ = ["native_vjp", "native_vjp_batch"]

#: The kernel's face-constant cotangents, columns of its ``GF`` output: name -> (start, shape).
_FACE_COLUMNS = {"normal": (0, (3,)), "edge_dir": (3, (3, 3)), "edge_out": (12, (3, 3)), "grad_bary": (21, (3, 3)),
                 "gnorm": (30, (3,))}  # fmt: skip


def native_vjp(
    lib: ctypes.CDLL,
    x: torch.Tensor,
    vertices: torch.Tensor,
    tri: torch.Tensor,
    gphi: torch.Tensor,
    gpsi: torch.Tensor,
    tol: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``dL/dx`` and ``dL/dP`` of Green coordinates ``(phi, psi)`` for the cotangents ``gphi``
    ``(n, V)`` and ``gpsi`` ``(n, T)``: float64 CPU points ``x`` ``(n, 3)`` and cage ``vertices``
    ``(V, 3)`` (centred, as the forward pass took them), faces ``tri`` ``(T, 3)``, ``tol`` the
    on-cage tolerance.

    Returns:
        ``(gx (n, 3), gP (V, 3), regular (n,) bool)``: ``gx`` is zero and ``gP`` holds nothing of
        the points that are not regular (on or near a face's plane or a corner, or seen by a thin
        or degenerate face): the caller differentiates those by autograd of the torch kernel.

    Examples:
        >>> import torch, torchcage
        >>> from torchcage.backends import native
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> x = torch.tensor([[0.1, 0.2, -0.3]], dtype=torch.float64)
        >>> gphi, gpsi = torch.ones(1, 8, dtype=torch.float64), torch.zeros(1, 12, dtype=torch.float64)
        >>> lib = native.library()  # (None where no native kernel loads: then nothing to show)
        >>> if lib is not None:
        ...     gx, gP, reg = native_vjp(lib, x, cube.vertices, cube.triangles, gphi, gpsi, 1e-12)
        ...     assert bool(reg[0]) and float(gx.abs().max()) < 1e-12  # sum phi = 1 inside: no derivative
    """
    tols = torch.tensor([float(tol)], dtype=torch.float64)
    gx, gP, reg = native_vjp_batch(lib, x[None], vertices[None], tri, gphi[None], gpsi[None], tols)
    return gx[0], gP[0], reg[0]


def native_vjp_batch(
    lib: ctypes.CDLL,
    x: torch.Tensor,
    vertices: torch.Tensor,
    tri: torch.Tensor,
    gphi: torch.Tensor,
    gpsi: torch.Tensor,
    tol: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`native_vjp` of B cages with one topology in one call: ``x`` ``(B, n, 3)``,
    ``vertices`` ``(B, V, 3)``, ``gphi`` ``(B, n, V)``, ``gpsi`` ``(B, n, T)``, ``tol`` ``(B,)`` ->
    ``(gx (B, n, 3), gP (B, V, 3), regular (B, n))``, element by element :func:`native_vjp`'s."""
    B, n, V, T = vertices.shape[0], x.shape[1], vertices.shape[1], tri.shape[0]
    f64 = torch.float64
    with torch.enable_grad():
        P = vertices.detach().to(f64).requires_grad_()
        p = P[:, tri]  # (B, T, 3, 3)
        normal, two_area, edge_dir, edge_out, grad_bary = triangle_green_geometry(p)
        gnorm = grad_bary.norm(dim=-1)
        nodes, weights, bary = far_nodes(p, two_area)
    consts = {"normal": normal, "edge_dir": edge_dir, "edge_out": edge_out, "grad_bary": grad_bary, "gnorm": gnorm}
    detached = {k: v.detach().contiguous() for k, v in consts.items()}
    pd = p.detach()
    longest = (pd.roll(-1, dims=-2) - pd).norm(dim=-1).amax(dim=-1)
    thin = (grad_bary.detach().square().sum(-1).amax(-1) * two_area.detach() > THIN_ASPECT).to(torch.uint8)
    Q = bary.shape[0]
    gx, gA, gF = (
        torch.empty((B, n, 3), dtype=f64),
        torch.empty((B, V, 3), dtype=f64),
        torch.empty((B, T, 33), dtype=f64),
    )
    gN, gW = torch.empty((B, T, Q, 3), dtype=f64), torch.empty((B, T, Q), dtype=f64)
    reg = torch.empty((B, n), dtype=torch.uint8)
    _native.call(
        lib,
        "tc_gc3d_vjp_batch",
        B=B,
        P=P.detach().contiguous(),
        V=V,
        tri=tri.to(torch.int32).contiguous(),
        T=T,
        nrm=detached["normal"],
        edir=detached["edge_dir"],
        eout=detached["edge_out"],
        gbary=detached["grad_bary"],
        gnorm=detached["gnorm"],
        two_area=two_area.detach().contiguous(),
        longest=longest.contiguous(),
        thin=thin.contiguous(),
        far_nodes=nodes.detach().contiguous(),
        far_w=weights.detach().contiguous(),
        far_bary=bary.contiguous(),
        Q=Q,
        far_c=FAR_RATIO,
        near_c=PERPENDICULAR_PLANE_RATIO,
        vertex_c=PERPENDICULAR_VERTEX_RATIO,
        tol=tol.to(f64).contiguous(),
        X=x.detach().to(f64).contiguous(),
        n=n,
        GPHI=gphi.detach().to(f64).contiguous(),
        GPSI=gpsi.detach().to(f64).contiguous(),
        GX=gx,
        GA=gA,
        GF=gF,
        GN=gN,
        GW=gW,
        reg=reg,
    )
    mb = 8 * ((3 * V + 33 * T) * 5 + 4 * T * Q + 4 * T + 42 * 4) / 2**20  # (gc3d_vjp.c: scratch_size)
    _native.check_workspace(gx, "Green backward", f"about {mb:.1f} MB per thread")
    # The face constants' cotangents to the vertices: autograd of the few operations over B T faces.
    outs = [*consts.values(), nodes, weights]
    cots = [gF[..., s : s + (3 if len(shape) == 1 else 9)].reshape(B, T, *shape) for s, shape in _FACE_COLUMNS.values()]
    (gP,) = torch.autograd.grad(outs, P, [*cots, gN, gW])
    return gx, gA + gP, reg.bool()
