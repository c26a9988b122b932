"""Triton kernel of the analytic gradients and Hessians of 3D mean value coordinates: the formulas
of the native kernel (``torchcage/backends/native/mvcd3d.c``, whose header derives them), a block of points
per program and a loop over the faces, every quantity a second-order jet (:mod:`.jet3`).

Per point–face pair, as the native kernel chooses:

* **far field** (longest edge ``<= far_c min |a_i|``): the collapsed Gauss rule of
  ``h int phi_i / |p - x|^4 dA``, differentiated under the integral;
* **near the support plane** (``|h| < near_c min |a_i|``): the split form with jets, the divided
  difference of ``G`` where an edge is seen under a small angle; the nearest face whose foot point
  the point sees inside keeps its singular part ``k s_i / h`` apart (its index and winding written
  to ``SFACE``, ``SWIND``), any other such face folds it back in;
* **direct** otherwise: ``U dw = dm + W e_c`` with the edges' jets ``theta_e / (2 |N_e|)``.

The kernel writes the raw weights' jets; :func:`mvcd3d_triton` normalises them in torch (the sum,
the singular form ``(k s_v + h r_v) / (k sum s + h sum r)``, or far away the first moment) and
redoes the flagged points (on the cage, or a thin face seen from a few widths) with the torch
kernel's derivatives (:mod:`.derivatives_torch`), on the same device.

Shapes: ``P (V, 3)``, ``tri (T, 3)`` int32, per-face tables ``(T, ...)``, ``X (n, 3)`` ->
``ACC (n, V, 10)`` (value, gradient, Hessian xx yy zz xy xz yz of each vertex's weight),
``SFACE (n,)`` int32 (the kept face, -1: none), ``SWIND (n,)`` and ``flags (n,)`` int32 (1: redo the
point).
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from torchcage._core.centre import keep_extent
from torchcage._core.common import FAR_MOMENT
from torchcage._core.thin_triangle import THIN_ASPECT, THIN_DISTANCE
from torchcage.backends.triton import device_function, interpreted, point_batch, warps
from torchcage.backends.triton.common import atan, atan2
from torchcage.cage import Cage
from torchcage.families.mean_value.derivatives_native import face_tables, native_tables
from torchcage.families.mean_value.derivatives_torch import torch_derivatives
from torchcage.families.mean_value.triton.jet3 import (
    atan_over,
    jadd,
    jatan2,
    jconst,
    jdiv,
    jf1,
    jf2,
    jlinear,
    jmul,
    jquad,
    jrecip,
    jscale,
    jsqrt,
    jsub,
    jwhere,
)
from torchcage.families.mean_value.triton.mvc3d import _thin_pair

__all__ = ["batch_tables", "derivative_tables", "mvcd3d_triton", "mvcd3d_triton_batch"]

TWO_PI = tl.constexpr(6.283185307179586)


@device_function
def _cross(a, b):
    return a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]


@device_function
def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@device_function
def _sub(a, b):
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


@device_function
def _g_closed(t):
    """``G(t) = atan(sqrt t) / sqrt t`` and its first two derivatives for ``0 <= t <= 1``: the
    alternating series below 0.1 (24 terms), the closed form above (``mvcd3d.c: g_closed``)."""
    small = t < 0.1
    ts = tl.where(small, t, 0.0)
    a0 = 1.0 - ts / 3.0
    a1 = tl.zeros_like(t) - 1.0 / 3.0
    a2 = tl.zeros_like(t)
    p = tl.zeros_like(t) + 1.0  # t^(k - 2)
    kf = tl.zeros_like(t) + 2.0  # k as a float
    sgn = tl.zeros_like(t) + 1.0  # (-1)^k
    for _k in range(2, 24):
        c = sgn / (2.0 * kf + 1.0)
        a2 += c * kf * (kf - 1.0) * p
        a1 += c * kf * p * ts
        a0 += c * p * ts * ts
        p *= ts
        kf += 1.0
        sgn = -sgn
    tc = tl.where(small, 1.0, t)
    s = tl.sqrt(tc)
    g = atan(s) / s
    q = 1.0 / (1.0 + tc)
    g1 = (q - g) / (2.0 * tc)
    g2 = (-q * q - 3.0 * g1) / (2.0 * tc)
    return tl.where(small, a0, g), tl.where(small, a1, g1), tl.where(small, a2, g2)


@device_function
def _g_fun(t, gl_y, gl_w, ng, NG: tl.constexpr):
    """``G(t) = int_0^1 dy / (1 + t y^2)`` and two derivatives by Gauss–Legendre (``g_fun``), ``NG``
    nodes at a time."""
    a = tl.zeros_like(t)
    b = tl.zeros_like(t)
    c = tl.zeros_like(t)
    if NG == 1:  # node by node (a GPU)
        for q in range(ng):
            y = tl.load(gl_y + q)
            y2 = y * y
            r = 1.0 / (1.0 + t * y2)
            wr = tl.load(gl_w + q) * r
            a += wr
            b -= wr * y2 * r
            c += 2.0 * wr * y2 * y2 * r * r
        return a, b, c
    for q0 in range(0, ng, NG):
        qo = q0 + tl.arange(0, NG)
        qm = (qo < ng)[None, :]
        y = tl.load(gl_y + qo, mask=qo < ng, other=0.0)[None, :]
        y2 = y * y
        r = 1.0 / (1.0 + t[:, None] * y2)
        wr = tl.load(gl_w + qo, mask=qo < ng, other=0.0)[None, :] * r
        a += tl.sum(tl.where(qm, wr, 0.0), axis=1)
        b -= tl.sum(tl.where(qm, wr * y2 * r, 0.0), axis=1)
        c += tl.sum(tl.where(qm, 2.0 * wr * y2 * y2 * r * r, 0.0), axis=1)
    return a, b, c


@device_function
def _g_divdiff(U, u, gl_y, gl_w, ng, NG: tl.constexpr):
    """The divided difference ``(G(U) - G(u)) / (U - u)`` with its partials
    ``D, D_U, D_u, D_UU, D_Uu, D_uu`` (``g_divdiff``), ``NG`` nodes at a time."""
    d0 = tl.zeros_like(U)
    d1 = tl.zeros_like(U)
    d2 = tl.zeros_like(U)
    d3 = tl.zeros_like(U)
    d4 = tl.zeros_like(U)
    d5 = tl.zeros_like(U)
    if NG == 1:  # node by node (a GPU)
        for q in range(ng):
            y = tl.load(gl_y + q)
            w = tl.load(gl_w + q)
            y2 = y * y
            y4 = y2 * y2
            y6 = y4 * y2
            a = 1.0 / (1.0 + U * y2)
            b = 1.0 / (1.0 + u * y2)
            wab = w * a * b
            d0 -= y2 * wab
            d1 += y4 * wab * a
            d2 += y4 * wab * b
            d3 -= 2.0 * y6 * wab * a * a
            d4 -= y6 * wab * a * b
            d5 -= 2.0 * y6 * wab * b * b
        return d0, d1, d2, d3, d4, d5
    for q0 in range(0, ng, NG):
        qo = q0 + tl.arange(0, NG)
        qm = (qo < ng)[None, :]
        y = tl.load(gl_y + qo, mask=qo < ng, other=0.0)[None, :]
        w = tl.load(gl_w + qo, mask=qo < ng, other=0.0)[None, :]
        y2 = y * y
        y4 = y2 * y2
        y6 = y4 * y2
        a = 1.0 / (1.0 + U[:, None] * y2)
        b = 1.0 / (1.0 + u[:, None] * y2)
        wab = w * a * b
        d0 -= tl.sum(tl.where(qm, y2 * wab, 0.0), axis=1)
        d1 += tl.sum(tl.where(qm, y4 * wab * a, 0.0), axis=1)
        d2 += tl.sum(tl.where(qm, y4 * wab * b, 0.0), axis=1)
        d3 -= tl.sum(tl.where(qm, 2.0 * y6 * wab * a * a, 0.0), axis=1)
        d4 -= tl.sum(tl.where(qm, y6 * wab * a * b, 0.0), axis=1)
        d5 -= tl.sum(tl.where(qm, 2.0 * y6 * wab * b * b, 0.0), axis=1)
    return d0, d1, d2, d3, d4, d5


@device_function
def _edge_phi(aj, ak):
    """``g_e = theta_e / (2 |N_e|)`` of the edge ``(j, k)`` as a jet, from the jets of
    ``u = |N|^2`` and ``v = a_j . a_k`` (``edge_phi`` and ``half_angle_over_norm``)."""
    N = _cross(aj, ak)
    E = _sub(aj, ak)
    EN = _cross(E, N)
    E2 = _dot(E, E)
    u = jquad(_dot(N, N), 2.0 * EN[0], 2.0 * EN[1], 2.0 * EN[2], 2.0 * (E2 - E[0] * E[0]), 2.0 * (E2 - E[1] * E[1]),
              2.0 * (E2 - E[2] * E[2]), -2.0 * E[0] * E[1], -2.0 * E[0] * E[2], -2.0 * E[1] * E[2])  # fmt: skip
    v = jquad(_dot(aj, ak), -(aj[0] + ak[0]), -(aj[1] + ak[1]), -(aj[2] + ak[2]), 2.0, 2.0, 2.0, 0.0, 0.0, 0.0)
    uv = u[0]
    vv = v[0]
    ok = (vv > 0) & (uv <= vv * vv)
    # below 45 degrees: G(u / v^2) / (2 v) by the chain rule
    iv = 1.0 / tl.where(ok, vv, 1.0)
    t = tl.where(ok, uv * iv * iv, 0.0)
    G0, G1, G2 = _g_closed(t)
    tu = iv * iv
    tv = -2.0 * t * iv
    tuv = -2.0 * tu * iv
    tvv = 6.0 * t * iv * iv
    h2 = 0.5 * iv
    f = G0 * h2
    fu = G1 * tu * h2
    fv = G1 * tv * h2 - G0 * h2 * iv
    fuu = G2 * tu * tu * h2
    fuv = (G2 * tu * tv + G1 * tuv) * h2 - G1 * tu * h2 * iv
    fvv = (G2 * tv * tv + G1 * tvv) * h2 - 2.0 * G1 * tv * h2 * iv + G0 * iv * iv * iv
    small = jf2(u, v, f, fu, fv, fuu, fuv, fvv)
    # else atan2(sqrt u, v) / (2 sqrt u)
    s = jsqrt(u)
    wide = jmul(jatan2(s, v), jrecip(jscale(s, 2.0)))
    return jwhere(ok, small, wide)


@device_function
def _axpy(y, a, x):
    """``y + a x`` for vectors ``x, y``."""
    return y[0] + a * x[0], y[1] + a * x[1], y[2] + a * x[2]


@device_function
def _direct_hess(Ni, M0, M1, M2, M3, M4, M5, Fx, Fy, Fz, gW, idet):
    """Row ``i`` of the weights' Hessians: ``N_i . M_cd + (F_c x N_i)_d + (F_d x N_i)_c
    + dW/dx_d N_ic + dW/dx_c N_id`` (``face_direct``)."""
    A = _cross(Fx, Ni)
    B = _cross(Fy, Ni)
    C = _cross(Fz, Ni)
    hxx = (_dot(Ni, M0) + 2.0 * A[0] + 2.0 * gW[0] * Ni[0]) * idet
    hyy = (_dot(Ni, M1) + 2.0 * B[1] + 2.0 * gW[1] * Ni[1]) * idet
    hzz = (_dot(Ni, M2) + 2.0 * C[2] + 2.0 * gW[2] * Ni[2]) * idet
    hxy = (_dot(Ni, M3) + A[1] + B[0] + gW[1] * Ni[0] + gW[0] * Ni[1]) * idet
    hxz = (_dot(Ni, M4) + A[2] + C[0] + gW[2] * Ni[0] + gW[0] * Ni[2]) * idet
    hyz = (_dot(Ni, M5) + B[2] + C[1] + gW[2] * Ni[1] + gW[1] * Ni[2]) * idet
    return hxx, hyy, hzz, hxy, hxz, hyz


@device_function
def _face_direct(a0, a1, a2, A2, h):
    """The direct evaluation: the three corners' weight jets (``face_direct``). The edges' jets
    ``phi_e`` are summed in a loop: ``m = sum phi_e N_e``, ``F_v = sum phi_e E_e``,
    ``F_c = sum dphi_e/dx_c E_e``, ``M_k = sum (H phi_e)_k N_e`` and, per corner,
    ``Q_i = sum_e grad phi_e (N_i . N_e)``."""
    N0 = _cross(a1, a2)
    N1 = _cross(a2, a0)
    N2 = _cross(a0, a1)
    z = tl.zeros_like(h)
    m = (z, z, z)
    Fv = (z, z, z)
    Fx = (z, z, z)
    Fy = (z, z, z)
    Fz = (z, z, z)
    M0 = (z, z, z)
    M1 = (z, z, z)
    M2 = (z, z, z)
    M3 = (z, z, z)
    M4 = (z, z, z)
    M5 = (z, z, z)
    Q0 = (z, z, z)
    Q1 = (z, z, z)
    Q2 = (z, z, z)
    for e in range(3):
        aj = _pick(e, a1, a2, a0)
        ak = _pick(e, a2, a0, a1)
        Ne = _cross(aj, ak)
        Ee = _sub(aj, ak)
        p = _edge_phi(aj, ak)
        m = _axpy(m, p[0], Ne)
        Fv = _axpy(Fv, p[0], Ee)
        Fx = _axpy(Fx, p[1], Ee)
        Fy = _axpy(Fy, p[2], Ee)
        Fz = _axpy(Fz, p[3], Ee)
        M0 = _axpy(M0, p[4], Ne)
        M1 = _axpy(M1, p[5], Ne)
        M2 = _axpy(M2, p[6], Ne)
        M3 = _axpy(M3, p[7], Ne)
        M4 = _axpy(M4, p[8], Ne)
        M5 = _axpy(M5, p[9], Ne)
        gp = (p[1], p[2], p[3])
        Q0 = _axpy(Q0, _dot(N0, Ne), gp)
        Q1 = _axpy(Q1, _dot(N1, Ne), gp)
        Q2 = _axpy(Q2, _dot(N2, Ne), gp)
    idet = 1.0 / (A2 * h)
    w0 = _dot(N0, m) * idet
    w1 = _dot(N1, m) * idet
    w2 = _dot(N2, m) * idet
    W = w0 + w1 + w2
    # gradient rows: (W N_i + F_v x N_i + Q_i) / det
    g0 = _axpy(_axpy(_cross(Fv, N0), W, N0), 1.0, Q0)
    g1 = _axpy(_axpy(_cross(Fv, N1), W, N1), 1.0, Q1)
    g2 = _axpy(_axpy(_cross(Fv, N2), W, N2), 1.0, Q2)
    g0 = (g0[0] * idet, g0[1] * idet, g0[2] * idet)
    g1 = (g1[0] * idet, g1[1] * idet, g1[2] * idet)
    g2 = (g2[0] * idet, g2[1] * idet, g2[2] * idet)
    gW = (g0[0] + g1[0] + g2[0], g0[1] + g1[1] + g2[1], g0[2] + g1[2] + g2[2])
    H0 = _direct_hess(N0, M0, M1, M2, M3, M4, M5, Fx, Fy, Fz, gW, idet)
    H1 = _direct_hess(N1, M0, M1, M2, M3, M4, M5, Fx, Fy, Fz, gW, idet)
    H2 = _direct_hess(N2, M0, M1, M2, M3, M4, M5, Fx, Fy, Fz, gW, idet)
    return (
        (w0, g0[0], g0[1], g0[2], H0[0], H0[1], H0[2], H0[3], H0[4], H0[5]),
        (w1, g1[0], g1[1], g1[2], H1[0], H1[1], H1[2], H1[3], H1[4], H1[5]),
        (w2, g2[0], g2[1], g2[2], H2[0], H2[1], H2[2], H2[3], H2[4], H2[5]),
    )


@device_function
def _far_integrand(d, n, h):
    """``h / |d|^4`` (``d = p - x``, ``h = n . (p_0 - x)``) with its gradient and Hessian in ``x``."""
    r2 = _dot(d, d)
    i2 = 1.0 / r2
    i4 = i2 * i2
    i6 = i4 * i2
    i8 = i4 * i4
    return (
        h * i4,
        -n[0] * i4 + 4.0 * h * d[0] * i6,
        -n[1] * i4 + 4.0 * h * d[1] * i6,
        -n[2] * i4 + 4.0 * h * d[2] * i6,
        -8.0 * n[0] * d[0] * i6 - 4.0 * h * i6 + 24.0 * h * d[0] * d[0] * i8,
        -8.0 * n[1] * d[1] * i6 - 4.0 * h * i6 + 24.0 * h * d[1] * d[1] * i8,
        -8.0 * n[2] * d[2] * i6 - 4.0 * h * i6 + 24.0 * h * d[2] * d[2] * i8,
        -4.0 * (n[0] * d[1] + d[0] * n[1]) * i6 + 24.0 * h * d[0] * d[1] * i8,
        -4.0 * (n[0] * d[2] + d[0] * n[2]) * i6 + 24.0 * h * d[0] * d[2] * i8,
        -4.0 * (n[1] * d[2] + d[1] * n[2]) * i6 + 24.0 * h * d[1] * d[2] * i8,
    )


@device_function
def _qsum(g, c, qm):
    """``sum_q c_q g_q`` over the tile's nodes ``(BLOCK, QT)`` of a jet (masked nodes add nothing)."""
    return (tl.sum(tl.where(qm, g[0] * c, 0.0), axis=1), tl.sum(tl.where(qm, g[1] * c, 0.0), axis=1),
            tl.sum(tl.where(qm, g[2] * c, 0.0), axis=1), tl.sum(tl.where(qm, g[3] * c, 0.0), axis=1),
            tl.sum(tl.where(qm, g[4] * c, 0.0), axis=1), tl.sum(tl.where(qm, g[5] * c, 0.0), axis=1),
            tl.sum(tl.where(qm, g[6] * c, 0.0), axis=1), tl.sum(tl.where(qm, g[7] * c, 0.0), axis=1),
            tl.sum(tl.where(qm, g[8] * c, 0.0), axis=1), tl.sum(tl.where(qm, g[9] * c, 0.0), axis=1))  # fmt: skip


