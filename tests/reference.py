"""Independent high-precision references (mpmath) for the coordinate kernels.

Written separately from the library's kernels: the 3D reference uses the half-angle (Floater)
form of the triangle weights, the 2D reference the tangent formula, both at 60 digits.
"""

from __future__ import annotations

import mpmath as mp
import torch

mp.mp.dps = 60


def _mpf(c):
    return c if isinstance(c, mp.mpf) else mp.mpf(float(c))


def _vec(p):
    return mp.matrix([_mpf(c) for c in p])


def _rows(vertices) -> list:
    """Vertices as a list of rows: a tensor's floats, or rows of (mpmath) numbers as given."""
    return vertices.tolist() if isinstance(vertices, torch.Tensor) else [list(r) for r in vertices]


def _cross(a, b):
    return mp.matrix([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@mp.workdps(60)
def mvc3d_reference(x, vertices, triangles) -> list:
    """Mean value coordinates of one point (mpmath numbers), Floater-Kos-Reimers form:
    w_i += (beta_jk + beta_ij n_ij.n_jk + beta_ki n_ki.n_jk) / (2 e_i . n_jk) / r_i, with unit
    vectors e, beta the angle of each edge seen from x and n the unit normals of the planes
    through x and each edge. Accurate in 60-digit arithmetic wherever x is off the support planes."""
    xv = _vec(x)
    P = [_vec(p) - xv for p in _rows(vertices)]
    r = [mp.sqrt(_dot(p, p)) for p in P]
    e = [p / rr for p, rr in zip(P, r, strict=True)]
    w = [mp.mpf(0)] * len(P)
    for t in triangles.tolist():
        for c in range(3):
            i, j, k = t[c], t[(c + 1) % 3], t[(c + 2) % 3]

            def beta(a, b):
                return 2 * mp.asin(mp.sqrt(_dot(e[a] - e[b], e[a] - e[b])) / 2)

            def nrm(a, b):
                c_ = _cross(e[a], e[b])
                return c_ / mp.sqrt(_dot(c_, c_))

            njk, nij, nki = nrm(j, k), nrm(i, j), nrm(k, i)
            num = beta(j, k) + beta(i, j) * _dot(nij, njk) + beta(k, i) * _dot(nki, njk)
            w[i] += num / (2 * _dot(e[i], njk)) / r[i]
    total = sum(w)
    return [wi / total for wi in w]


@mp.workdps(60)
def mvc2d_reference(x, vertices) -> list:
    """2D mean value coordinates of one point for a counter-clockwise polygon given in order."""
    xv = [_mpf(c) for c in x]
    P = [[_mpf(a) - xv[0], _mpf(b) - xv[1]] for a, b in _rows(vertices)]
    n = len(P)
    r = [mp.sqrt(p[0] ** 2 + p[1] ** 2) for p in P]
    ang = []
    for i in range(n):
        a, b = P[i], P[(i + 1) % n]
        ang.append(mp.atan2(a[0] * b[1] - a[1] * b[0], a[0] * b[0] + a[1] * b[1]))
    w = [(mp.tan(ang[i - 1] / 2) + mp.tan(ang[i] / 2)) / r[i] for i in range(n)]
    total = sum(w)
    return [wi / total for wi in w]


@mp.workdps(60)
def green3d_reference(x, vertices, triangles) -> tuple[list, list]:
    """Green coordinates ``(phi (V,), psi (T,))`` of one point for a triangle cage (outward
    triangles), the bare boundary integrals (0 outside the cage), at 60 digits.

    Per face, with ``a_k = v_k - x``, unit normal ``n``, ``h = a_0 . n`` (> 0 on the inner side),
    the solid angle ``Omega`` (Van Oosterom-Strackee), and for the edge ``e`` opposite corner ``i``
    its unit direction ``u_e``, outward in-plane normal ``m_e = u_e x n``, the foot's signed distance
    ``d_e = a_{i+1} . m_e`` and ``I_e = int_e dl / r = asinh(l_k / R0) - asinh(l_j / R0)``: the single
    layer ``psi = (sum_e d_e I_e - h Omega) / 4 pi`` and the double layer of corner ``i``'s hat
    function ``(alpha_i Omega - h (m_i l_i / 2A) . K) / 4 pi`` with ``K = -sum_e m_e I_e`` and
    ``alpha_i = d_i l_i / 2A`` (classical potentials of constant and linear densities on a flat
    triangle). Accurate wherever ``x`` is off the faces and the edges' lines."""
    xv = _vec(x)
    V = [_vec(p) for p in _rows(vertices)]
    phi = [mp.mpf(0)] * len(V)
    psi = []
    for t in triangles.tolist():
        a = [V[k] - xv for k in t]
        cr = _cross(a[1] - a[0], a[2] - a[0])
        two_area = mp.sqrt(_dot(cr, cr))
        n = cr / two_area
        h = _dot(a[0], n)
        R = [mp.sqrt(_dot(p, p)) for p in a]
        det = _dot(a[0], _cross(a[1], a[2]))
        den = R[0] * R[1] * R[2] + _dot(a[0], a[1]) * R[2] + _dot(a[0], a[2]) * R[1] + _dot(a[1], a[2]) * R[0]
        omega = 2 * mp.atan2(det, den)
        K = mp.matrix([0, 0, 0])
        dI = mp.mpf(0)
        m, d, ell = [], [], []
        for i in range(3):
            j, k = (i + 1) % 3, (i + 2) % 3
            E = a[k] - a[j]
            le = mp.sqrt(_dot(E, E))
            u = E / le
            me = _cross(u, n)
            de = _dot(a[j], me)
            R0 = mp.sqrt(de * de + h * h)
            lj, lk = _dot(a[j], u), _dot(a[k], u)
            if R0 == 0:  # on the edge's line beyond the edge: the limit of the asinh difference
                I = mp.sign(lk) * (mp.log(abs(lk)) - mp.log(abs(lj)))
            else:
                I = mp.asinh(lk / R0) - mp.asinh(lj / R0)
            K -= me * I
            dI += de * I
            m.append(me)
            d.append(de)
            ell.append(le)
        for i in range(3):
            alpha = d[i] * ell[i] / two_area
            g = -m[i] * (ell[i] / two_area)
            phi[t[i]] += (alpha * omega + h * _dot(g, K)) / (4 * mp.pi)
        psi.append((dI - h * omega) / (4 * mp.pi))
    return phi, psi


@mp.workdps(60)
def gradient_reference(f, x, scale: float, step: float = 1e-20) -> list:
    """Central differences ``df/dx_c`` (floats) of a scalar function ``f`` of a list of mpmath
    numbers at ``x`` (floats, taken exactly), in 60-digit arithmetic with the step ``step * scale``:
    truncation about ``(step * scale / feature)^2``, rounding ``1e-60 / step``."""
    x0 = [_mpf(c) for c in x]
    h = mp.mpf(scale) * mp.mpf(step)
    out = []
    for c in range(len(x0)):
        up, dn = list(x0), list(x0)
        up[c] += h
        dn[c] -= h
        out.append(float((f(up) - f(dn)) / (2 * h)))
    return out


def to_tensor(values) -> torch.Tensor:
    return torch.tensor([float(v) for v in values], dtype=torch.float64)


@mp.workdps(60)
def mvc_derivatives_reference(x, coordinates, scale: float) -> tuple[list, list]:
    """Gradients ``[i][c]`` and Hessians ``[i][c][d]`` (floats) of ``coordinates(x)`` (a function
    returning a list of mpmath numbers, e.g. a closure over :func:`mvc3d_reference`; ``x`` may hold
    mpmath numbers, to sit closer to a singular plane than float64 can) by central
    differences in 60-digit arithmetic with the step ``1e-12 * scale``: truncation error about
    ``1e-24`` relative to the scale on which the coordinates vary, rounding about ``1e-36``."""
    D = len(x)
    x0 = [c if isinstance(c, mp.mpf) else mp.mpf(float(c)) for c in x]
    step = mp.mpf(scale) * mp.mpf("1e-12")

    def f(offsets):
        y = list(x0)
        for c, s in offsets:
            y[c] += s * step
        return coordinates(y)

    f0 = f([])
    plus = [f([(c, 1)]) for c in range(D)]
    minus = [f([(c, -1)]) for c in range(D)]
    V = len(f0)
    grad = [[float((plus[c][i] - minus[c][i]) / (2 * step)) for c in range(D)] for i in range(V)]
    hess = [[[0.0] * D for _ in range(D)] for _ in range(V)]
    for c in range(D):
        for i in range(V):
            hess[i][c][c] = float((plus[c][i] - 2 * f0[i] + minus[c][i]) / step**2)
        for d in range(c + 1, D):
            pp, pm = f([(c, 1), (d, 1)]), f([(c, 1), (d, -1)])
            mp_, mm = f([(c, -1), (d, 1)]), f([(c, -1), (d, -1)])
            for i in range(V):
                val = float((pp[i] - pm[i] - mp_[i] + mm[i]) / (4 * step**2))
                hess[i][c][d] = hess[i][d][c] = val
    return grad, hess


def distance_to_triangles(points: torch.Tensor, vertices: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    """Euclidean distance ``(N,)`` from each point to a set of triangles (brute force, float64)."""
    p = vertices.to(torch.float64)[triangles]  # (T, 3, 3)
    x = points.to(torch.float64)[:, None, :]  # (N, 1, 3)
    best = torch.full((points.shape[0],), float("inf"), dtype=torch.float64)
    for i in range(3):  # the three edges
        a, b = p[:, i][None], p[:, (i + 1) % 3][None]
        ab = b - a
        t = (((x - a) * ab).sum(-1) / (ab * ab).sum(-1)).clamp(0, 1)
        best = torch.minimum(best, (x - a - t[..., None] * ab).norm(dim=-1).min(dim=1).values)
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True)
    h = ((x - p[:, 0][None]) * n[None]).sum(-1)  # (N, T)
    foot = x - h[..., None] * n[None]
    inside = torch.ones_like(h, dtype=torch.bool)
    for i in range(3):
        a, b = p[:, i][None], p[:, (i + 1) % 3][None]
        inside &= (torch.linalg.cross(b - a, foot - a, dim=-1) * n[None]).sum(-1) >= 0
    plane = torch.where(inside, h.abs(), torch.inf).min(dim=1).values
    return torch.minimum(best, plane)


def quad_weights_reference(
    x, corners, radial_nodes: int = 20, angular_nodes: int = 16, angular_panels: int = 32, green: bool = False
):
    """Independent reference of a bilinear quad's four corner integrals
    ``int phi_i N.(xi - x) / |xi - x|^4 du dv`` (the unnormalised QMVC weights of one quad).

    Polar coordinates around the nearest point ``c`` of the sheet (Newton from the best node of a
    grid; snapped to the boundary when within a tenth of the distance), in the parameters scaled by
    the sheet's side lengths at ``c``: four triangles ``(c, edge)``, each by ``angular_panels``
    Gauss panels in the angle and, along every ray, geometric Gauss panels in the radius from
    ``r_max`` down to ``1e-3`` of the distance (and one panel to 0). Points off the quad's ball by a
    quarter of its radius: a composite Gauss rule. A different construction from torchcage's
    quadtree of Gauss panels; converged when doubling the nodes changes nothing (the tests check).

    Args:
        x: ``(3,)`` float64 numpy point; corners: ``(4, 3)`` float64 numpy corners ``q0..q3``.
        green: instead, the eight integrals of quad Green coordinates (without ``1 / 4 pi``):
            ``int phi_i N.(xi - x) / |xi - x|^3`` and ``int phi_i / |xi - x|``.

    Returns:
        ``(4,)`` (or ``(8,)``) numpy array.
    """
    import numpy as np

    q0, q1, q2, q3 = corners
    b, c_, dd = q1 - q0, q3 - q0, q0 - q1 + q2 - q3
    p0 = q0 - x

    def sheet(u, v):
        return p0 + u[..., None] * b + v[..., None] * c_ + (u * v)[..., None] * dd

    def integrand(u, v):
        X = sheet(u, v)
        N = np.cross(b, c_) + u[..., None] * np.cross(b, dd) + v[..., None] * np.cross(dd, c_)
        r2 = (X * X).sum(-1)
        hats = [(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v]
        if green:
            r = np.sqrt(r2)
            f, g = (N * X).sum(-1) / (r2 * r), 1 / r
            return np.stack([h * f for h in hats] + [h * g for h in hats])
        f = (N * X).sum(-1) / (r2 * r2)
        return np.stack([h * f for h in hats])

    centre = corners.mean(0)
    ratio = np.linalg.norm(x - centre) / np.linalg.norm(corners - centre, axis=1).max()
    if ratio >= 1.25:
        # off the quad's ball by a quarter radius: a composite Gauss rule of k x k panels, 14^2
        # nodes each (every panel then 4 or more of its radii away: converged to rounding)
        k = 4 if ratio >= 4 else 16
        t, w = np.polynomial.legendre.leggauss(14)
        t = ((np.arange(k)[:, None] + (t + 1) / 2) / k).ravel()
        w = np.tile(w / (2 * k), k)
        Ug, Vg = np.meshgrid(t, t, indexing="ij")
        return (integrand(Ug, Vg) * (w[:, None] * w[None, :])).sum(axis=(1, 2))
    g = np.linspace(0, 1, 21)
    U, V = np.meshgrid(g, g, indexing="ij")
    d2 = (sheet(U, V) ** 2).sum(-1)
    k = np.unravel_index(np.argmin(d2), d2.shape)
    u, v = U[k], V[k]
    for _ in range(50):  # projected Newton on |xi - x|^2
        X = sheet(np.array(u), np.array(v))
        xu, xv = b + v * dd, c_ + u * dd
        H = np.array([[xu @ xu, xu @ xv + X @ dd], [xu @ xv + X @ dd, xv @ xv]])
        gr = np.array([X @ xu, X @ xv])
        try:
            step = np.linalg.solve(H, gr)
        except np.linalg.LinAlgError:
            break
        u, v = float(np.clip(u - step[0], 0, 1)), float(np.clip(v - step[1], 0, 1))
    h = float(np.sqrt((sheet(np.array(u), np.array(v)) ** 2).sum()))
    # polar coordinates in the parameters scaled by the sheet's side lengths at c (so that the
    # nearly singular spot is round, not an ellipse of the panel's aspect)
    # (bounded below: a triangle, the quad (a, b, c, c), has no u-length at its apex)
    floor = 0.1 * max(np.linalg.norm(b), np.linalg.norm(c_))
    Lu, Lv = max(float(np.linalg.norm(b + v * dd)), floor), max(float(np.linalg.norm(c_ + u * dd)), floor)
    snap = 0.1 * h / max(Lu, Lv)  # a tenth of the distance, in the parameters
    u = 0.0 if u < snap else (1.0 if u > 1 - snap else u)
    v = 0.0 if v < snap else (1.0 if v > 1 - snap else v)
    c = np.array([u * Lu, v * Lv])
    tr, wr = np.polynomial.legendre.leggauss(radial_nodes)
    ta, wa = np.polynomial.legendre.leggauss(angular_nodes)
    square = np.array([[0.0, 0.0], [Lu, 0.0], [Lu, Lv], [0.0, Lv]])
    total = np.zeros(8 if green else 4)
    for e in range(4):
        A, B = square[e], square[(e + 1) % 4]
        n_e = np.array([(B - A)[1], -(B - A)[0]])
        n_e /= np.linalg.norm(n_e)
        de = float((A - c) @ n_e)  # distance from c to the edge's line (outward normal)
        if de <= 1e-15:
            continue
        ta_, tb_ = np.arctan2(*(A - c)[::-1]), np.arctan2(*(B - c)[::-1])
        if tb_ < ta_:
            tb_ += 2 * np.pi
        edges = np.linspace(ta_, tb_, angular_panels + 1)
        th = ((edges[:-1, None] + edges[1:, None]) + (edges[1:, None] - edges[:-1, None]) * ta) / 2
        wth = ((edges[1:, None] - edges[:-1, None]) / 2 * wa).ravel()
        th = th.ravel()
        dirs = np.stack([np.cos(th), np.sin(th)], axis=1)
        rmax = de / (dirs @ n_e)
        levels = max(1, int(np.ceil(np.log2(max(rmax.max() / (1e-3 * h + 1e-300), 2.0)))))
        levels = min(levels, 80)
        bps = rmax[:, None] * np.concatenate([2.0 ** -np.arange(levels + 1), [0.0]])[None, :]
        lo, hi = bps[:, 1:], bps[:, :-1]  # (T, levels+1)
        r = ((lo + hi)[..., None] + (hi - lo)[..., None] * tr) / 2  # (T, L, R)
        wrr = (hi - lo)[..., None] / 2 * wr
        uu = (c[0] + r * dirs[:, 0, None, None]) / Lu
        vv = (c[1] + r * dirs[:, 1, None, None]) / Lv
        F = integrand(uu, vv)  # (C, T, L, R)
        total += (F * (r * wrr)[None]).sum(axis=(2, 3)) @ wth / (Lu * Lv)
    return total
