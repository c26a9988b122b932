"""Derivatives of the bare Green integrals (no exterior extension) at checked points: the closed
form where it serves (the native kernel for float64 CPU points, else the torch kernel) and, for the
other rows, autograd of the torch kernel. Both the public :func:`.green_derivatives` and the
autograd Functions (:mod:`.ops`) import it; it imports neither."""

from __future__ import annotations

import torch

from torchcage._core.alloc import zeros_output
from torchcage._core.common import chunks, default_chunk, jacobian_rows
from torchcage.backends import Op, select
from torchcage.cage import Cage
from torchcage.families.green import derivatives3d_native as _green3d_derivatives_native
from torchcage.families.green.derivatives3d import green3d_derivatives
from torchcage.families.green.dispatch import green_flat
from torchcage.families.green.kernel2d import green2d_derivatives
from torchcage.families.green.kernel3d import triangle_green_data

__all__ = ["GC_DERIVATIVES", "autograd_rows", "bare_derivatives", "closed_form"]


#: The kernels of Green derivatives: native C for 3D float64 CPU points, else torch.
GC_DERIVATIVES = Op("Green derivatives")


def closed_form(
    x: torch.Tensor, cage: Cage, order: int, chunk_size: int | None = None, backend: str = "auto"
) -> tuple[torch.Tensor, ...]:
    """``(grad_phi (n, V, D), grad_psi (n, T, D), hess_phi (n, V, D, D), hess_psi (n, T, D, D),
    exact (n,))`` of a triangle cage or a polygon at points ``x`` in the compute dtype (Hessians
    empty ``(0,)`` for ``order=1``); rows where ``exact`` is False are zero (see
    :func:`._green3d_derivatives.green3d_derivatives`, :func:`._green2d.green2d_derivatives`)."""
    if cage.dim == 2:  # (torch only: polygons have few edges; "native" is refused as for 3D points it cannot take)
        select(GC_DERIVATIVES, backend, x, graph=False)
        parts = [green2d_derivatives(x[sl], cage, order) for sl in chunks(x.shape[0], chunk_size or 4096)]
        return tuple(torch.cat(col) for col in zip(*parts, strict=True))
    n, V = x.shape[0], cage.num_vertices
    data = triangle_green_data(cage, x.dtype)
    T = data.tri.shape[0]
    gphi = zeros_output(n, V, 3, dtype=x.dtype, device=x.device)
    gpsi = zeros_output(n, T, 3, dtype=x.dtype, device=x.device)
    hphi = zeros_output(n, V, 3, 3, dtype=x.dtype, device=x.device) if order == 2 else x.new_empty((0,))
    hpsi = zeros_output(n, T, 3, 3, dtype=x.dtype, device=x.device) if order == 2 else x.new_empty((0,))
    exact = torch.zeros(n, dtype=torch.bool, device=x.device)
    if n == 0:
        return gphi, gpsi, hphi, hpsi, exact
    lib = select(GC_DERIVATIVES, backend, x, graph=False).lib  # (the kernels record no graph)
    if lib is not None:
        verts = cage.vertices.to(x.dtype)
        exact = _green3d_derivatives_native.derivatives(x, data, verts, lib, order, gphi, gpsi, hphi, hpsi)
        return gphi, gpsi, hphi, hpsi, exact
    for sl in chunks(n, chunk_size or default_chunk(T, (1 << 16) if order == 1 else (1 << 14))):
        gp, gs, hp, hs, ok = green3d_derivatives(x[sl], data, V, order)
        gphi[sl], gpsi[sl], exact[sl] = gp, gs, ok
        if order == 2:
            hphi[sl], hpsi[sl] = hp, hs
    return gphi, gpsi, hphi, hpsi, exact


def autograd_rows(
    x: torch.Tensor, order: int, coordinates
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(grad_phi (m, V, D), grad_psi (m, T, D), hess_phi (m, V, D, D), hess_psi (m, T, D, D))``
    (Hessians empty for ``order=1``) by autograd of ``coordinates(x) -> (phi (m, V), psi (m, T))``,
    a row-wise map (each row depends on its own point only): ``D + 1`` backward passes give every
    gradient (:func:`._common.jacobian_rows`), ``D + 1`` more per gradient column the Hessians.
    """
    xr = x.detach().clone().requires_grad_(True)
    with torch.enable_grad():
        phi, psi = coordinates(xr)
        V = phi.shape[1]
        cols = jacobian_rows(torch.cat([phi, psi], dim=1), xr, create_graph=order == 2)
        hess = x.new_empty((0,))
        if order == 2:
            hess = torch.stack([torch.stack(jacobian_rows(c, xr, False), dim=-1) for c in cols], dim=2).detach()
            hess = 0.5 * (hess + hess.transpose(-1, -2))
    G = torch.stack(cols, dim=-1).detach()
    if order == 1:
        return G[:, :V], G[:, V:], hess, hess
    return G[:, :V], G[:, V:], hess[:, :V], hess[:, V:]


def bare_derivatives(x: torch.Tensor, cage: Cage, order: int) -> tuple[torch.Tensor, ...]:
    """``(grad_phi, grad_psi, hess_phi, hess_psi)`` of the bare integrals at checked points ``x``
    (compute dtype; Hessians empty for ``order=1``): the closed form, autograd of the torch
    kernel for the rows it does not serve (points on the cage, thin faces seen from a few widths)."""
    gphi, gpsi, hphi, hpsi, exact = closed_form(x, cage, order)
    rest = torch.nonzero(~exact).flatten()
    if rest.numel():
        parts = autograd_rows(x.index_select(0, rest), order, lambda y: green_flat(y, cage, backend="torch"))
        for full, part in zip((gphi, gpsi, hphi, hpsi)[: 2 * order], parts, strict=False):
            full[rest] = part.to(full.dtype)
    return gphi, gpsi, hphi, hpsi
