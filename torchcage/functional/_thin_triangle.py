r"""Green integrals of thin triangles seen from a few widths away, by a quadrature across the width.

The closed forms of :mod:`._green3d` write a face's hat-function integral as
:math:`\alpha_i \Omega + h\, g_i \cdot K`. For a triangle of width ``w`` (twice its area over its
longest edge ``L``) seen from a point ``D`` from it, the barycentric coordinates :math:`\alpha_i` of
the foot point reach ``D / w`` and :math:`g_i` reaches ``1 / w``, while :math:`\Omega` and ``K``
are sums of terms of order 1 that cancel: the two products cancel to the face's share, and their
rounding (``eps D / w``) is what is left. The derivatives with respect to the corners lose another
``L / w``: a sliver of width 1e-9 of the size gave gradients off by 70 (relative).

Here the face is swept by the polylines ``A -> C_tau -> B`` (``AB`` the longest edge, ``C`` the
apex, ``F`` its foot on ``AB``, ``C_tau = F + tau (C - F)``): the area element is
``w s_C sigma dsigma dtau`` on the first segment and ``w (L - s_C) (1 - sigma) dsigma dtau`` on the
second. Along each segment the hat functions and the area element are linear in ``sigma`` and the
moments ``int sigma^k / r^3`` and ``int sigma^k / r`` have closed forms (or, for segments short next
to their distance, an accurate Gauss rule); across the width (``tau``) the integrand is analytic in
a disc of radius ``D / w``, and an 8-point Gauss rule is exact to rounding for ``D >= 8 w``. Nothing
cancels: the result is as accurate as the face's own share.
"""

from __future__ import annotations

import math
from functools import cache

import torch

from ._common import safe_norm

#: Faces whose longest edge is this many times their width take the swept form for the points
#: ``THIN_DISTANCE`` widths or more from their longest edge.
THIN_ASPECT = 100.0
THIN_DISTANCE = 9.0

_ACROSS = 8  # Gauss nodes across the width (error ~ (w / 4 D)^16)
_ALONG = 12  # Gauss nodes along a segment shorter than its distance (error ~ 4.2^-24)


