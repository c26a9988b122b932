r"""Error-controlled quadrature of the defining integrals of quad mean value and quad Green coordinates.

For a bilinear sheet ``xi(u, v) - x = p0 + u b + v c + u v dd`` over ``[0, 1]^2`` (relative to the
point ``x``) with normal ``N = xi_u x xi_v = b x c + u (b x dd) + v (dd x c)``, the four corner
integrals are

    Omega_i = int phi_i(u, v) N . (xi - x) / |xi - x|^4 du dv,

``phi = ((1-u)(1-v), u(1-v), uv, (1-u)v)``: the mean value weights of the quad's corners
(Thiery et al. 2018, Eq. 8 written in the quad's parameters); quad Green coordinates (Thiery and
Boubekeur 2022) need ``int phi_i N . (xi - x) / |xi - x|^3`` and ``int phi_i / |xi - x|`` (``green``).
This module computes them to a relative tolerance ``tol``:

- The domain is cut into rectangular panels. A panel's corners span a bilinear sheet that lies in
  their convex hull, so inside the ball around their centroid ``c_P`` of radius ``R_P`` (the farthest
  corner). The integrand is analytic on the panel with the singularity ``x`` at the ratio
  ``q = |x - c_P| / R_P``, and the ``m x m`` tensor Gauss–Legendre rule's error is below
  ``C m rho^(-2m)`` times the panel's integral of ``|N| / |xi - x|^3`` (the integrand without its
  cosine), with ``rho = q + sqrt(q^2 - 1)`` (the Bernstein ellipse through a singularity at that
  ratio); :data:`ERROR_C` is calibrated with a margin on random curved, elongated panels seen from
  all sides (the tests check the bound).
- A panel takes the least order ``m`` with ``C m rho^(-2m) <= tol``; if that exceeds
  :data:`MAX_ORDER`, if ``q < MIN_RATIO``, or if its four children would take fewer nodes, it is
  split: the first time at the point's projection ``(u*, v*)`` onto the quad (so the nearly
  singular spot sits at a corner of each part, and bisection grades the panels geometrically
  towards it), then in halves (the longer side in space alone when the panel is more than twice
  as long as wide). The sheet is written about ``(u*, v*)`` (:func:`centred`), so that near the
  point its offsets are accurate to their own rounding.
- The rule is a-priori (a bound on the error from the geometry, no second rule): every panel is
  evaluated once, and the torch and native kernels take the same decisions.

The error in each integral is then at most ``tol`` times the integral of ``|N| / |xi - x|^3`` over
the quad; for the normalised coordinates of a point inside the cage this is about ``tol`` (the total
weight is the same integral with the cosine of the angle under which the point sees the surface),
whatever the cage's size: the coordinates are scale-invariant. The Green integrands are milder
(``1 / r^2`` and ``1 / r``): the same orders bound their errors relative to their own magnitudes.
"""

from __future__ import annotations

import functools
import math

import torch

Vec = tuple[torch.Tensor, torch.Tensor, torch.Tensor]

#: Constant of the error model ``C m rho^(-2m)``, relative to the panel's integral of
#: ``|N| / |xi - x|^3`` (the integrand without its cosine). The worst measured over 2,000 random
#: panels (aspect 1-10, corners off a plane by up to half the width, points at ratios 1.3-5 in every
#: direction and in the panel's plane), orders 2-16, is 20 (tests/test_quad_tolerance.py checks it).
ERROR_C = 30.0

#: The least ratio ``|x - c_P| / R_P`` at which a panel is integrated (below it: split). With
#: :data:`MAX_ORDER` chosen for the cost: FireHydrant, all vertices, tol 1e-8: 1.2x the Riemann
#: sum at n = 4 (2.0x with ratio 2 and order 10).
MIN_RATIO = 1.3

#: The highest Gauss order per direction; a panel needing more is split.
MAX_ORDER = 16