@device_function
def _face_far(x, f, n, h, far_nodes, far_coef, Q, QT: tl.constexpr):
    """The collapsed Gauss rule of ``h int_T phi_i / |p - x|^4 dA``, differentiated under the sign
    (``face_far``), ``QT`` nodes at a time (tiles ``(BLOCK, QT)``)."""
    w0 = jconst(0.0, h)
    w1 = jconst(0.0, h)
    w2 = jconst(0.0, h)
    if QT == 1:  # node by node (a GPU: 2D tiles of one column cost the compiler minutes)
        for q in range(Q):
            base = (f * Q + q) * 3
            d = (tl.load(far_nodes + base) - x[0], tl.load(far_nodes + base + 1) - x[1],
                 tl.load(far_nodes + base + 2) - x[2])  # fmt: skip
            g = _far_integrand(d, n, h)
            w0 = jadd(w0, jscale(g, tl.load(far_coef + base)))
            w1 = jadd(w1, jscale(g, tl.load(far_coef + base + 1)))
            w2 = jadd(w2, jscale(g, tl.load(far_coef + base + 2)))
        return w0, w1, w2
    for q0 in range(0, Q, QT):
        qo = q0 + tl.arange(0, QT)
        ok = qo < Q
        qm = ok[None, :]
        base = (f * Q + qo) * 3
        d = (tl.load(far_nodes + base, mask=ok, other=0.0)[None, :] - x[0][:, None],
             tl.load(far_nodes + base + 1, mask=ok, other=0.0)[None, :] - x[1][:, None],
             tl.load(far_nodes + base + 2, mask=ok, other=0.0)[None, :] - x[2][:, None])  # fmt: skip
        g = _far_integrand(d, n, h[:, None])
        w0 = jadd(w0, _qsum(g, tl.load(far_coef + base, mask=ok, other=0.0)[None, :], qm))
        w1 = jadd(w1, _qsum(g, tl.load(far_coef + base + 1, mask=ok, other=0.0)[None, :], qm))
        w2 = jadd(w2, _qsum(g, tl.load(far_coef + base + 2, mask=ok, other=0.0)[None, :], qm))
    return w0, w1, w2


