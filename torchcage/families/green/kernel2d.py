r"""Torch kernel of 2D Green coordinates (Lipman, Levin, Cohen-Or 2008) for closed polygons.

Groundwork for conformal image warps: not yet exported (the public ``green_coordinates`` will
cover triangle cages too). For a point :math:`\eta` inside a counter-clockwise polygon, Green's
third identity applied to the coordinate functions gives

.. math::
    \eta = \sum_i \phi_i(\eta)\, v_i + \sum_j \psi_j(\eta)\, n_j,\qquad
    \phi_i = \int \Gamma_i\, \partial_n G\, d\sigma,\quad \psi_j = -\int_{e_j} G\, d\sigma,

with :math:`G(\xi, \eta) = \log\|\xi - \eta\| / 2\pi`, :math:`\Gamma_i` the hat functions on the
edges and :math:`n_j` the outward unit normals. For the edge ``j`` from ``v_j`` to ``v_{j+1}``, with
``a = v_{j+1} - v_j``, ``b = v_j - eta``, ``Q = a.a``, ``S = b.b``, ``R = 2 a.b``,
``P(t) = Q t^2 + R t + S``, ``L0 = log S``, ``L1 = log(Q + R + S)``, ``c |a| = b x a`` (signed,
positive on the inner side) and :math:`\theta` the angle the edge subtends at :math:`\eta`,
the integrals are

.. math::
    \int_0^1 \log P = L_1 + \tfrac{R}{2Q}(L_1 - L_0) - 2 + \tfrac{2 |a \times b|}{Q}\theta,\quad
    \int_0^1 \tfrac{dt}{P} = \tfrac{\theta}{|a \times b|},\quad
    \int_0^1 \tfrac{t\,dt}{P} = \tfrac{L_1 - L_0}{2Q} - \tfrac{R\,\theta}{2Q\,|a\times b|}.

Written with :math:`\theta = \mathrm{atan2}(2|a \times b|, 2\, b \cdot (b + a))` and the products
``c |a| / |a x b| = ±1``, nothing cancels near an edge's line. Points on the polygon get the limit
from inside: edges through the point contribute their principal value and the hat values enter with
the jump weight ``1 - omega / 2 pi`` (``omega`` the angle the rest of the polygon subtends).
Outside the polygon the identity gives 0, not :math:`\eta`: Green coordinates are defined inside
(their extension outside is not implemented).
"""

from __future__ import annotations

import math

import torch

from torchcage._core.common import on_cage_tolerance, safe_atan2
from torchcage.cage import Cage
from torchcage.errors import CageError


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``(a * b).sum(-1)`` over a last axis of 2, as the sum of the two products."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]


def green2d_coordinates(points: torch.Tensor, cage: Cage) -> tuple[torch.Tensor, torch.Tensor]:
    """2D Green coordinates of points inside a closed polygon.

    Args:
        points: ``(n, 2)`` points (inside the cage for the identity to hold).
        cage: a 2D cage (counter-clockwise after validation).

    Returns:
        ``(phi (n, V), psi (n, E))`` in the points' dtype: ``phi @ V + psi @ normals = points``
        inside, with ``normals = cage.edge_normals()`` (outward, unit).

    Examples:
        >>> import torch, torchcage
        >>> from torchcage.families.green.kernel2d import green2d_coordinates
        >>> cage = torchcage.Cage([[0.0, 0], [2, 0], [2, 1], [0, 1]])
        >>> x = torch.tensor([[0.5, 0.25], [1.5, 0.5]], dtype=torch.float64)
        >>> phi, psi = green2d_coordinates(x, cage)
        >>> torch.allclose(phi @ cage.vertices + psi @ cage.edge_normals(), x)
        True
    """
    if cage.dim != 2:
        raise CageError("green2d_coordinates needs a 2D cage")
    tol = torch.tensor([on_cage_tolerance(cage)], dtype=points.dtype, device=points.device)  # (MPS: no float64)
    phi, psi = green2d_batch(points[None], cage.vertices[None], cage.edges, tol)
    return phi[0], psi[0]