#: A panel is split where four children, each seen at this many times its ratio (their radius halves,
#: their distance shrinks by at most the parent's radius), would take fewer nodes than it.
SPLIT_GAIN = 2.0

#: Panels at this depth are integrated at :data:`MAX_ORDER` whatever their ratio (a point within
#: ``2^-MAX_DEPTH`` of the quad's size; points that close are on the cage for the callers).
MAX_DEPTH = 48


def _least_order(q: torch.Tensor, tol: float) -> torch.Tensor:
    """The least ``m`` with ``C m rho^(-2m) <= tol`` at ratios ``q >= 1``, or ``MAX_ORDER + 1``."""
    log_rho = torch.log(q + torch.sqrt(q * q - 1))
    m = torch.full_like(q, MAX_ORDER + 1)
    for k in range(MAX_ORDER, 0, -1):
        m = torch.where(math.log(ERROR_C) + math.log(k) - 2 * k * log_rho <= math.log(tol), float(k), m)
    return m


def order(q: torch.Tensor, tol: float) -> torch.Tensor:
    """Gauss order per direction for panels at ratios ``q`` ``(K,)``: the least ``m`` with
    ``C m rho^(-2m) <= tol``, or 0 (split) where ``q < MIN_RATIO``, where no ``m`` up to
    :data:`MAX_ORDER` is enough, or where four children at :data:`SPLIT_GAIN` times the ratio would
    take fewer nodes (``4 m_child^2 < m^2``)."""
    qs = q.clamp_min(MIN_RATIO)
    m = _least_order(qs, tol)
    mc = _least_order(SPLIT_GAIN * qs, tol)
    split = (q < MIN_RATIO) | (m > MAX_ORDER) | (4 * mc * mc < m * m)
    return torch.where(split, torch.zeros_like(m), m).to(torch.int64)