@device_function
def _near_edge(aj, ak, Ee, n, h, hj, h2, Pn, le, tol, gl_y, gl_w, ng, NG: tl.constexpr):
    """One edge of the split form with jets (``face_near_plane``): ``(s_e, T_e, S term, signed
    angle, outside)``: ``T_e = theta / |N|`` and the term of ``S`` with the powers of ``h`` divided
    out (the divided difference where the edge is seen under a small angle)."""
    Ne = _cross(aj, ak)
    En = _cross(Ee, n)
    qj = (aj[0] - h * n[0], aj[1] - h * n[1], aj[2] - h * n[2])
    qk = (ak[0] - h * n[0], ak[1] - h * n[1], ak[2] - h * n[2])
    se = jlinear(_dot(n, Ne), En[0], En[1], En[2])
    qq = jquad(_dot(qj, qk), -(qj[0] + qk[0]), -(qj[1] + qk[1]), -(qj[2] + qk[2]), Pn[0], Pn[1], Pn[2], Pn[3], Pn[4],
               Pn[5])  # fmt: skip
    d = jadd(qq, h2)
    l2 = le * le
    s2 = jmul(se, se)
    N2 = jadd(s2, jscale(h2, l2))
    sv = se[0]
    qv = qq[0]
    sig = tl.where(sv >= 0, 1.0, -1.0)
    sabs = tl.abs(sv)
    angle = sig * atan2(sabs, qv)
    dd = (qv > 0) & (sv * sv < 0.64 * qv * qv) & (N2[0] < d[0] * d[0])
    # the divided difference (small angle)
    d2 = jmul(d, d)
    qq2 = jmul(qq, qq)
    qs = jwhere(dd, qq, jconst(1.0, h))
    dsafe = jwhere(dd, d, jconst(1.0, h))
    U = jdiv(N2, jmul(dsafe, dsafe))
    u = jdiv(s2, jmul(qs, qs))
    Uv = tl.where(dd, U[0], 0.0)
    uv = tl.where(dd, u[0], 0.0)
    G0, G1, G2 = _g_fun(Uv, gl_y, gl_w, ng, NG)
    D0, D1, D2, D3, D4, D5 = _g_divdiff(Uv, uv, gl_y, gl_w, ng, NG)
    gU = jf1(U, G0, G1, G2)
    Dj = jf2(U, u, D0, D1, D2, D3, D4, D5)
    poly = jsub(jsub(jscale(qq2, l2), jscale(jmul(s2, qq), 2.0)), jmul(s2, h2))
    K = jsub(jmul(Dj, jdiv(poly, jmul(d2, jmul(qq2, qs)))), jdiv(gU, jmul(dsafe, qs)))
    S_dd = jmul(se, K)
    T_dd = jdiv(gU, dsafe)
    # the arctangent form
    sa = jscale(se, sig)
    th0 = jatan2(sa, qq)
    Nj = jsqrt(N2)
    Nps = jadd(Nj, sa)
    X = jsub(jscale(jdiv(qq, Nps), l2), sa)
    Y = jadd(jmul(d, qq), jmul(Nj, sa))
    r = jdiv(X, Y)
    A0, A1, A2 = atan_over(h * h * r[0])
    dh2 = jmul(r, jf1(jmul(h2, r), A0, A1, A2))
    th = jadd(th0, jmul(h2, dh2))
    T_at = jdiv(th, Nj)
    eps = jscale(jrecip(jmul(Nj, Nps)), l2)
    S_at = jscale(jsub(dh2, jmul(th, eps)), sig)
    return se, jwhere(dd, T_dd, T_at), jwhere(dd, S_dd, S_at), angle, sv < -tol * le