def green2d_batch(
    points: torch.Tensor, vertices: torch.Tensor, edges: torch.Tensor, tol: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`green2d_coordinates` of a batch of ``B`` polygons with one topology, by one set of
    tensor operations (element by element the numbers of the call on one polygon to rounding: a
    vectorised ``log`` or ``atan2`` may round its tail lanes apart; differentiable).

    Args:
        points: ``(B, n, 2)`` points, one set per polygon, or ``(1, n, 2)`` shared.
        vertices: ``(B, V, 2)`` the polygons' vertices (cast to the points' dtype).
        edges: ``(E, 2)`` the shared directed edges (counter-clockwise polygons).
        tol: ``(B,)`` absolute on-polygon tolerances (:func:`on_cage_tolerance` of each), cast to
            the points' dtype and device.

    Returns:
        ``(phi (B, n, V), psi (B, n, E))`` in the points' dtype.

    Examples:
        >>> import torch
        >>> V = torch.tensor([[0.0, 0], [2, 0], [2, 1], [0, 1]], dtype=torch.float64)
        >>> V = torch.stack([V, 2 * V])  # (2, 4, 2)
        >>> E = torch.tensor([[0, 1], [1, 2], [2, 3], [3, 0]])
        >>> phi, psi = green2d_batch(torch.tensor([[[0.5, 0.25]]], dtype=torch.float64), V, E, torch.zeros(2))
        >>> phi.shape, psi.shape
        (torch.Size([2, 1, 4]), torch.Size([2, 1, 4]))
    """
    v = vertices.to(points.dtype)
    j, k = edges[:, 0], edges[:, 1]
    a = (v[:, k] - v[:, j])[:, None]  # (B, 1, E, 2)
    # Both ends relative to the point, formed once: every product below that vanishes as the point
    # nears an end (or the edge's line near an end) is a product of these, so it keeps its relative
    # accuracy there (b x a with b = v_j - x of the size's order cancelled to eps * size: a point
    # 1e-14 of the size from the end v_k took the wrong side of the edge, phi off by 0.1).
    b = v[:, j][:, None] - points[:, :, None]  # (B, n, E, 2)
    bp = v[:, k][:, None] - points[:, :, None]  # b + a
    # (dot products written out: a sum over an axis of 2 took most of the kernel's time, and the
    # two products added are the same numbers)
    Q = _dot(a, a)
    S = _dot(b, b)
    Sp = _dot(bp, bp)
    ab = _dot(a, b)  # = -Q t, t the projection parameter of the point on the edge
    abp = _dot(a, bp)  # = Q (1 - t)
    cross = b[..., 0] * bp[..., 1] - b[..., 1] * bp[..., 0]  # = b x a = c |a|, > 0 on the inner side
    norm_a = torch.sqrt(Q)
    tol = tol.to(points.device, points.dtype)[:, None, None]  # (B, 1, 1)
    # Edges that hold the point (within the tolerance) contribute their principal value (no angle
    # term); off the segment, near its line, the angle is small and computed as it is.
    t = -ab / Q  # projection parameter of the point on each edge
    on_line = cross.abs() <= tol * norm_a
    on_edge = on_line & (t >= -tol / norm_a) & (t <= 1 + tol / norm_a)
    # safe_atan2: a point on a vertex gives atan2(0, 0), whose derivative is NaN before torch 2.10
    # (the where below masks the value, not a NaN in the backward pass)
    theta = safe_atan2(cross.abs(), _dot(b, bp))
    theta = torch.where(on_edge, 0.0, theta)
    sigma = torch.where(cross >= 0, 1.0, -1.0).to(points.dtype)
    # log P at the ends, each multiplied by a factor that vanishes where P does (the point on a vertex).
    L0 = torch.log(torch.where(S > 0, S, 1.0))
    L1 = torch.log(torch.where(Sp > 0, Sp, 1.0))
    int_log = (abp * L1 - ab * L0) / Q - 2 + 2 * cross.abs() * theta / Q
    psi = -(norm_a / (4 * math.pi)) * int_log
    # phi_k gets c|a|/(2 pi) * int t/P, phi_j gets c|a|/(2 pi) * int (1 - t)/P, with c|a| / |a x b| = sigma;
    # int (1 - t)/P is written with a.(b + a) = Q (1 - t) (no difference of the two).
    moment = cross * (L1 - L0) / (2 * Q)
    int_1 = sigma * theta
    int_t = moment - int_1 * ab / Q
    int_s = int_1 * abp / Q - moment
    B, n, V = b.shape[0], b.shape[1], v.shape[1]
    phi = torch.zeros(B, n, V, dtype=points.dtype, device=points.device)
    phi.index_add_(2, k, int_t / (2 * math.pi))
    phi.index_add_(2, j, int_s / (2 * math.pi))
    # Points on the polygon: the hat values with the jump weight 1 - omega / (2 pi), omega the angle
    # the rest of the polygon subtends (pi on an edge, the interior angle at a vertex).
    on_cage = on_edge.any(dim=2)  # (B, n)
    if bool(on_cage.any()):
        bi, pi = torch.nonzero(on_cage, as_tuple=True)
        e = on_edge[bi, pi].to(torch.int8).argmax(dim=1)
        tt = t[bi, pi, e].clamp(0.0, 1.0)
        omega = int_1[bi, pi].sum(dim=1, keepdim=True)
        hat = torch.zeros(bi.shape[0], V, dtype=points.dtype, device=points.device)
        hat.scatter_add_(1, torch.stack([j[e], k[e]], dim=1), torch.stack([1 - tt, tt], dim=1))
        phi[bi, pi] = phi[bi, pi] + (1 - omega / (2 * math.pi)) * hat
    return phi, psi


def green2d_derivatives(points: torch.Tensor, cage: Cage, order: int = 1) -> tuple[torch.Tensor, ...]:
    r"""Gradients (and Hessians) of 2D Green coordinates with respect to the points, closed form.

    The 2D counterparts of the 3D formulas (:mod:`.derivatives3d`): per edge ``e`` from
    ``v_j`` to ``v_k`` (unit direction ``u``, outward normal ``n``, length ``l``), with
    ``a = v_j - x``, ``b = v_k - x``, the signed angle ``omega`` the edge subtends (positive on the
    inner side), the in-line moment ``K = u log(|b| / |a|)`` and the hat functions' gradients
    ``g_j = -u / l``, ``g_k = u / l``:

    .. math::
        \nabla\phi_i = \frac{1}{2\pi}\sum_{e \ni i} (\omega_e g_i - n_e\, g_i \cdot K_e),\qquad
        \nabla\psi_e = \frac{1}{2\pi}(K_e + \omega_e n_e),

    (the end-point terms of the integration by parts cancel around the closed polygon), and with
    :math:`\nabla\omega = a^\perp / |a|^2 - b^\perp / |b|^2` (:math:`v^\perp = (-v_y, v_x)`, times
    the orientation's sign) and :math:`\nabla K = u\, (a / |a|^2 - b / |b|^2)^T`, the Hessians
    :math:`H\phi_i = \frac{1}{2\pi}\sum_e (g_i \nabla\omega_e^T - n_e\, g_i^T \nabla K_e)`,
    :math:`H\psi_e = \frac{1}{2\pi}(\nabla K_e + n_e \nabla\omega_e^T)`.

    Args:
        points: ``(n, 2)`` points off the polygon.
        cage: a 2D cage.
        order: 1 or 2.

    Returns:
        ``(grad_phi (n, V, 2), grad_psi (n, E, 2), hess_phi (n, V, 2, 2), hess_psi (n, E, 2, 2),
        exact (n,))``, Hessians empty for ``order=1``; ``exact`` is False on the polygon (rows left
        zero for the caller).

    Examples:
        >>> import torch, torchcage
        >>> from torchcage.families.green.kernel2d import green2d_derivatives
        >>> cage = torchcage.Cage([[0.0, 0], [2, 0], [2, 1], [0, 1]]).to(torch.float64)
        >>> x = torch.tensor([[0.5, 0.25]], dtype=torch.float64)
        >>> gp, gs, hp, hs, ok = green2d_derivatives(x, cage, order=2)
        >>> J = torch.einsum("nvi,vj->nji", gp, cage.vertices) + torch.einsum("nei,ej->nji", gs, cage.edge_normals())
        >>> torch.allclose(J[0], torch.eye(2, dtype=torch.float64))
        True
    """
    v = cage.vertices.to(points.dtype)
    j, k = cage.edges[:, 0], cage.edges[:, 1]
    E = v[k] - v[j]
    ell = E.norm(dim=-1)
    u = E / ell[:, None]  # (E, 2)
    n = torch.stack([u[:, 1], -u[:, 0]], dim=-1)  # outward for a counter-clockwise polygon
    a = v[j][None] - points[:, None]  # (n, E, 2)
    b = v[k][None] - points[:, None]
    Ra2, Rb2 = _dot(a, a), _dot(b, b)
    cross = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    omega = torch.atan2(cross, _dot(a, b))  # signed: positive with the polygon on the left
    # on the polygon: a row for the caller (the derivatives there are those of the interpolant)
    tol = on_cage_tolerance(cage)
    t = -_dot(a, u) / ell
    on_line = (a[..., 0] * u[..., 1] - a[..., 1] * u[..., 0]).abs() <= tol
    exact = ~(on_line & (t >= -tol / ell) & (t <= 1 + tol / ell)).any(dim=1)
    safe = lambda r2: torch.where(r2 > 0, r2, 1.0)  # noqa: E731
    K = u * (0.5 * (torch.log(safe(Rb2)) - torch.log(safe(Ra2))))[..., None]  # (n, E, 2)
    g = torch.stack([-u / ell[:, None], u / ell[:, None]], dim=1)  # (E, 2 ends, 2)
    inv2pi = 1.0 / (2 * math.pi)
    face = (omega[..., None, None] * g - n[:, None, :] * _dot(g, K[..., None, :])[..., None]) * inv2pi
    grad_phi = points.new_zeros(points.shape[0], cage.num_vertices, 2)
    grad_phi.index_add_(1, j, face[:, :, 0])
    grad_phi.index_add_(1, k, face[:, :, 1])
    grad_psi = (K + omega[..., None] * n) * inv2pi
    empty = points.new_empty((0,))
    if order == 1:
        return grad_phi, grad_psi, empty, empty, exact

    def perp(q: torch.Tensor) -> torch.Tensor:
        return torch.stack([-q[..., 1], q[..., 0]], dim=-1)

    grad_omega = perp(a) / safe(Ra2)[..., None] - perp(b) / safe(Rb2)[..., None]  # (n, E, 2)
    grad_K = u[None, :, :, None] * (a / safe(Ra2)[..., None] - b / safe(Rb2)[..., None])[..., None, :]
    hess_psi = (grad_K + n[None, :, :, None] * grad_omega[..., None, :]) * inv2pi
    hess_psi = 0.5 * (hess_psi + hess_psi.transpose(-1, -2))
    gK = torch.einsum("ezc,necb->nezb", g, grad_K)  # (n, E, 2 ends, 2)
    face2 = g[None, :, :, :, None] * grad_omega[:, :, None, None, :] - n[None, :, None, :, None] * gK[..., None, :]
    face2 = face2 * inv2pi  # (n, E, 2 ends, a, b)
    hess_phi = points.new_zeros(points.shape[0], cage.num_vertices, 2, 2)
    hess_phi.index_add_(1, j, face2[:, :, 0])
    hess_phi.index_add_(1, k, face2[:, :, 1])
    hess_phi = 0.5 * (hess_phi + hess_phi.transpose(-1, -2))
    return grad_phi, grad_psi, hess_phi, hess_psi, exact
