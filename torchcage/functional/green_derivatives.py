r"""Derivatives of Green coordinates with respect to the points: gradients and Hessians.

For points inside a triangle cage they come in closed form from per-face edge sums
(:mod:`._green3d_derivatives`, whose docstring derives them; the native kernel ``gcd3d.c`` for
float64 CPU points). Rows the closed form does not serve (points outside the cage, whose
coordinates are continued by the exterior extension; points on the cage; thin faces seen from a
few widths; 2D polygons) are differentiated through the torch kernel instead, over those rows
only (``D + 1`` backward passes for the gradients, ``(D + 1)^2`` with the Hessians).
"""

from __future__ import annotations

import torch

from .. import _native
from ..cage import Cage
from ..errors import CageError
from ..geometry import inside_cage
from . import _green3d_derivatives_native
from ._common import as_inputs, check_points, chunks, default_chunk, jacobian_rows, result_dtype
from ._green3d import triangle_green_data
from ._green3d_derivatives import green3d_derivatives
from .green import green_coordinates

__all__ = ["green_derivatives"]


def _autograd_rows(
    x: torch.Tensor, cage: Cage, exterior: str, order: int = 1
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(grad_phi (m, V, D), grad_psi (m, T, D), hess_phi (m, V, D, D), hess_psi (m, T, D, D))``
    (Hessians empty for ``order=1``) by autograd of the torch kernel. Each coordinate of a row
    depends on that row's point only, so ``D + 1`` backward passes give every gradient
    (:func:`._common.jacobian_rows`), and ``D + 1`` more per gradient column the Hessians."""
    xr = x.detach().clone().requires_grad_(True)
    V = cage.num_vertices
    with torch.enable_grad():
        phi, psi = green_coordinates(xr, cage, backend="torch", exterior=exterior)
        y = torch.cat([phi, psi], dim=1)
        cols = jacobian_rows(y, xr, create_graph=order == 2)
        hess = x.new_empty((0,))
        if order == 2:
            hess = torch.stack([torch.stack(jacobian_rows(c, xr, False), dim=-1) for c in cols], dim=2).detach()
            hess = 0.5 * (hess + hess.transpose(-1, -2))
    G = torch.stack(cols, dim=-1).detach()
    if order == 1:
        return G[:, :V], G[:, V:], hess, hess
    return G[:, :V], G[:, V:], hess[:, :V], hess[:, V:]


def green_derivatives(
    points: torch.Tensor,
    cage: Cage,
    order: int = 1,
    *,
    chunk_size: int | None = None,
    dtype: torch.dtype | None = None,
    exterior: str = "extend",
    backend: str = "auto",
) -> tuple[torch.Tensor, ...]:
    """Green coordinates and their gradients (and Hessians) with respect to the points.

    Args:
        points: ``(*, D)`` query points.
        cage: a closed triangle cage or polygon (as :func:`green_coordinates`).
        order: 1 (gradients) or 2 (gradients and Hessians).
        chunk_size: points per chunk of the closed form.
        dtype: dtype of the results (computed in float64).
        exterior: as :func:`green_coordinates` (outside points: the derivatives of the extension).
        backend: ``"auto"`` (the native kernel for CPU points where it loads, else torch),
            ``"native"`` or ``"torch"``.

    Returns:
        ``(phi (*, V), psi (*, T), grad_phi (*, V, D), grad_psi (*, T, D))`` and, for ``order=2``,
        also ``hess_phi (*, V, D, D)`` and ``hess_psi (*, T, D, D)``. With a deformed cage ``P``
        and the stretched normals ``s_t n_t`` of :class:`~torchcage.GreenCoordinates`, the
        deformation's Jacobian at a point is ``sum_i P_i grad_phi_i^T + sum_t s_t n_t grad_psi_t^T``
        (:meth:`~torchcage.GreenCoordinates.jacobian`).

    Raises:
        CageError: a quad cage (use :func:`quad_green_coordinates` under autograd).

    Examples:
        >>> import torch, torchcage
        >>> from torchcage import functional as F
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> x = torch.tensor([[0.1, 0.2, -0.3]], dtype=torch.float64)
        >>> phi, psi, gphi, gpsi = F.green_derivatives(x, cube)
        >>> n = cube.triangle_normals()
        >>> J = torch.einsum("nvi,vj->nji", gphi, cube.vertices) + torch.einsum("nti,tj->nji", gpsi, n)
        >>> torch.allclose(J[0], torch.eye(3, dtype=torch.float64))  # the rest pose: the identity
        True
        >>> *_, hphi, hpsi = F.green_derivatives(x, cube, order=2)
        >>> H = torch.einsum("nvab,vj->njab", hphi, cube.vertices) + torch.einsum("ntab,tj->njab", hpsi, n)
        >>> bool(H.abs().max() < 1e-10)  # an affine map has no second derivatives
        True
    """
    if order not in (1, 2):
        raise ValueError(f"order must be 1 or 2, got {order!r}")
    if backend not in ("auto", "native", "torch"):
        raise ValueError(f"backend must be 'auto', 'native' or 'torch', got {backend!r}")
    points, cage = as_inputs(points, cage)
    if cage.is_batched:
        raise CageError("green_derivatives takes one cage; call it per element (cage[b])")
    lead = points.shape[:-1]
    flat = check_points(points, cage)
    compute, out = result_dtype(flat, cage, dtype)
    x = flat.detach().to(compute)
    phi, psi = green_coordinates(x, cage, exterior=exterior)
    V, T, D = phi.shape[1], psi.shape[1], cage.dim
    gphi = torch.zeros(x.shape[0], V, D, dtype=compute, device=x.device)
    gpsi = torch.zeros(x.shape[0], T, D, dtype=compute, device=x.device)
    hshape = (x.shape[0], D, D) if order == 2 else None
    hphi = torch.zeros(hshape[0], V, D, D, dtype=compute, device=x.device) if hshape else x.new_empty((0,))
    hpsi = torch.zeros(hshape[0], T, D, D, dtype=compute, device=x.device) if hshape else x.new_empty((0,))
    exact = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
    if D == 3 and x.shape[0]:
        data = triangle_green_data(cage, compute)
        inside = inside_cage(x, cage.to(compute)) if exterior == "extend" else torch.ones_like(exact)
        lib = _library(backend, x) if compute == torch.float64 else None
        if lib is not None:
            exact = _green3d_derivatives_native.derivatives(x, data, cage.vertices.to(compute), lib, order, gphi, gpsi, hphi, hpsi)
        else:
            for sl in chunks(x.shape[0], chunk_size or default_chunk(T, (1 << 16) if order == 1 else (1 << 14))):
                gp, gs, hp, hs, ok = green3d_derivatives(x[sl], data, V, order)
                gphi[sl], gpsi[sl], exact[sl] = gp, gs, ok
                if order == 2:
                    hphi[sl], hpsi[sl] = hp, hs
        exact &= inside
        # (inside, the coordinates are divided by their sum, 1 to rounding, whose derivatives are 0)
        s = phi.sum(dim=1)
        scale = torch.where((s - 1).abs() <= 1e-8, 1.0 / s, 1.0)
        gphi = gphi * scale[:, None, None]
        if order == 2:
            hphi = hphi * scale[:, None, None, None]
    rest = torch.nonzero(~exact).flatten()
    if rest.numel():
        gp, gs, hp, hs = _autograd_rows(x.index_select(0, rest), cage.to(compute), exterior, order)
        gphi[rest], gpsi[rest] = gp.to(compute), gs.to(compute)
        if order == 2:
            hphi[rest], hpsi[rest] = hp.to(compute), hs.to(compute)
    result = (
        phi.to(out).reshape(*lead, V),
        psi.to(out).reshape(*lead, T),
        gphi.to(out).reshape(*lead, V, D),
        gpsi.to(out).reshape(*lead, T, D),
    )
    if order == 1:
        return result
    return (*result, hphi.to(out).reshape(*lead, V, D, D), hpsi.to(out).reshape(*lead, T, D, D))


def _library(backend: str, x: torch.Tensor) -> object | None:
    """The native library when it serves this call (CPU points, float64, a loadable library)."""
    if backend == "torch" or (backend == "auto" and x.device.type != "cpu"):
        return None
    lib = _native.library()
    if lib is None and backend == "native":
        raise RuntimeError(
            "the native kernel of Green derivatives is unavailable "
            f"({_native.failure_reason()}); use backend='torch' (or 'auto', which falls back to it)"
        )
    return lib