@device_function
def _pick(e, a, b, c):
    """Vector ``a``, ``b`` or ``c`` for ``e = 0, 1, 2`` (a loop index)."""
    return (tl.where(e == 0, a[0], tl.where(e == 1, b[0], c[0])), tl.where(e == 0, a[1], tl.where(e == 1, b[1], c[1])),
            tl.where(e == 0, a[2], tl.where(e == 1, b[2], c[2])))  # fmt: skip


@device_function
def _face_near(a0, a1, a2, f, n, h, A2, ell, gram, tol, gl_y, gl_w, ng, NG: tl.constexpr):
    """The split form near the support plane (``face_near_plane``): the three weight jets, the three
    singular jets ``k s_i`` (the weight's singular part is ``k s_i / h``; 0 unless the point sees the
    foot inside), whether the point lies on the face, its winding number (+-1 or 0). The edges run in a loop
    (one copy of the edge's code: the compile time stays in bounds)."""
    hj = jlinear(h, -n[0], -n[1], -n[2])
    h2 = jmul(hj, hj)
    Pn = (2.0 * (1.0 - n[0] * n[0]), 2.0 * (1.0 - n[1] * n[1]), 2.0 * (1.0 - n[2] * n[2]), -2.0 * n[0] * n[1],
          -2.0 * n[0] * n[2], -2.0 * n[1] * n[2])  # fmt: skip
    G = gram + 9 * f
    S = jconst(0.0, h)
    C0 = jconst(0.0, h)  # C_i = sum_e T_e (E_i . E_e)
    C1 = jconst(0.0, h)
    C2 = jconst(0.0, h)
    s0 = jconst(0.0, h)
    s1 = jconst(0.0, h)
    s2 = jconst(0.0, h)
    angle = tl.zeros_like(h)
    outside = h != h
    for e in range(3):
        aj = _pick(e, a1, a2, a0)
        ak = _pick(e, a2, a0, a1)
        se, Te, Se, we, oe = _near_edge(aj, ak, _sub(aj, ak), n, h, hj, h2, Pn, tl.load(ell + 3 * f + e), tol, gl_y,
                                        gl_w, ng, NG)  # fmt: skip
        S = jadd(S, Se)
        C0 = jadd(C0, jscale(Te, tl.load(G + e)))
        C1 = jadd(C1, jscale(Te, tl.load(G + 3 + e)))
        C2 = jadd(C2, jscale(Te, tl.load(G + 6 + e)))
        s0 = jwhere(e == 0, se, s0)
        s1 = jwhere(e == 1, se, s1)
        s2 = jwhere(e == 2, se, s2)
        angle += we
        outside = outside | oe
    on = ~outside & (tl.abs(h) <= tol)
    wind = tl.floor(angle / TWO_PI + 0.5)
    i4A = 1.0 / (2.0 * A2)
    k = TWO_PI * wind * i4A
    return (
        jscale(jmul(hj, jadd(jmul(s0, S), C0)), i4A),
        jscale(jmul(hj, jadd(jmul(s1, S), C1)), i4A),
        jscale(jmul(hj, jadd(jmul(s2, S), C2)), i4A),
        jscale(s0, k),
        jscale(s1, k),
        jscale(s2, k),
        on,
        wind,
    )


