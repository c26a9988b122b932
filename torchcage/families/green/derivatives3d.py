r"""Torch kernel of the derivatives of 3D Green coordinates with respect to the points, in closed
form (the native kernel, ``backends/native/gcd3d.c``, evaluates the same formulas).

**Gradients.** Differentiating the double layer of a face's hat function and integrating by parts
on the face (the vector potential of a flat panel: :math:`(n \cdot \nabla)\nabla G = -\nabla \times
(n \times \nabla G)` for harmonic ``G``, then Stokes' theorem) gives an edge integral plus the face
terms

.. math::
    \nabla \int_t \Gamma_i \frac{h}{r^3} = \oint_{\partial t} \Gamma_i \frac{(\rho - x) \times d\rho}{r^3}
        + \Omega_t\, g_i - n_t\, (g_i \cdot K_t),\qquad
    \nabla \int_t \frac{1}{r} = K_t + \Omega_t\, n_t .

The hat functions are continuous across the cage's edges, which the two faces of an edge run in
opposite directions: summed over a closed cage the edge integrals cancel, and

.. math::
    \nabla\phi_i = \frac{1}{4\pi}\sum_{t \ni i} (\Omega_t g_i - n_t\, g_i \cdot K_t),\qquad
    \nabla\psi_t = \frac{1}{4\pi}(K_t + \Omega_t n_t),

from quantities the values already need (``K_t = -sum_e m_e I_e``, ``I_e = int_e dl / r``).

**Hessians.** Differentiating once more needs the gradients of ``Omega_t`` and ``K_t``, both edge
sums. With, for the edge ``e`` from ``p_j`` to ``p_k`` (unit direction ``u_e``), ``l = (p - x) .
u_e`` at its ends, ``R = |p - x|`` and ``w_e`` the perpendicular from the point to the edge's line
(``R0 = |w_e|``), the segment integral :math:`\int_e dl / r^3 = c_e = (l_k / R_k - l_j / R_j) / R_0^2`
gives

.. math::
    \nabla I_e = u_e \Big(\frac{1}{R_j} - \frac{1}{R_k}\Big) + c_e\, w_e,\qquad
    \nabla \Omega_t = \sum_{e \in t} c_e\, w_e \times u_e \quad\text{(Biot–Savart)},

so :math:`\partial_b K_a = -\sum_e m_{e,a} \partial_b I_e` and

.. math::
    H\phi_i = \frac{1}{4\pi}\sum_{t \ni i} \big(g_i \nabla\Omega_t^T - n_t\, (g_i^T \nabla K_t)\big),\qquad
    H\psi_t = \frac{1}{4\pi}\big(\nabla K_t + n_t \nabla\Omega_t^T\big).

Where the ends lie on one side of the foot (``l_j l_k > 0``), ``c_e`` is evaluated as
``(l_k^2 - l_j^2) / ((l_k R_j + l_j R_k) R_j R_k)``, which does not cancel (and stays finite) as the
point nears the edge's line; there ``w_e`` vanishes with its term. ``w_e`` is taken from the edge's
nearer end, as the values' kernel does (:func:`._green3d._edge_perpendicular`).

Faces seen from far (the nearest corner ``FAR_RATIO`` longest edges away) take ``Omega_t``, ``K_t``
and their gradients from the quadrature rule of :mod:`.far_triangle`: the edge sums lose
``eps rho^2`` there.
"""

from __future__ import annotations

import math

import torch

from torchcage.families.green.far_triangle import far_triangle_gradients
from torchcage.families.green.kernel3d import TriangleGreenData, _edge_perpendicular, put_far, triangle_integrals

__all__ = ["green3d_derivatives"]


