r"""Green integrals of thin triangles seen from a few widths away, by a quadrature across the width.

The closed forms of :mod:`torchcage.families.green.kernel3d` write a face's hat-function integral as
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

from torchcage._core.common import log_ratio, safe_norm

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
        log_ratio(ub + Rb, ua + Ra),
        torch.where(ub <= 0, log_ratio(Ra - ua, Rb - ub), log_ratio((ub + Rb) * (Ra - ua), c2)),
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


def _sweep(a: torch.Tensor, two_area: torch.Tensor, moments) -> tuple[torch.Tensor, list[tuple]]:
    """The swept form's pieces for ``k`` pairs: ``a`` ``(k, 3, 3)`` corners minus the point,
    ``two_area`` ``(k,)``, ``moments(p0, p1)`` a segment-moment function (``(..., 3)`` endpoints in,
    a tuple of ``(...)`` moments out, the first three ``int sigma^j f(r) dsigma``, ``j = 0, 1, 2``).

    Returns:
        ``(order, terms)``: ``order`` ``(k, 3)`` the corners ``A, B, C`` (``AB`` the longest edge),
        and per segment ``(moments, g0, g1, jc0, jc1)``: the moments ``(k, m)`` at the ``m`` Gauss
        nodes across, the hats ``g0 + sigma g1`` ``(k, m, 3)`` (order ``A, B, C``) and the area
        element ``jc0 + sigma jc1`` ``(k, 1)``; the integral of ``Gamma f(r)`` over the face is
        ``sum_segments sum_m wt_m (jc0 M0 g0 + jc0 M1 g1 + jc1 M1 g0 + jc1 M2 g1)`` (:func:`_hat`).
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
    tau, _ = _nodes(_ACROSS, a)
    aCt = aF[:, None] + tau[None, :, None] * (aC - aF)[:, None]  # (k, m, 3)
    m1 = moments(aA[:, None].expand_as(aCt), aCt)  # A -> C_tau
    m2 = moments(aCt, aB[:, None].expand_as(aCt))  # C_tau -> B
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
    return order, [(m1, bA, bCt - bA, torch.zeros_like(j1), j1), (m2, bCt, bB - bCt, j2, -j2)]


def _hat(terms: list[tuple], wt: torch.Tensor) -> torch.Tensor:
    """``(k, 3)`` the integrals of the hats times ``f(r)`` (order ``A, B, C``) from :func:`_sweep`'s
    terms and the weights ``wt`` ``(m,)`` of the rule across."""
    total = 0.0
    for (M0, M1, M2, *_), g0, g1, jc0, jc1 in terms:
        hat = (jc0 * M0)[..., None] * g0 + (jc0 * M1)[..., None] * g1 + (jc1 * M1)[..., None] * g0
        total = total + hat + (jc1 * M2)[..., None] * g1
    return (total * wt[:, None]).sum(1)


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
    order, terms = _sweep(a, two_area, segment_moments)
    _, wt = _nodes(_ACROSS, a)
    hat = _hat(terms, wt)  # (k, 3) int Gamma / r^3, order A, B, C
    inv3 = sum(((jc0 * M0 + jc1 * M1) * wt).sum(1) for (M0, M1, *_), _g0, _g1, jc0, jc1 in terms)
    inv1 = sum(((jc0 * m[3] + jc1 * m[4]) * wt).sum(1) for m, _g0, _g1, jc0, jc1 in terms)
    phi_abc = h[:, None] * hat / (4 * math.pi)
    phi_face = torch.zeros_like(phi_abc).scatter(-1, order, phi_abc)
    return phi_face, inv1 / (4 * math.pi), h * inv3


# ------------------------------------------------------------------ mean value weights: 1 / r^4
_ALONG4 = 16  # Gauss nodes along a short segment for 1 / r^4 (error ~ 4.2^-32 times a few)
_SERIES = 11  # terms of the series of (psi - sin psi) / psi^3 (psi <= pi / 2: below 1e-18)


def _tail_ratio(y: torch.Tensor) -> torch.Tensor:
    """``(atan y - y / (1 + y^2)) / y^3`` for ``0 <= y <= 1`` (``2/3`` at 0), without cancellation:
    with ``psi = 2 atan y`` the numerator is ``(psi - sin psi) / 2``, summed as its series."""
    pos = y > 0
    ys = torch.where(pos, y, 1.0)
    ratio = torch.where(pos, torch.atan(ys) / ys, 1.0)  # psi / (2 y)
    psi2 = (2 * torch.atan(y)) ** 2
    coef = [(-1) ** k / math.factorial(2 * k + 3) for k in range(_SERIES)]
    series = torch.full_like(y, coef[-1])
    for c in reversed(coef[:-1]):
        series = series * psi2 + c
    return 4 * ratio**3 * series  # (psi / y)^3 / 2 * series


def _g(z: torch.Tensor) -> torch.Tensor:
    """``atan z - z / (1 + z^2)`` for ``z >= 0`` (``phi - sin phi cos phi``, ``phi = atan z``)."""
    small = z <= 1
    zs = torch.where(small, z, 1.0)
    zl = torch.where(small, 1.0, z)
    return torch.where(small, zs**3 * _tail_ratio(zs), torch.atan(zl) - zl / (1 + zl * zl))