@device_function
def _acc(row, v, m, a):
    """``ACC[point, v] += a`` where ``m``."""
    base = row + 10 * v
    tl.store(base, tl.load(base, mask=m, other=0.0) + a[0], mask=m)
    tl.store(base + 1, tl.load(base + 1, mask=m, other=0.0) + a[1], mask=m)
    tl.store(base + 2, tl.load(base + 2, mask=m, other=0.0) + a[2], mask=m)
    tl.store(base + 3, tl.load(base + 3, mask=m, other=0.0) + a[3], mask=m)
    tl.store(base + 4, tl.load(base + 4, mask=m, other=0.0) + a[4], mask=m)
    tl.store(base + 5, tl.load(base + 5, mask=m, other=0.0) + a[5], mask=m)
    tl.store(base + 6, tl.load(base + 6, mask=m, other=0.0) + a[6], mask=m)
    tl.store(base + 7, tl.load(base + 7, mask=m, other=0.0) + a[7], mask=m)
    tl.store(base + 8, tl.load(base + 8, mask=m, other=0.0) + a[8], mask=m)
    tl.store(base + 9, tl.load(base + 9, mask=m, other=0.0) + a[9], mask=m)


@triton.jit
def _mvcd3d_kernel(
    X, xs, n, P, V, tri, T, nrm, two_area, ell, gram, longest, thin, far_nodes, far_coef, Q, far_c, near_c,
    gl_y, gl_w, ng, tol, thin_distance, ACC, SFACE, SWIND, flags, BLOCK: tl.constexpr, QT: tl.constexpr,
    NG: tl.constexpr, BATCHED: tl.constexpr = True,
):  # fmt: skip
    # one program: a block of points against cage cb (program index cb * blocks + block); the
    # topology and the quadrature tables are shared, the geometric tables have a leading cage axis.
    # One cage (BATCHED false, a compile-time constant): no cage offsets, which cost registers in a
    # kernel that spills already.
    pid = tl.program_id(0)
    if BATCHED:
        nblk = tl.cdiv(n, BLOCK)
        cb = (pid // nblk).to(tl.int64)
        offs = (pid % nblk) * BLOCK + tl.arange(0, BLOCK)
        P += cb * V * 3
        nrm += cb * T * 3
        two_area += cb * T
        ell += cb * T * 3
        gram += cb * T * 9
        longest += cb * T
        thin += cb * T
        far_nodes += cb * T * Q * 3
        far_coef += cb * T * Q * 3
        tol = tl.load(tol + cb)
        X += cb * xs
        point = cb * n + offs.to(tl.int64)
    else:
        offs = pid * BLOCK + tl.arange(0, BLOCK)
        tol = tl.load(tol)
        point = offs.to(tl.int64)
    live = offs < n
    x = (tl.load(X + 3 * offs, mask=live, other=0.0), tl.load(X + 3 * offs + 1, mask=live, other=0.0),
         tl.load(X + 3 * offs + 2, mask=live, other=0.0))  # fmt: skip
    row = ACC + point * (10 * V)
    for k in range(10 * V):
        tl.store(row + k, tl.zeros_like(x[0]), mask=live)
    redo = offs < 0
    # the kept singular part: its face's h and normal, the jets k s_i, their vertices
    has = offs < 0
    sh = tl.zeros_like(x[0])
    sn = (tl.zeros_like(x[0]), tl.zeros_like(x[0]), tl.zeros_like(x[0]))
    ss0 = jconst(0.0, x[0])
    ss1 = jconst(0.0, x[0])
    ss2 = jconst(0.0, x[0])
    si0 = tl.zeros_like(offs) - 1
    si1 = tl.zeros_like(offs) - 1
    si2 = tl.zeros_like(offs) - 1
    sf = tl.zeros_like(offs) - 1
    swind = tl.zeros_like(x[0])
    for f in range(T):
        i0 = tl.load(tri + 3 * f)
        i1 = tl.load(tri + 3 * f + 1)
        i2 = tl.load(tri + 3 * f + 2)
        a0 = (tl.load(P + 3 * i0) - x[0], tl.load(P + 3 * i0 + 1) - x[1], tl.load(P + 3 * i0 + 2) - x[2])
        a1 = (tl.load(P + 3 * i1) - x[0], tl.load(P + 3 * i1 + 1) - x[1], tl.load(P + 3 * i1 + 2) - x[2])
        a2 = (tl.load(P + 3 * i2) - x[0], tl.load(P + 3 * i2 + 1) - x[1], tl.load(P + 3 * i2 + 2) - x[2])
        rmin = tl.sqrt(tl.minimum(tl.minimum(_dot(a0, a0), _dot(a1, a1)), _dot(a2, a2)))
        nv = (tl.load(nrm + 3 * f), tl.load(nrm + 3 * f + 1), tl.load(nrm + 3 * f + 2))
        h = _dot(nv, a0)
        A2 = tl.load(two_area + f)
        at_vertex = rmin <= tol
        far = tl.load(longest + f) <= far_c * rmin
        near = (tl.abs(h) < near_c * rmin) & ~far
        direct = ~far & ~near & ~at_vertex
        if tl.load(thin + f) != 0:
            redo = redo | _thin_pair(x[0], x[1], x[2], f, P, tri, two_area, thin_distance)
        hs = tl.where(direct, h, 1.0)
        w0 = jconst(0.0, h)
        w1 = jconst(0.0, h)
        w2 = jconst(0.0, h)
        if tl.sum((direct & live).to(tl.int32)) > 0:
            d0, d1, d2 = _face_direct(a0, a1, a2, A2, hs)
            w0 = jwhere(direct, d0, w0)
            w1 = jwhere(direct, d1, w1)
            w2 = jwhere(direct, d2, w2)
        if tl.sum((far & live).to(tl.int32)) > 0:
            q0, q1, q2 = _face_far(x, f, nv, h, far_nodes, far_coef, Q, QT)
            w0 = jwhere(far, q0, w0)
            w1 = jwhere(far, q1, w1)
            w2 = jwhere(far, q2, w2)
        near = near & ~at_vertex
        if tl.sum((near & live).to(tl.int32)) > 0:
            e0, e1, e2, g0, g1, g2, on, wind = _face_near(a0, a1, a2, f, nv, h, A2, ell, gram, tol, gl_y, gl_w, ng, NG)
            w0 = jwhere(near, e0, w0)
            w1 = jwhere(near, e1, w1)
            w2 = jwhere(near, e2, w2)
            redo = redo | (near & on)
            m2 = near & (wind != 0) & ~on & live
            nearer = tl.abs(h) < tl.abs(sh)
            old = m2 & has & nearer  # the kept part folds back in, this face's is kept
            new = m2 & has & ~nearer  # this face's part folds in
            take = m2 & (~has | nearer)
            if tl.sum(old.to(tl.int32)) > 0:
                hold = jlinear(tl.where(old, sh, 1.0), -sn[0], -sn[1], -sn[2])
                for i in range(3):  # (a loop: one copy of the accumulation's code)
                    _acc(row, tl.where(i == 0, si0, tl.where(i == 1, si1, si2)), old,
                         jdiv(jwhere(i == 0, ss0, jwhere(i == 1, ss1, ss2)), hold))  # fmt: skip
            if tl.sum(new.to(tl.int32)) > 0:  # (the same vertices as this face's weights)
                hnew = jlinear(tl.where(new, h, 1.0), -nv[0], -nv[1], -nv[2])
                w0 = jadd(w0, jwhere(new, jdiv(g0, hnew), jconst(0.0, h)))
                w1 = jadd(w1, jwhere(new, jdiv(g1, hnew), jconst(0.0, h)))
                w2 = jadd(w2, jwhere(new, jdiv(g2, hnew), jconst(0.0, h)))
            sh = tl.where(take, h, sh)
            sn = (tl.where(take, nv[0], sn[0]), tl.where(take, nv[1], sn[1]), tl.where(take, nv[2], sn[2]))
            ss0 = jwhere(take, g0, ss0)
            ss1 = jwhere(take, g1, ss1)
            ss2 = jwhere(take, g2, ss2)
            si0 = tl.where(take, i0, si0)
            si1 = tl.where(take, i1, si1)
            si2 = tl.where(take, i2, si2)
            sf = tl.where(take, f, sf)
            swind = tl.where(take, wind, swind)
            has = has | m2
        redo = redo | at_vertex
        keep = live & ~at_vertex
        for i in range(3):
            _acc(row, tl.where(i == 0, i0, tl.where(i == 1, i1, i2)), keep, jwhere(i == 0, w0, jwhere(i == 1, w1, w2)))
    # the kept face and its winding: the caller rebuilds k s_i and h from them (a few stores: every
    # memory operation costs the compiler's coalescing pass time)
    tl.store(SFACE + point, tl.where(has, sf, -1), mask=live)
    tl.store(SWIND + point, swind, mask=live)
    tl.store(flags + point, tl.where(redo, 1, 0), mask=live)


def derivative_tables(cage: Cage, device: torch.device) -> dict[str, object]:
    """The kernel's arguments for one cage (a batch of one): the native kernel's tables (float64)
    on ``device``."""
    return _triton_tables(native_tables(cage), device)


def batch_tables(vertices: torch.Tensor, tri: torch.Tensor, tol: torch.Tensor) -> dict[str, object]:
    """The kernel's arguments for a batch of cages with one topology (the native kernel's tables,
    built by one set of tensor operations on the vertices' device).

    Args:
        vertices: ``(B, V, 3)`` float64 vertices on the kernel's device.
        tri: ``(T, 3)`` the shared triangles.
        tol: ``(B,)`` absolute on-cage tolerances.
    """
    dev = vertices.device
    return _triton_tables(face_tables(vertices, tri.to(dev), tol.to(dev)), dev)


def _triton_tables(t: dict[str, object], device: torch.device) -> dict[str, object]:
    """The native tables ``t`` (a leading cage axis) as the kernel's: the native-only edge tables
    dropped, the thin faces flagged, on ``device``."""
    out = {
        k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in t.items() if k not in ("fe", "NE", "E", "B")
    }
    out["thin"] = ((out["two_area"] > 0) & (out["longest"] ** 2 > THIN_ASPECT * out["two_area"])).to(torch.int32)
    out["thin_distance"] = THIN_DISTANCE
    return out


_I = (0, 1, 2, 0, 0, 1)
_J = (0, 1, 2, 1, 2, 2)


def _jet_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Product of jets ``(..., 10)`` (value, gradient, Hessian xx yy zz xy xz yz), broadcast."""
    av, bv = a[..., :1], b[..., :1]
    ag, bg = a[..., 1:4], b[..., 1:4]
    i, j = list(_I), list(_J)
    h = av * b[..., 4:] + bv * a[..., 4:] + ag[..., i] * bg[..., j] + ag[..., j] * bg[..., i]
    return torch.cat([av * bv, av * bg + bv * ag, h], dim=-1)


def _jet_recip(a: torch.Tensor) -> torch.Tensor:
    """``1 / a`` of jets ``(..., 10)``."""
    r = 1.0 / a[..., :1]
    f1, f2 = -r * r, 2 * r * r * r
    g = a[..., 1:4]
    i, j = list(_I), list(_J)
    return torch.cat([r, f1 * g, f1 * a[..., 4:] + f2 * g[..., i] * g[..., j]], dim=-1)


def _linear_jet(value: torch.Tensor, grad: torch.Tensor) -> torch.Tensor:
    """Jets ``(m, 10)`` of affine functions: values ``(m,)``, gradients ``(m, 3)``."""
    out = torch.zeros(value.shape[0], 10, dtype=value.dtype, device=value.device)
    out[:, 0], out[:, 1:4] = value, grad
    return out


def _totals(acc: torch.Tensor, xs: torch.Tensor, P: torch.Tensor) -> torch.Tensor:
    """The normaliser of each point as a jet ``(B, n, 10)``: the sum of the weights ``acc``
    ``(B, n, V, 10)``, or far from the cage ``P`` ``(B, V, 3)`` their first moment
    ``(sum_v w_v (P_v - c)) . y / |y|^2`` (``y = x - c``, points ``xs`` ``(B, n, 3)``)."""
    c = 0.5 * (P.amin(dim=1) + P.amax(dim=1))  # (B, 3)
    Pc = P - c[:, None]
    far2 = FAR_MOMENT * FAR_MOMENT * (Pc**2).sum(dim=-1).amax(dim=-1)  # (B,)
    y = xs - c[:, None]
    y2 = (y * y).sum(dim=-1)
    total = acc.sum(dim=2)
    far = y2 > far2[:, None]
    if bool(far.any()):
        bi, ni = torch.nonzero(far, as_tuple=True)
        a = acc[bi, ni]
        # (m, 3, 10); one cage: its vertices shared by the rows, as the single-cage kernel always did
        S = torch.einsum("nvk,vd->ndk", a, Pc[0]) if P.shape[0] == 1 else torch.einsum("mvk,mvd->mdk", a, Pc[bi])
        eye = torch.eye(3, dtype=P.dtype, device=P.device)
        yj = torch.zeros(S.shape[0], 3, 10, dtype=P.dtype, device=P.device)
        yj[..., 0], yj[..., 1:4] = y[bi, ni], eye
        num = _jet_mul(S, yj).sum(dim=1)
        den = torch.zeros_like(num)
        den[:, 0], den[:, 1:4], den[:, 4:7] = y2[bi, ni], 2 * y[bi, ni], 2.0
        total[bi, ni] = _jet_mul(num, _jet_recip(den))
    return total


def _singular(
    x: torch.Tensor, cage: torch.Tensor, face: torch.Tensor, wind: torch.Tensor, tables: dict[str, object]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The kept singular part of points ``x (m, 3)`` of cages ``cage (m,)`` next to faces
    ``face (m,)`` of winding ``wind``: the jets ``(m, 10)`` of ``h = n . (p_0 - x)``, ``(m, 3, 10)``
    of ``k s_i`` (``s_i = n . N_i``, ``k = 2 pi wind / (4 area)``; affine in ``x``) and the corners'
    vertices ``(m, 3)``."""
    idx = tables["tri"][face].long()  # (m, 3)
    p = tables["P"][cage[:, None], idx]  # (m, 3, 3)
    a = p - x[:, None, :]
    n = tables["nrm"][cage, face]  # (m, 3)
    h = (n * a[:, 0]).sum(dim=1)
    N = torch.cross(a.roll(-1, dims=1), a.roll(-2, dims=1), dim=2)  # N_i = a_{i+1} x a_{i+2}
    E = p.roll(-1, dims=1) - p.roll(-2, dims=1)
    k = 2.0 * torch.pi * wind / (2.0 * tables["two_area"][cage, face])
    ks = torch.zeros(x.shape[0], 3, 10, dtype=x.dtype, device=x.device)
    ks[..., 0] = k[:, None] * (N * n[:, None, :]).sum(dim=2)
    ks[..., 1:4] = k[:, None, None] * torch.cross(E, n[:, None, :].expand_as(E), dim=2)
    return _linear_jet(h, -n), ks, idx


def mvcd3d_triton(
    x: torch.Tensor, cage: Cage, order: int, block: int | None = None, tables: dict[str, object] | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Coordinates ``lam (n, V)``, gradients ``(n, V, 3)``, Hessians ``(n, V, 3, 3)`` (empty for
    ``order=1``) and flags ``(n,)`` (uint8: 1 on the cage, 2 the total weight vanishes) of points
    ``x (n, 3)``, in float64 on the points' device (as every backend of the derivatives: in float32
    the jets of far points overflow). Points on the cage or next to a thin face are redone by the
    torch kernel's derivatives (:mod:`.derivatives_torch`), on the same device.

    The public way in is ``F.mean_value_derivatives(points, cage, backend="triton")`` (or
    ``"auto"`` for CUDA points); the autograd Functions take it for CUDA points. ``tables``:
    :func:`derivative_tables` of the cage on the points' device (built here when ``None``).
    """
    if tables is None:
        tables = derivative_tables(cage, x.device)
    xs = x.detach().to(torch.float64)[None]
    lam, grad, hess, out = mvcd3d_triton_batch(xs, tables, order, [cage], block)
    return lam[0], grad[0], hess[0] if order == 2 else hess, out[0]


def mvcd3d_triton_batch(
    x: torch.Tensor,
    tables: dict[str, object],
    order: int,
    cages: list[Cage],
    block: int | None = None,
    extents: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`mvcd3d_triton` for a batch of ``B`` cages with one topology in one launch: float64
    points ``x`` ``(B, n, 3)``, or ``(1, n, 3)`` shared by every cage, on the tables' device
    (:func:`batch_tables`) -> ``lam (B, n, V)``, ``grad (B, n, V, 3)``, ``hess (B, n, V, 3, 3)``
    (empty for ``order=1``) and the uint8 flags ``(B, n)``. ``cages``: each cage (``B`` of them),
    for the points redone by the torch kernel (on a cage, next to a thin face), cage by cage;
    ``extents`` ``(B,)``: the largest coordinate of each uncentred cage (their redo's on-cage tolerance, as
    :func:`torchcage._core.centre.keep_extent` gives the single-cage call). Element by element the
    numbers of :func:`mvcd3d_triton`, to rounding.

    Raises:
        ValueError: points whose batch is neither 1 nor the cages'.
    """
    dtype = torch.float64
    P = tables["P"]
    B, V = P.shape[0], tables["V"]  # type: ignore[attr-defined]
    X, _ = point_batch(x, B, "mvcd3d_triton_batch")
    XB, n = X.shape[0], X.shape[1]
    dev = X.device
    acc = torch.empty((B, n, V, 10), dtype=dtype, device=dev)
    sface = torch.empty((B, n), dtype=torch.int32, device=dev)
    swind = torch.empty((B, n), dtype=dtype, device=dev)
    flags = torch.empty((B, n), dtype=torch.int32, device=dev)
    if block is None:
        block = min(512, triton.next_power_of_2(max(n, 16))) if interpreted() else 32
    # quadrature nodes per step: all at once in the interpreter (one numpy op per step), one on a GPU
    tile = triton.next_power_of_2(int(tables["Q"])) if interpreted() else 1  # type: ignore[call-overload]
    gtile = triton.next_power_of_2(int(tables["ng"])) if interpreted() else 1  # type: ignore[call-overload]
    if n:
        _mvcd3d_kernel[(B * triton.cdiv(n, block),)](
            X, 0 if XB == 1 else 3 * n, n, **tables, ACC=acc, SFACE=sface, SWIND=swind, flags=flags, BLOCK=block,
            QT=tile, NG=gtile, BATCHED=B > 1, num_warps=warps(block),
        )  # fmt: skip
    Xb = X.expand(B, n, 3)
    total = _totals(acc, Xb, P)  # type: ignore[arg-type]
    num = acc
    bi, ni = torch.nonzero(sface >= 0, as_tuple=True)
    if bi.numel():  # lam_v = (k s_v + h r_v) / (k sum s + h sum r)
        hj, ks, idx = _singular(Xb[bi, ni], bi, sface[bi, ni].long(), swind[bi, ni], tables)
        num = acc.clone()
        num[bi, ni] = _jet_mul(hj[:, None, :], acc[bi, ni])
        for i in range(3):
            num[bi, ni, idx[:, i]] += ks[:, i]
        total = total.clone()
        total[bi, ni] = _jet_mul(hj, acc[bi, ni].sum(dim=1)) + ks.sum(dim=1)
    redo = flags == 1
    bad = ~redo & ~((total[..., 0] != 0) & torch.isfinite(total[..., 0]))
    safe = torch.where(bad[..., None], torch.ones_like(total), total)
    lam10 = _jet_mul(num, _jet_recip(safe)[:, :, None, :])  # (B, n, V, 10)
    lam = lam10[..., 0].contiguous()
    grad = lam10[..., 1:4].contiguous()
    hess = torch.empty((B, n, V, 3, 3) if order == 2 else (0,), dtype=dtype, device=dev)
    if order == 2:
        hess = lam10[..., [4, 7, 8, 7, 5, 9, 8, 9, 6]].reshape(B, n, V, 3, 3).contiguous()
    out = torch.where(bad, 2, 0).to(torch.uint8)
    for b in torch.nonzero(redo.any(dim=1)).flatten().tolist():  # (rare: on a cage, next to a thin face)
        rows = torch.nonzero(redo[b]).flatten()
        with keep_extent(float(extents[b]) if extents is not None else 0.0):
            lr, gr, hr, onr = torch_derivatives(Xb[b, rows], cages[b], order)
        lam[b, rows], grad[b, rows] = lr, gr
        if order == 2:
            hess[b, rows] = hr
        out[b, rows] = onr.to(torch.uint8)
    return lam, grad, hess, out