@functools.lru_cache(maxsize=64)
def _gauss(m: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Gauss–Legendre nodes and weights of order ``m`` on [0, 1] (as Python floats)."""
    t, w = _legendre(m)
    return tuple(0.5 * (1 + a) for a in t), tuple(0.5 * a for a in w)


@functools.cache
def gauss_table() -> torch.Tensor:
    """The rules of orders ``0..MAX_ORDER`` as a float64 table ``(MAX_ORDER + 1, 2, MAX_ORDER)``
    (nodes, then weights, zero-padded; row 0 unused) for the native kernel. Built once: every call
    returns the same tensor, which the kernels only read (do not write into it)."""
    table = torch.zeros((MAX_ORDER + 1, 2, MAX_ORDER), dtype=torch.float64)
    for m in range(1, MAX_ORDER + 1):
        t, w = _gauss(m)
        table[m, 0, :m] = torch.tensor(t, dtype=torch.float64)
        table[m, 1, :m] = torch.tensor(w, dtype=torch.float64)
    return table


def _legendre(m: int) -> tuple[list[float], list[float]]:
    """Nodes and weights of the ``m``-point Gauss–Legendre rule on [-1, 1] (Newton on ``P_m``)."""

    def legendre(x: float) -> tuple[float, float]:  # P_m(x) and P_m'(x)
        p0, p1 = 1.0, x
        for k in range(2, m + 1):
            p0, p1 = p1, ((2 * k - 1) * x * p1 - (k - 1) * p0) / k
        return (p1, m * (x * p1 - p0) / (x * x - 1)) if m > 1 else (x, 1.0)

    nodes, weights = [], []
    for i in range(m):
        x = -math.cos(math.pi * (i + 0.75) / (m + 0.5))
        for _ in range(100):
            p, dp = legendre(x)
            x -= p / dp
            if abs(p / dp) < 1e-16:
                break
        _, dp = legendre(x)
        nodes.append(x)
        weights.append(2 / ((1 - x * x) * dp * dp))
    return nodes, weights


def centred(
    p0: Vec, b: Vec, c: Vec, dd: Vec, us: torch.Tensor, vs: torch.Tensor, on: torch.Tensor | None = None
) -> tuple[Vec, Vec, Vec, Vec]:
    """The sheets ``xi - x = p0 + u b + v c + u v dd`` about ``(us, vs)``: ``(h, b', c', dd)`` with
    ``xi - x = h + du b' + dv c' + du dv dd`` in ``du = u - us``, ``dv = v - vs`` (exact for a
    bilinear sheet), so that near the point the differences are accurate to rounding of themselves,
    not of ``|p0|``. Where ``on`` (the point lies on the quad), ``h = 0``: the point is taken at
    ``xi(us, vs)`` and the integrals are principal values. Vectors ``(S,)`` each."""
    h = [p0[i] + us * b[i] + vs * c[i] + (us * vs) * dd[i] for i in range(3)]
    if on is not None:
        h = [torch.where(on, torch.zeros_like(t), t) for t in h]
    b1 = tuple(b[i] + vs * dd[i] for i in range(3))
    c1 = tuple(c[i] + us * dd[i] for i in range(3))
    return tuple(h), b1, c1, dd  # type: ignore[return-value]


def _sheet(h: Vec, b: Vec, c: Vec, dd: Vec, du: torch.Tensor, dv: torch.Tensor) -> Vec:
    """``xi - x`` at offsets ``du, dv`` from the centre (vectors broadcast against them)."""
    return tuple(h[i] + du * b[i] + dv * c[i] + (du * dv) * dd[i] for i in range(3))  # type: ignore[return-value]


def _cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def panel_ratio(
    sheet: tuple[Vec, Vec, Vec, Vec],
    us: torch.Tensor,
    vs: torch.Tensor,
    u0: torch.Tensor,
    u1: torch.Tensor,
    v0: torch.Tensor,
    v1: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Ratio ``|x - c_P| / R_P`` of panels ``[u0, u1] x [v0, v1]`` (all ``(K,)``) of the centred
    sheets (:func:`centred`, vectors ``(K,)`` each, centres ``us, vs``), and the lengths in space of
    their ``u`` and ``v`` sides (the longer of each pair)."""
    a0, a1, b0, b1 = u0 - us, u1 - us, v0 - vs, v1 - vs
    X = [_sheet(*sheet, uu, vv) for uu, vv in ((a0, b0), (a1, b0), (a1, b1), (a0, b1))]
    ctr = [(X[0][i] + X[1][i] + X[2][i] + X[3][i]) * 0.25 for i in range(3)]

    def dist(a: Vec | list[torch.Tensor], bb: Vec | list[torch.Tensor]) -> torch.Tensor:
        return torch.sqrt(sum((a[i] - bb[i]) ** 2 for i in range(3)))  # type: ignore[return-value]

    R = torch.stack([dist(X[k], ctr) for k in range(4)]).amax(dim=0)
    d = torch.sqrt(ctr[0] * ctr[0] + ctr[1] * ctr[1] + ctr[2] * ctr[2])
    q = torch.where(R > 0, d / torch.where(R > 0, R, torch.ones_like(R)), torch.full_like(R, math.inf))
    lu = torch.maximum(dist(X[0], X[1]), dist(X[3], X[2]))
    lv = torch.maximum(dist(X[0], X[3]), dist(X[1], X[2]))
    return q, lu, lv


def gauss_panels(
    sheet: tuple[Vec, Vec, Vec, Vec],
    us: torch.Tensor,
    vs: torch.Tensor,
    u0: torch.Tensor,
    u1: torch.Tensor,
    v0: torch.Tensor,
    v1: torch.Tensor,
    m: int,
    green: bool = False,
) -> torch.Tensor:
    """The four corner integrals over panels ``[u0, u1] x [v0, v1]`` ``(K,)`` of the centred
    sheets (:func:`centred`, centres ``us, vs``) by the ``m x m`` tensor Gauss rule. Returns
    ``(4, K)``, or with ``green`` the eight of quad Green coordinates ``(8, K)`` (see
    :func:`quad_integrals`)."""
    h, b, c, dd = sheet
    t, g = (torch.tensor(a, dtype=u0.dtype, device=u0.device) for a in _gauss(m))
    du, dv = u1 - u0, v1 - v0
    U = (u0[:, None] + du[:, None] * t)[:, :, None]  # (K, m, 1) for the basis
    V = (v0[:, None] + dv[:, None] * t)[:, None, :]  # (K, 1, m)
    DU = ((u0 - us)[:, None] + du[:, None] * t)[:, :, None]  # offsets from the centre: for xi - x
    DV = ((v0 - vs)[:, None] + dv[:, None] * t)[:, None, :]
    Nc, Nu, Nv = _cross(b, c), _cross(b, dd), _cross(dd, c)  # N = Nc + du Nu + dv Nv
    # along a row (fixed U): xi - x = Pu + DV Qu, N = Ru + DV Nv (the native kernel's order)
    Pu = [h[i][:, None, None] + DU * b[i][:, None, None] for i in range(3)]
    Qu = [c[i][:, None, None] + DU * dd[i][:, None, None] for i in range(3)]
    Ru = [Nc[i][:, None, None] + DU * Nu[i][:, None, None] for i in range(3)]
    X = [Pu[i] + DV * Qu[i] for i in range(3)]
    N = [Ru[i] + DV * Nv[i][:, None, None] for i in range(3)]
    r2 = X[0] * X[0] + X[1] * X[1] + X[2] * X[2]
    ok = r2 > 0  # (a node on the point: a null set, where the integrands are O(1 / r) on the quad)
    r2 = torch.where(ok, r2, torch.ones_like(r2))
    Nd = N[0] * X[0] + N[1] * X[1] + N[2] * X[2]
    gw = torch.where(ok, g, torch.zeros_like(r2))
    ga = g * (du * dv)[:, None]
    U = U[..., 0]
    if green:
        r = torch.sqrt(r2)
        fs = [Nd / (r * r * r) * gw, gw / r]
    else:
        fs = [Nd / (r2 * r2) * gw]
    out = []
    for f in fs:
        lo, hi = (f * (1 - V)).sum(dim=-1), (f * V).sum(dim=-1)  # (K, m)
        out += [((1 - U) * ga * lo).sum(-1), (U * ga * lo).sum(-1), (U * ga * hi).sum(-1), ((1 - U) * ga * hi).sum(-1)]
    return torch.stack(out)


def quad_integrals(
    p0: Vec,
    b: Vec,
    c: Vec,
    dd: Vec,
    us: torch.Tensor,
    vs: torch.Tensor,
    tol: float,
    green: bool = False,
    on: torch.Tensor | None = None,
) -> torch.Tensor:
    """The corner integrals ``Omega`` ``(4, S)`` of ``S`` point–quad pairs to the relative
    tolerance ``tol``.

    Args:
        p0, b, c, dd: the sheets ``xi - x = p0 + u b + v c + u v dd``, three ``(S,)`` each.
        us, vs: ``(S,)`` the points' projections onto the quads, in ``[0, 1]`` (the first split).
        tol: relative tolerance (``> 0``).
        green: instead, the eight integrals of quad Green coordinates ``(8, S)`` (without their
            ``1 / 4 pi``): ``int phi_i N.(xi - x) / |xi - x|^3`` (the solid angle's, rows 0-3) and
            ``int phi_i / |xi - x|`` (the single layer's, rows 4-7), over ``du dv``.
        on: ``(S,)`` bool, the point lies on the quad (at ``xi(us, vs)``): principal values.

    Examples:
        >>> import torch
        >>> z = torch.zeros(1, dtype=torch.float64)
        >>> one, h = torch.ones_like(z), torch.full_like(z, -0.5)
        >>> sheet = ((-0.5 * one, -0.5 * one, h), (one, z, z), (z, one, z), (z, z, z))  # unit square below x
        >>> om = quad_integrals(*sheet, 0.5 * one, 0.5 * one, 1e-10)
        >>> om.shape, bool(torch.allclose(om, om[0].expand(4, 1)))
        (torch.Size([4, 1]), True)
    """
    S = us.shape[0]
    us, vs = us.detach(), vs.detach()  # (a change of variables: the integrals do not depend on them)
    full = centred(p0, b, c, dd, us, vs, on)
    out = us.new_zeros((8 if green else 4, S))
    pid = torch.arange(S, device=us.device)
    u0, v0 = us.new_zeros(S), us.new_zeros(S)
    u1, v1 = us.new_ones(S), us.new_ones(S)
    for depth in range(MAX_DEPTH + 1):
        if pid.numel() == 0:
            break
        sel = tuple(tuple(a[i].index_select(0, pid) for i in range(3)) for a in full)
        cu, cv = us.index_select(0, pid), vs.index_select(0, pid)
        q, lu, lv = panel_ratio(sel, cu, cv, u0, u1, v0, v1)  # type: ignore[arg-type]
        m = order(q, tol)
        if depth == MAX_DEPTH:
            m = torch.where(m == 0, MAX_ORDER, m)
        done = m >= 1
        # zero-area panels (a projection on the boundary) contribute nothing
        empty = (u1 <= u0) | (v1 <= v0)
        for mm in torch.unique(m[done & ~empty]).tolist():
            k = torch.nonzero(done & ~empty & (m == mm)).squeeze(1)
            part = gauss_panels(
                tuple(tuple(t.index_select(0, k) for t in vec) for vec in sel),  # type: ignore[arg-type]
                cu[k], cv[k], u0[k], u1[k], v0[k], v1[k], int(mm), green,
            )  # fmt: skip
            out = out.index_add(1, pid[k], part)
        keep = torch.nonzero(~done & ~empty).squeeze(1)
        pid, u0, u1, v0, v1, lu, lv = (t.index_select(0, keep) for t in (pid, u0, u1, v0, v1, lu, lv))
        if depth == 0:
            su, sv = us.index_select(0, pid), vs.index_select(0, pid)
            cut_u = cut_v = torch.ones_like(su, dtype=torch.bool)
        else:
            su, sv = 0.5 * (u0 + u1), 0.5 * (v0 + v1)
            cut_u, cut_v = ~(lv > 2 * lu), ~(lu > 2 * lv)
        pid, u0, u1, v0, v1 = _split(pid, u0, u1, v0, v1, su, sv, cut_u, cut_v)
    return out


def _split(
    pid: torch.Tensor,
    u0: torch.Tensor,
    u1: torch.Tensor,
    v0: torch.Tensor,
    v1: torch.Tensor,
    su: torch.Tensor,
    sv: torch.Tensor,
    cut_u: torch.Tensor,
    cut_v: torch.Tensor,
) -> tuple[torch.Tensor, ...]:
    """Children of panels cut at ``su`` (where ``cut_u``) and ``sv`` (where ``cut_v``), in the order
    (low u, low v), (high u, low v), (high u, high v), (low u, high v) per panel, panel-major; an
    uncut side gives one child there (the parent's range), so uncut panels give 2 or 1 children."""
    parts = []
    for hu, hv in ((0, 0), (1, 0), (1, 1), (0, 1)):
        a0 = torch.where(cut_u, su, u0) if hu else u0
        a1 = u1 if hu else torch.where(cut_u, su, u1)
        b0 = torch.where(cut_v, sv, v0) if hv else v0
        b1 = v1 if hv else torch.where(cut_v, sv, v1)
        valid = (cut_u | (hu == 0)) & (cut_v | (hv == 0))
        if isinstance(valid, bool):
            valid = torch.full_like(cut_u, valid)
        parts.append((pid, a0, a1, b0, b1, valid))
    stacked = [torch.stack([p[i] for p in parts], dim=1).reshape(-1) for i in range(6)]
    keep = torch.nonzero(stacked[5]).squeeze(1)
    return tuple(t.index_select(0, keep) for t in stacked[:5])