def segment_moments4(p0: torch.Tensor, p1: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(P0, P1, P2)`` ``(...)``: ``P_k = int_0^1 sigma^k / r^4 dsigma`` along the segment
    ``p0 + sigma (p1 - p0)`` (endpoints ``(..., 3)`` relative to the point, which must lie off the
    segment).

    In the variable ``u`` along the line from the point's foot (``c`` the distance to the line,
    ``R^2 = u^2 + c^2``): ``int du / R^4`` and ``int u^2 du / R^4`` from the foot (``K``) or to
    infinity (``T``, for the part of the line beyond ``c`` on one side), each in a form free of
    cancellation (:func:`_g`, :func:`_tail_ratio`); segments shorter than their distance take a
    16-point Gauss rule.

    Examples:
        >>> p0, p1 = torch.tensor([[1.0, -1, 0]]).double(), torch.tensor([[1.0, 1, 0]]).double()
        >>> p = segment_moments4(p0, p1)[0]  # (1 / 2) int_-1^1 du / (1 + u^2)^2 = (1 / 2 + pi / 4) / 2
        >>> abs(float(p) - (0.5 + math.pi / 4) / 2) < 1e-15
        True
    """
    d = p1 - p0
    ell = safe_norm(d)
    ok = ell > 0
    L = torch.where(ok, ell, 1.0)
    e = d / L[..., None]
    ua, ub = (p0 * e).sum(-1), (p1 * e).sum(-1)
    Ra2, Rb2 = p0.square().sum(-1), p1.square().sum(-1)
    near = torch.where((Ra2 <= Rb2)[..., None], p0, p1)
    c = safe_norm(torch.linalg.cross(near, e, dim=-1))
    t = (-(p0 * d).sum(-1) / (L * L)).clamp(0.0, 1.0)
    dist = safe_norm(p0 + t[..., None] * d)
    cs = torch.where(c > 0, c, 1.0)
    # the same side of the foot: mirror to 0 <= lo < hi
    neg = ub <= 0
    lo = torch.where(neg, -ub, ua).clamp_min(0.0)
    hi = torch.where(neg, -ua, ub)
    same = (ua >= 0) | neg

    # K0(u) = int_0^u dt / R^4 = (atan z + z / (1 + z^2)) / (2 c^3), K2(u) = int_0^u t^2 / R^4 = g(z) / (2 c)
    def K0(u):
        z = u / cs
        return (torch.atan(z) + z / (1 + z * z)) / (2 * cs**3)

    def K2(u):
        return _g((u / cs).clamp_min(0.0)) / (2 * cs)

    # T0(u) = int_u^inf dt / R^4 = tail(c / u) / (2 u^3),
    # T2(u) = int_u^inf t^2 / R^4 = (atan y / y + 1 / (1 + y^2)) / (2 u), y = c / u
    far_side = same & (lo >= c) & (lo > 0)
    los = torch.where(far_side, lo, 1.0)
    his = torch.where(far_side, hi, 2.0)

    def T0(u):
        return _tail_ratio(torch.where(far_side, c / u, 0.0)) / (2 * u**3)

    def T2(u):
        y = torch.where(far_side, c / u, 0.0)
        yp = torch.where(y > 0, y, 1.0)
        return (torch.where(y > 0, torch.atan(yp) / yp, 1.0) + 1 / (1 + y * y)) / (2 * u)

    J0 = torch.where(
        far_side,
        T0(los) - T0(his),
        torch.where(same, K0(hi) - K0(lo), K0(ub) + K0(-ua)),
    )
    J2 = torch.where(
        far_side,
        T2(los) - T2(his),
        torch.where(same, K2(hi) - K2(lo), K2(ub) + K2(-ua)),
    )
    RR = torch.where((Ra2 > 0) & (Rb2 > 0), Ra2 * Rb2, 1.0)
    J1 = ell * (ua + ub) / (2 * RR)  # int u du / R^4 = (1 / Ra^2 - 1 / Rb^2) / 2
    closed = (J0 / L, (J1 - ua * J0) / L**2, (J2 - 2 * ua * J1 + ua * ua * J0) / L**3)
    # Gauss rule
    s, w = _nodes(_ALONG4, p0)
    r2 = (p0[..., None, :] + s[:, None] * d[..., None, :]).square().sum(-1)  # (..., q)
    inv4 = w / torch.where(r2 > 0, r2, 1.0) ** 2
    gauss = (inv4.sum(-1), (inv4 * s).sum(-1), (inv4 * s * s).sum(-1))
    short = ell < dist
    return tuple(torch.where(short, g, cl) for g, cl in zip(gauss, closed, strict=True))


def thin_triangle_mvc(a: torch.Tensor, h: torch.Tensor, two_area: torch.Tensor) -> torch.Tensor:
    """Mean value weights ``w_i = h int_T Gamma_i / r^4 dA`` of triangles by the swept form
    (``a`` ``(k, 3, 3)`` corners minus the point, ``h`` ``(k,)`` the signed distance to the plane,
    positive on the inner side, ``two_area`` ``(k,)``; the point off the triangle, as in
    :func:`thin_pairs`). Returns ``(k, 3)``, corners in ``a``'s order."""
    order, terms = _sweep(a, two_area, segment_moments4)
    _, wt = _nodes(_ACROSS, a)
    w_abc = h[:, None] * _hat(terms, wt)
    return torch.zeros_like(w_abc).scatter(-1, order, w_abc)
