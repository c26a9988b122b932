r"""Green integrals of triangles seen from far away, by quadrature.

Far from a face (its nearest corner ``FAR_RATIO`` longest edges away or more) the closed forms of
:mod:`.kernel3d` lose digits: their terms (``alpha_i Omega`` against ``h g_i . K``, the edge
integrals' ``asinh`` differences) are ``rho = r / edge`` times larger than the integrals they sum
to, and the rounding grows like ``eps rho^2`` (5e-6 of a face's terms at ``rho = 1e4``). There the
integrands are smooth on the face, and a Gauss rule on the collapsed square (order
``FAR_ORDER``: error about ``(1 / 4 rho)^(2 FAR_ORDER)``, below 4e-15 from ``rho = 10``) gives
every term to a few ``eps``, with nodes placed from the face's corners and the point apart (a
node's offset from the point is then exact to ``eps r``, where ``p - x`` first would blur the
face's shape by ``eps rho``).

With ``y`` a node, ``a = y - x``, ``r = |a|``, ``h = a . n`` (the same for every node) and
``Gamma_i`` the hat functions (the nodes' barycentric coordinates):

.. math::
    4\pi\,\phi_{t,i} = \int_t \Gamma_i \frac{h}{r^3},\quad 4\pi\,\psi_t = \int_t \frac{1}{r},\quad
    \Omega_t = \int_t \frac{h}{r^3},\quad K_t = \int_t \frac{a - h n}{r^3},

and their gradients with respect to the point (for the Hessians of :mod:`.derivatives3d`):

.. math::
    \nabla\Omega_t = \int_t \Big(\frac{3 h\, a}{r^5} - \frac{n}{r^3}\Big),\qquad
    \partial_b K_a = \int_t \Big(\frac{n_a n_b - \delta_{ab}}{r^3} + \frac{3 (a - h n)_a\, a_b}{r^5}\Big).

The native kernels (``backends/native/gc3d.c``, ``gcd3d.c``) and the Triton kernel use the same rule and
threshold.
"""

from __future__ import annotations

import math

import torch

from torchcage._core.common import collapsed_gauss

__all__ = ["FAR_ORDER", "FAR_RATIO", "far_nodes", "far_pairs", "far_triangle_gradients", "far_triangle_integrals"]

#: Pairs whose nearest corner is at least this many times the face's longest edge away take the rule.
FAR_RATIO = 10.0
#: Gauss–Legendre order per direction of the collapsed square (``FAR_ORDER^2`` nodes).
FAR_ORDER = 5


def far_nodes(p: torch.Tensor, two_area: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The rule's nodes on faces with corners ``p`` ``(*B, T, 3, 3)`` and twice their areas
    ``(*B, T)``.

    Returns:
        ``(nodes (*B, T, Q, 3), weights (*B, T, Q), bary (Q, 3))``: node positions, their weights
        (area included) and barycentric coordinates.
    """
    bary, qw = collapsed_gauss(FAR_ORDER, p.dtype, p.device)
    nodes = torch.einsum("qi,...tic->...tqc", bary, p)
    return nodes, two_area[..., None] * qw, bary


def far_pairs(R: torch.Tensor, longest: torch.Tensor) -> torch.Tensor:
    """Which point–face pairs take the rule: ``R`` ``(..., 3)`` the corners' distances to the
    point, ``longest`` (broadcastable to ``R.shape[:-1]``) the faces' longest edges (degenerate
    faces, ``0``, never do). Returns bools (the native kernels decide alike, on ``min R^2``)."""
    rmin = R.amin(dim=-1)
    return (rmin * rmin >= (FAR_RATIO * longest) ** 2) & (longest > 0)


def far_triangle_integrals(
    x: torch.Tensor,
    nodes: torch.Tensor,
    weights: torch.Tensor,
    bary: torch.Tensor,
    normal: torch.Tensor,
    h: torch.Tensor,
) -> tuple[torch.Tensor, ...]:
    """The integrals of ``k`` point–face pairs by the rule.

    Args:
        x: ``(k, 3)`` points; nodes: ``(k, Q, 3)``; weights: ``(k, Q)``; bary: ``(Q, 3)``;
        normal: ``(k, 3)`` unit normals; h: ``(k,)`` signed distances (positive on the inner side).

    Returns:
        ``(phi_face (k, 3), psi (k,), omega (k,), K (k, 3))`` as the closed forms of
        :func:`._green3d.triangle_integrals` (``phi_face`` and ``psi`` with their ``1 / 4 pi``).

    Examples:
        >>> import torch
        >>> p = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]], dtype=torch.float64)
        >>> nodes, w, bary = far_nodes(p, torch.ones(1, dtype=torch.float64))
        >>> x = torch.tensor([[0.2, 0.3, -50.0]], dtype=torch.float64)
        >>> n = torch.tensor([[0.0, 0, 1]], dtype=torch.float64)
        >>> phi, psi, omega, K = far_triangle_integrals(x, nodes, w, bary, n, torch.tensor([50.0], dtype=torch.float64))
        >>> bool(torch.isclose(omega, torch.tensor(0.5 / 2500, dtype=torch.float64), rtol=1e-3))
        True
    """
    a = nodes - x[:, None, :]  # (k, Q, 3)
    inv_r = torch.rsqrt((a * a).sum(-1))
    w1 = weights * inv_r
    w3 = w1 * inv_r * inv_r
    omega = h * w3.sum(-1)
    phi_face = (h[:, None] * (w3 @ bary)) / (4 * math.pi)
    psi = w1.sum(-1) / (4 * math.pi)
    K = torch.einsum("kq,kqc->kc", w3, a) - omega[:, None] * normal
    return phi_face, psi, omega, K


def far_triangle_gradients(
    x: torch.Tensor, nodes: torch.Tensor, weights: torch.Tensor, normal: torch.Tensor, h: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(grad_omega (k, 3), grad_K (k, 3, 3))`` (``grad_K[:, a, b] = d K_a / d x_b``) of ``k``
    point–face pairs by the rule (arguments as :func:`far_triangle_integrals`)."""
    a = nodes - x[:, None, :]
    inv_r = torch.rsqrt((a * a).sum(-1))
    w3 = weights * inv_r * inv_r * inv_r  # (the area first: inv_r^3 alone underflows float32 far away)
    w5 = w3 * inv_r * inv_r
    s3, a5 = w3.sum(-1), torch.einsum("kq,kqc->kc", w5, a)  # int 1/r^3, int a / r^5
    aa5 = torch.einsum("kq,kqa,kqb->kab", w5, a, a)  # int a a^T / r^5
    grad_omega = 3.0 * h[:, None] * a5 - s3[:, None] * normal
    nn = normal[:, :, None] * normal[:, None, :]
    eye = torch.eye(3, dtype=x.dtype, device=x.device)
    grad_K = (nn - eye) * s3[:, None, None] + 3.0 * (aa5 - normal[:, :, None] * (h[:, None] * a5)[:, None, :])
    return grad_omega, grad_K