def _edge_terms(a: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(grad_I (..., 3 edges, 3), biot (..., 3 edges, 3))`` of triangles with corners ``a``
    ``(..., 3, 3)`` (minus the point) and unit edge directions ``u`` (edge ``e`` opposite corner
    ``e``, from corner ``e + 1`` to ``e + 2``): the gradients of the edge integrals ``I_e`` and the
    edges' Biot–Savart terms ``c_e w_e x u_e``, which sum to the gradient of the solid angle."""
    aj, ak = a[..., [1, 2, 0], :], a[..., [2, 0, 1], :]
    u = u.expand_as(aj)
    R = a.norm(dim=-1)
    Rj, Rk = R[..., [1, 2, 0]], R[..., [2, 0, 1]]
    lj, lk = (aj * u).sum(-1), (ak * u).sum(-1)
    w = _edge_perpendicular(aj, ak, Rj, Rk, u)
    R0sq = (w * w).sum(-1)
    one_side = (lj >= 0) | (lk <= 0)
    den = torch.where(one_side, (lk * Rj + lj * Rk) * Rj * Rk, R0sq)
    num = torch.where(one_side, (lk - lj) * (lk + lj), lk / Rk - lj / Rj)
    c = num / torch.where(den != 0, den, 1.0)  # (den = 0: a point on the edge, a row callers redo)
    grad_I = u * (1.0 / Rj - 1.0 / Rk)[..., None] + w * c[..., None]
    biot = torch.linalg.cross(w, u, dim=-1) * c[..., None]
    return grad_I, biot


def green3d_derivatives(
    x: torch.Tensor, data: TriangleGreenData, num_vertices: int, order: int = 1
) -> tuple[torch.Tensor, ...]:
    """Gradients (and Hessians) of the bare Green integrals with respect to the points.

    Args:
        x: ``(n, 3)`` points.
        data: the cage constants.
        num_vertices: ``V``.
        order: 1 (gradients) or 2 (gradients and Hessians).

    Returns:
        ``(grad_phi (n, V, 3), grad_psi (n, T, 3), hess_phi (n, V, 3, 3), hess_psi (n, T, 3, 3),
        exact (n,))``, the Hessians empty ``(0,)`` for ``order=1``. ``exact`` is False for rows the
        closed form does not serve (a point on the cage, or a thin face seen from a few widths,
        where ``K`` cancels: callers differentiate the kernel there).

    Examples:
        >>> import torch, torchcage
        >>> from torchcage.families.green.kernel3d import triangle_green_data
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).to(torch.float64).triangulated()
        >>> x = torch.tensor([[0.1, 0.2, -0.3]], dtype=torch.float64)
        >>> gp, gs, hp, hs, ok = green3d_derivatives(x, triangle_green_data(cube, torch.float64), 8, order=2)
        >>> hp.shape, hs.shape, bool(ok.all())
        (torch.Size([1, 8, 3, 3]), torch.Size([1, 12, 3, 3]), True)
    """
    extras: dict = {}
    a = data.p[None] - x[:, None, None, :]  # (n, T, 3 corners, 3)
    geometry = (data.normal[None], data.two_area[None], data.edge_dir[None], data.edge_out[None], data.grad_bary[None])
    phi_face, psi, omega, on_face, _ = triangle_integrals(a, geometry, data.tol, extras=extras)
    _, _, omega, far = put_far(x, a, data, phi_face, psi, omega, extras)
    K, n, g = extras["K"], data.normal[None], data.grad_bary[None]  # (n, T, 3), (1, T, 3), (1, T, 3, 3)
    face = (omega[..., None, None] * g - n[..., None, :] * (g * K[..., None, :]).sum(-1)[..., None]) / (4 * math.pi)
    grad_phi = _scatter_corners(face, data.tri, num_vertices)
    grad_psi = (K + omega[..., None] * n) / (4 * math.pi)
    exact = ~on_face.any(dim=1)
    if extras["thin"] is not None:  # (a thin face seen from far takes the far-field rule: exact)
        exact &= ~(extras["thin"] & ~far if far is not None else extras["thin"]).any(dim=1)
    if order == 1:
        empty = x.new_empty((0,))
        return grad_phi, grad_psi, empty, empty, exact
    live = (data.two_area > 0).to(x.dtype)[None, :, None]  # a degenerate face integrates to nothing
    grad_I, biot = _edge_terms(a, data.edge_dir[None])
    grad_omega = biot.sum(-2) * live  # (n, T, 3)
    grad_K = -(data.edge_out[None, :, :, :, None] * grad_I[..., :, None, :]).sum(-3) * live[..., None]  # (n, T, a, b)
    if far is not None:  # faces seen from far: the quadrature rule (module _far_triangle)
        pt, ft = torch.nonzero(far, as_tuple=True)
        h = (a[pt, ft, 0] * data.normal[ft]).sum(-1)
        go, gk = far_triangle_gradients(x[pt], data.far_nodes[ft], data.far_weights[ft], data.normal[ft], h)
        grad_omega[pt, ft], grad_K[pt, ft] = go, gk
    hess_psi = (grad_K + n[..., :, None] * grad_omega[..., None, :]) / (4 * math.pi)
    hess_psi = 0.5 * (hess_psi + hess_psi.transpose(-1, -2))  # (a face's potential is smooth off the face)
    gK = torch.einsum("tic,ntcb->ntib", data.grad_bary, grad_K)  # g_i^T grad K: (n, T, 3 corners, 3)
    face2 = g[..., :, :, None] * grad_omega[:, :, None, None, :] - n[..., None, :, None] * gK[..., :, None, :]
    hess_phi = _scatter_corners(face2 / (4 * math.pi), data.tri, num_vertices)
    hess_phi = 0.5 * (hess_phi + hess_phi.transpose(-1, -2))  # symmetric once summed over the cage
    return grad_phi, grad_psi, hess_phi, hess_psi, exact


def _scatter_corners(face: torch.Tensor, tri: torch.Tensor, num_vertices: int) -> torch.Tensor:
    """Sum per-face corner terms ``(n, T, 3, ...)`` into per-vertex rows ``(n, V, ...)``."""
    out = face.new_zeros(face.shape[0], num_vertices, *face.shape[3:])
    for i in range(3):
        out.index_add_(1, tri[:, i], face[:, :, i])
    return out