@cache
def _gauss(n: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Gauss-Legendre nodes and weights on ``[0, 1]`` (Golub-Welsch, float64)."""
    k = torch.arange(1, n, dtype=torch.float64)
    beta = k / torch.sqrt(4 * k * k - 1)
    nodes, vecs = torch.linalg.eigh(torch.diag(beta, 1) + torch.diag(beta, -1))
    weights = 2 * vecs[0] ** 2
    return tuple(((nodes + 1) / 2).tolist()), tuple((weights / 2).tolist())


def _nodes(n: int, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    x, w = _gauss(n)
    return like.new_tensor(x), like.new_tensor(w)


def _log_ratio(num: torch.Tensor, den: torch.Tensor) -> torch.Tensor:
    ok = (num > 0) & (den > 0)
    return torch.log(torch.where(ok, num, 1.0) / torch.where(ok, den, 1.0))


def segment_moments(p0: torch.Tensor, p1: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """``(M0, M1, M2, N0, N1)`` ``(...)``: ``M_k = int_0^1 sigma^k / r^3 dsigma`` and
    ``N_k = int_0^1 sigma^k / r dsigma`` along the segment ``p0 + sigma (p1 - p0)`` (endpoints
    ``(..., 3)`` relative to the point, which must not lie on the segment), ``r`` the distance to
    the point.

    Segments at least as long as their distance take the closed forms (in the variable ``u`` along
    the line from the point's foot, in forms without cancellation), shorter ones a 12-point Gauss
    rule, exact to rounding there.

    Examples:
        >>> p0, p1 = torch.tensor([[1.0, -1, 0]]).double(), torch.tensor([[1.0, 1, 0]]).double()
        >>> m0 = segment_moments(p0, p1)[0]  # (1 / 2) int_-1^1 du / (1 + u^2)^1.5 = 1 / sqrt(2)
        >>> round(float(m0), 12) == round(2 ** 0.5 / 2, 12)
        True
    """
    d = p1 - p0
    ell = safe_norm(d)
    ok = ell > 0
    e = d / torch.where(ok, ell, 1.0)[..., None]
    ua, ub = (p0 * e).sum(-1), (p1 * e).sum(-1)
    Ra, Rb = safe_norm(p0), safe_norm(p1)
    # distance to the line from the nearer end
    near = torch.where((Ra <= Rb)[..., None], p0, p1)
    c2 = torch.linalg.cross(near, e, dim=-1).square().sum(-1)
    t = (-(p0 * d).sum(-1) / torch.where(ok, ell * ell, 1.0)).clamp(0.0, 1.0)
    dist = safe_norm(p0 + t[..., None] * d)
    # closed forms
    same = (ua > 0) | (ub < 0)
    c2s = torch.where(c2 > 0, c2, 1.0)
    den_same = Ra * Rb * (ub * Ra + ua * Rb)
    F0 = torch.where(
        same,
        ell * (ub + ua) / torch.where(same & (den_same != 0), den_same, 1.0),
        (ub / torch.where(Rb > 0, Rb, 1.0) - ua / torch.where(Ra > 0, Ra, 1.0)) / c2s,
    )  # int du / R^3
    RaRb = torch.where((Ra > 0) & (Rb > 0), Ra * Rb * (Ra + Rb), 1.0)
    F1 = ell * (ub + ua) / RaRb  # int u du / R^3 = 1 / Ra - 1 / Rb
    A0 = torch.where(
        ua >= 0,
        _log_ratio(ub + Rb, ua + Ra),
        torch.where(ub <= 0, _log_ratio(Ra - ua, Rb - ub), _log_ratio((ub + Rb) * (Ra - ua), c2)),
    )  # int du / R
    F2 = A0 - c2 * F0  # int u^2 du / R^3 = asinh(u / c) - u / R
    G1 = ell * (ub + ua) / torch.where(Ra + Rb > 0, Ra + Rb, 1.0)  # int u du / R = Rb - Ra
    L = torch.where(ok, ell, 1.0)
    closed = (
        F0 / L,
        (F1 - ua * F0) / L**2,
        (F2 - 2 * ua * F1 + ua * ua * F0) / L**3,
        A0 / L,
        (G1 - ua * A0) / L**2,
    )
    # Gauss rule
    s, w = _nodes(_ALONG, p0)
    r = safe_norm(p0[..., None, :] + s[:, None] * d[..., None, :])  # (..., q)
    r = torch.where(r > 0, r, 1.0)
    inv3, inv1 = w / r**3, w / r
    gauss = ((inv3).sum(-1), (inv3 * s).sum(-1), (inv3 * s * s).sum(-1), inv1.sum(-1), (inv1 * s).sum(-1))
    short = ell < dist
    return tuple(torch.where(short, g, c) for g, c in zip(gauss, closed, strict=True))


def thin_pairs(a: torch.Tensor, two_area: torch.Tensor) -> torch.Tensor:
    """Which pairs take :func:`thin_triangle_integrals`: ``a`` ``(..., 3, 3)`` corners minus the
    point, ``two_area`` ``(...)``. A face ``THIN_ASPECT`` times longer than wide, the point at least
    ``THIN_DISTANCE`` widths from its longest edge. Returns ``(...)`` bools."""
    E = a.roll(-2, dims=-2) - a.roll(-1, dims=-2)
    ell2 = E.square().sum(-1)  # (..., 3)
    L2, i = ell2.max(dim=-1)
    thin = L2 > THIN_ASPECT * two_area  # L / w = L^2 / 2A
    if not bool(thin.any()):
        return thin
    A = a.gather(-2, ((i + 1) % 3)[..., None, None].expand(*i.shape, 1, 3)).squeeze(-2)
    d = E.gather(-2, i[..., None, None].expand(*i.shape, 1, 3)).squeeze(-2)  # A -> B
    t = (-(A * d).sum(-1) / torch.where(L2 > 0, L2, 1.0)).clamp(0.0, 1.0)
    dist2 = (A + t[..., None] * d).square().sum(-1)
    # dist >= THIN_DISTANCE * w, w = 2A / L
    return thin & (dist2 * L2 >= (THIN_DISTANCE * two_area) ** 2) & (two_area > 0)


def thin_triangle_integrals(
    a: torch.Tensor, h: torch.Tensor, two_area: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Green integrals of triangles by the swept form: ``a`` ``(k, 3, 3)`` corners minus the point,
    ``h`` ``(k,)`` the signed distance to the plane (positive on the inner side), ``two_area``
    ``(k,)``. The point must lie off the triangle (the pairs of :func:`thin_pairs`).

    Returns:
        ``(phi_face (k, 3), psi (k,), omega (k,))`` as :func:`._green3d.triangle_integrals`:
        ``int Gamma_i h / r^3 / 4 pi``, ``int 1 / r / 4 pi`` and ``int h / r^3``.
    """
    E = a.roll(-2, dims=-2) - a.roll(-1, dims=-2)
    ell2 = E.square().sum(-1)
    i = ell2.argmax(dim=-1)  # the apex: the corner opposite the longest edge
    order = torch.stack([(i + 1) % 3, (i + 2) % 3, i], dim=-1)  # A, B, C
    abc = a.gather(-2, order[..., None].expand(-1, 3, 3))
    aA, aB, aC = abc[:, 0], abc[:, 1], abc[:, 2]
    AB = aB - aA
    L2 = AB.square().sum(-1)
    lam = ((aC - aA) * AB).sum(-1) / torch.where(L2 > 0, L2, 1.0)
    lam = lam.clamp(0.0, 1.0)  # the apex's foot F = A + lam (B - A)
    aF = aA + lam[:, None] * AB
    tau, wt = _nodes(_ACROSS, a)
    aCt = aF[:, None] + tau[None, :, None] * (aC - aF)[:, None]  # (k, m, 3)
    m1 = segment_moments(aA[:, None].expand_as(aCt), aCt)  # A -> C_tau
    m2 = segment_moments(aCt, aB[:, None].expand_as(aCt))  # C_tau -> B
    one = torch.ones_like(tau)
    zero = torch.zeros_like(tau)
    # barycentric coordinates (A, B, C) of C_tau: ((1 - tau)(1 - lam), (1 - tau) lam, tau)
    bCt = torch.stack(
        [(1 - tau)[None] * (1 - lam)[:, None], (1 - tau)[None] * lam[:, None], tau[None].expand(lam.shape[0], -1)],
        dim=-1,
    )  # (k, m, 3)
    bA = torch.stack([one, zero, zero], dim=-1)[None].expand_as(bCt)
    bB = torch.stack([zero, one, zero], dim=-1)[None].expand_as(bCt)
    # segment 1: hats bA + sigma (bCt - bA), area element 2A lam sigma
    # segment 2: hats bCt + sigma (bB - bCt), area element 2A (1 - lam) (1 - sigma)
    j1 = (two_area * lam)[:, None]
    j2 = (two_area * (1 - lam))[:, None]
    terms = []
    for (M0, M1, M2, N0, N1), g0, g1, jc0, jc1 in (
        (m1, bA, bCt - bA, torch.zeros_like(j1), j1),
        (m2, bCt, bB - bCt, j2, -j2),
    ):
        hat = (jc0 * M0)[..., None] * g0 + (jc0 * M1)[..., None] * g1 + (jc1 * M1)[..., None] * g0
        hat = hat + (jc1 * M2)[..., None] * g1
        terms.append((hat, jc0 * M0 + jc1 * M1, jc0 * N0 + jc1 * N1))
    hat = ((terms[0][0] + terms[1][0]) * wt[:, None]).sum(1)  # (k, 3) int Gamma / r^3, order A, B, C
    inv3 = ((terms[0][1] + terms[1][1]) * wt).sum(1)
    inv1 = ((terms[0][2] + terms[1][2]) * wt).sum(1)
    phi_abc = h[:, None] * hat / (4 * math.pi)
    phi_face = torch.zeros_like(phi_abc).scatter(-1, order, phi_abc)
    return phi_face, inv1 / (4 * math.pi), h * inv3
