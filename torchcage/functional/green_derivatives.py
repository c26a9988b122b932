r"""Derivatives of Green coordinates with respect to the points (first order).

For points inside a triangle cage the gradients come in closed form from the quantities the
values need (:func:`._green3d.green3d_gradients`: per face, the solid angle, the in-plane moment
``K`` and the hat functions' gradients). Rows it does not serve (points outside the cage, whose
coordinates are continued by the exterior extension; points on the cage; thin faces seen from a
few widths; 2D polygons) are differentiated through the torch kernel instead, one backward pass
per coordinate over those rows only.
"""

from __future__ import annotations

import torch

from ..cage import Cage
from ..errors import CageError
from ..geometry import inside_cage
from ._common import as_inputs, check_points, chunks, default_chunk, result_dtype
from ._green3d import green3d_gradients, triangle_green_data
from .green import green_coordinates

__all__ = ["green_derivatives"]


def _autograd_rows(x: torch.Tensor, cage: Cage, exterior: str) -> tuple[torch.Tensor, torch.Tensor]:
    """``(grad_phi (m, V, D), grad_psi (m, T, D))`` by reverse mode through the torch kernel: each
    coordinate of a row depends on that row's point only, so one backward pass of a column's sum
    gives that column's gradient at every row."""
    xr = x.detach().clone().requires_grad_(True)
    with torch.enable_grad():
        phi, psi = green_coordinates(xr, cage, backend="torch", exterior=exterior)
        cols = [*phi.unbind(1), *psi.unbind(1)]
        grads = [torch.autograd.grad(c.sum(), xr, retain_graph=True)[0] for c in cols]
    G = torch.stack(grads, dim=1) if grads else x.new_zeros(x.shape[0], 0, x.shape[1])
    return G[:, : phi.shape[1]], G[:, phi.shape[1] :]


def green_derivatives(
    points: torch.Tensor,
    cage: Cage,
    order: int = 1,
    *,
    chunk_size: int | None = None,
    dtype: torch.dtype | None = None,
    exterior: str = "extend",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Green coordinates and their gradients with respect to the points.

    Args:
        points: ``(*, D)`` query points.
        cage: a closed triangle cage or polygon (as :func:`green_coordinates`).
        order: 1 (gradients). Hessians (``order=2``) are not implemented yet.
        chunk_size: points per chunk of the closed form.
        dtype: dtype of the results (computed in float64).
        exterior: as :func:`green_coordinates` (outside points: the gradient of the extension).

    Returns:
        ``(phi (*, V), psi (*, T), grad_phi (*, V, D), grad_psi (*, T, D))``. With a deformed cage
        ``P`` and the stretched normals ``s_t n_t`` of :class:`~torchcage.GreenCoordinates`, the
        deformation's Jacobian at a point is ``sum_i P_i grad_phi_i^T + sum_t s_t n_t grad_psi_t^T``.

    Raises:
        NotImplementedError: ``order=2``.
        CageError: a quad cage.

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
    """
    if order == 2:
        raise NotImplementedError(
            "Hessians of Green coordinates are not implemented yet; use order=1, or differentiate the gradients "
            "with torch.autograd (green_coordinates is twice differentiable through the torch kernel)"
        )
    if order != 1:
        raise ValueError(f"order must be 1, got {order!r}")
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
    exact = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
    if D == 3 and x.shape[0]:
        data = triangle_green_data(cage, compute)
        inside = inside_cage(x, cage.to(compute)) if exterior == "extend" else torch.ones_like(exact)
        for sl in chunks(x.shape[0], chunk_size or default_chunk(T, 1 << 16)):
            gp, gs, ok = green3d_gradients(x[sl], data, V)
            gphi[sl], gpsi[sl], exact[sl] = gp, gs, ok & inside[sl]
        # (inside, the coordinates are divided by their sum, 1 to rounding, whose gradient is 0)
        s = phi.sum(dim=1)
        scale = torch.where((s - 1).abs() <= 1e-8, 1.0 / s, 1.0)
        gphi = gphi * scale[:, None, None]
    rest = torch.nonzero(~exact).flatten()
    if rest.numel():
        gp, gs = _autograd_rows(x.index_select(0, rest), cage.to(compute), exterior)
        gphi[rest], gpsi[rest] = gp.to(compute), gs.to(compute)
    return (
        phi.to(out).reshape(*lead, V),
        psi.to(out).reshape(*lead, T),
        gphi.to(out).reshape(*lead, V, D),
        gpsi.to(out).reshape(*lead, T, D),
    )
