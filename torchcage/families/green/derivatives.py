r"""Derivatives of Green coordinates with respect to the points: gradients and Hessians.

For points inside a triangle cage they come in closed form from per-face edge sums
(:mod:`.derivatives3d`, whose docstring derives them; the native kernel ``gcd3d.c`` for
float64 CPU points), inside a polygon from per-edge end-point terms
(:func:`._green2d.green2d_derivatives`). Rows the closed form does not serve (points outside the
cage, whose coordinates are continued by the exterior extension; points on the cage; thin faces
seen from a few widths) are differentiated through the torch kernel instead, over those rows
only (``D + 1`` backward passes for the gradients, ``(D + 1)^2`` with the Hessians).
"""

from __future__ import annotations

import torch

from torchcage._core.common import as_inputs, check_points, result_dtype
from torchcage._core.compiled import DerivativesOp
from torchcage.backends import check, resolve, use
from torchcage.cage import Cage
from torchcage.errors import CageError
from torchcage.families.green.api import centred, green_coordinates
from torchcage.families.green.derivatives_flat import GC_DERIVATIVES, autograd_rows, closed_form

__all__ = ["green_derivatives"]


def _autograd_rows(
    x: torch.Tensor, cage: Cage, exterior: str, order: int = 1
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The derivatives of :func:`green_coordinates` (with ``exterior``) at ``x`` by autograd of
    the torch kernel (:func:`._green_derivatives_flat.autograd_rows`)."""
    return autograd_rows(x, order, lambda y: green_coordinates(y, cage, backend="torch", exterior=exterior))


def _eager(
    points: torch.Tensor, cage: Cage, order: int, chunk_size: int | None, extend: bool
) -> tuple[torch.Tensor, ...]:
    return green_derivatives(points, cage, order, chunk_size=chunk_size, exterior="extend" if extend else "none")


def _tails(v: torch.Tensor, t: torch.Tensor, q: torch.Tensor, e: torch.Tensor, order: int) -> list[list[int] | None]:
    V, D = v.shape[-2], v.shape[-1]
    T = t.shape[0] if D == 3 else e.shape[0]
    first = [[V], [T], [V, D], [T, D]]
    return [*first, [V, D, D], [T, D, D]] if order == 2 else first


#: The function as one opaque custom op under ``torch.compile`` (:mod:`torchcage._core.compiled`).
COMPILED = DerivativesOp("green_derivatives", _eager, _tails, GC_DERIVATIVES, promote=True)


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
        (:meth:`~torchcage.GreenCoordinates.jacobian`). ``grad_phi`` and ``hess_phi`` sum to
        zero over the vertices (``sum(phi)`` is constant), exactly.

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
    if exterior not in ("extend", "none"):
        raise ValueError(f"exterior must be 'extend' or 'none', got {exterior!r}")
    if torch.compiler.is_compiling():  # one opaque op: the checks and kernels below are not traceable
        outs = COMPILED(points, cage, order, chunk_size, backend, exterior == "extend")
        return tuple(o if dtype is None else o.to(dtype) for o in outs if o is not None)
    backend = resolve(backend)
    check(GC_DERIVATIVES, backend)
    points, cage = as_inputs(points, cage)
    if cage.is_batched:
        raise CageError("green_derivatives takes one cage; call it per element (cage[b])")
    lead = points.shape[:-1]
    flat = check_points(points, cage)
    compute, out = result_dtype(flat, cage, dtype)
    x = flat.detach().to(compute)
    # the bare coordinates once; inside is where they sum to 1/2 or more, the rule the values'
    # extension uses (families/green/exterior.py), so values and derivatives agree on which points are
    # extended (a separate winding number flipped points within 1e-13 of the size outside a needle's
    # edge); only the points outside are computed again, extended (inside, both are the same)
    with use("auto"):  # (the values' own choice of kernel: `backend` is the derivatives')
        phi, psi = green_coordinates(x, cage, exterior="none")
        inside = phi.sum(dim=1) >= 0.5 if exterior == "extend" else torch.ones(x.shape[0], dtype=torch.bool)
        inside = inside.to(x.device)
        out_rows = torch.nonzero(~inside).flatten()
        if out_rows.numel():
            phi[out_rows], psi[out_rows] = green_coordinates(x.index_select(0, out_rows), cage, exterior="extend")
    V, T, D = phi.shape[1], psi.shape[1], cage.dim
    # (closed_form's outputs are fresh tensors: scaled and centred in place below, sparing a pass
    # of allocation over the Hessians' N x V x 9 entries per step)
    if x.shape[0]:
        xc, cage_c = centred(x, cage, compute)  # (about the cage's centre, as green_coordinates)
        gphi, gpsi, hphi, hpsi, exact = closed_form(xc, cage_c, order, chunk_size, backend)
        exact &= inside
        # (inside, the coordinates are divided by their sum, 1 to rounding, whose derivatives are 0)
        s = phi.sum(dim=1)
        scale = torch.where((s - 1).abs() <= 1e-8, 1.0 / s, 1.0)
        gphi.mul_(scale[:, None, None])
        if order == 2:
            hphi.mul_(scale[:, None, None, None])
    else:  # (no points)
        gphi, gpsi = x.new_zeros(0, V, D), x.new_zeros(0, T, D)
        hphi = x.new_zeros(0, V, D, D) if order == 2 else x.new_empty((0,))
        hpsi = x.new_zeros(0, T, D, D) if order == 2 else x.new_empty((0,))
        exact = torch.zeros(0, dtype=torch.bool, device=x.device)
    rest = torch.nonzero(~exact).flatten()
    if rest.numel():
        gp, gs, hp, hs = _autograd_rows(x.index_select(0, rest), cage.to(compute), exterior, order)
        gphi[rest], gpsi[rest] = gp.to(compute), gs.to(compute)
        if order == 2:
            hphi[rest], hpsi[rest] = hp.to(compute), hs.to(compute)
    # sum(phi) is constant off the cage (the winding number, or 1 with the extension) and 1 on it,
    # so its derivatives vanish: they are made to, exactly. Next to an edge each near face's terms
    # are ~1 / distance and their rounding left eps / distance in the sum (outside a needle's edge,
    # 1e-4 of the largest gradient at 1e-14 of the size), which a cage far from the origin
    # multiplies by its distance in the Jacobian sum_i P_i grad phi_i^T.
    gphi.sub_(gphi.mean(dim=1, keepdim=True))
    if order == 2:
        hphi.sub_(hphi.mean(dim=1, keepdim=True))
    result = (
        phi.to(out).reshape(*lead, V),
        psi.to(out).reshape(*lead, T),
        gphi.to(out).reshape(*lead, V, D),
        gpsi.to(out).reshape(*lead, T, D),
    )
    if order == 1:
        return result
    return (*result, hphi.to(out).reshape(*lead, V, D, D), hpsi.to(out).reshape(*lead, T, D, D))
