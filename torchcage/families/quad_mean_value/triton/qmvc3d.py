"""Triton kernel of quad mean value coordinates (the quads of a quad or triquad cage): the formulas
and thresholds of the native kernel (``torchcage/backends/native/qmvc3d.c``; derivation in
:mod:`.kernel`), a block of points per program and a loop over the quads.

Per point–quad pair: the kernel ``kappa`` of ``A = [p_0 .. p_3]`` and the rows of its
pseudo-inverse (Cramer form), the mean vector, the smooth projection ``(u, v)`` of Algorithm 1
(the tetrahedron's hull faces' weights where the point is outside it), the adaptive ``(2n+1)^2``
Riemann sum of the corner integrals around ``(u, v)``, the least-norm solution plus the
norm-corrected ``lambda kappa``, the split triangles' stable weights near a flat quad's plane, and
the order-4 Gauss rule for quads seen small (blended in by ``log10`` of the distance). Triangles
(the mean value form of :mod:`torchcage.families.mean_value.triton.mvc3d`, raw weights) are added
by the caller before this kernel runs; the normalisation is the caller's too. The exact integrals
(``tol``) are not here: the caller takes the torch kernel for them.

Shapes: ``P (V, 3)``, ``quads (Q, 4)`` int32, per-quad tables ``(Q, ...)``, ``X (n, 3)``; ``W (n, V)``
in/out (raw weights: the triangles' on entry, plus the quads' on exit), ``flags (n,)`` int32 in/out
(1: the row is final, on the cage). A batch of ``B`` cages with one topology is one launch (a
program per cage and block of points): ``quads`` and the Gauss table are shared, the vertices, the
per-quad tables and the tolerance carry a leading cage axis, ``X (B or 1, n, 3)``, ``W (B, n, V)``,
``flags (B, n)``; one cage is a batch of one.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from torchcage.backends.triton import device_function, interpreted, point_batch, warps
from torchcage.backends.triton.common import log
from torchcage.families.mean_value.triton.mvc3d import TRITON_SPLIT_FORM_RATIO, _half_angle, face_form
from torchcage.families.quad_mean_value.kernel import (
    FAR_QUAD_LOG,
    GAUSS4,
    NEAR_FLAT,
    ON_QUAD_BAND,
    REFINE,
    QuadData,
    quad_sizes,
)

__all__ = ["batch_tables", "qmvc3d_triton", "triton_tables"]

INV_LN10 = tl.constexpr(0.4342944819032518)
FAR_LO = tl.constexpr(FAR_QUAD_LOG[0])
FAR_SPAN = tl.constexpr(FAR_QUAD_LOG[1] - FAR_QUAD_LOG[0])
NEAR_FLAT_C = tl.constexpr(NEAR_FLAT)
BAND2 = tl.constexpr(ON_QUAD_BAND * ON_QUAD_BAND)
NREFINE = tl.constexpr(REFINE)
#: ``16 eps`` (float64): the rounding level of ``kappa`` (relative to ``sum_i prod_{j != i} |p_j|``).
NOISE = tl.constexpr(16.0 * 2.220446049250313e-16)
BIG = tl.constexpr(1e300)
#: The split form of the hull and split triangles (as the mean value kernel's,
#: :mod:`torchcage.families.mean_value.triton.mvc3d`).
SPLIT = tl.constexpr(TRITON_SPLIT_FORM_RATIO)


@device_function
def _cross(ax, ay, az, bx, by, bz):
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


@device_function
def _dot(ax, ay, az, bx, by, bz):
    return ax * bx + ay * by + az * bz


@device_function
def _edge_term(cx, cy, cz, ax, ay, az, bx, by, bz, Ra, Rb):
    """``theta_ab / (2 |p_a x p_b|)`` from ``c = p_a x p_b`` (0 where ``c`` vanishes)."""
    c2 = cx * cx + cy * cy + cz * cz
    cn = tl.sqrt(c2)
    theta = _half_angle(cn, _dot(ax, ay, az, bx, by, bz), Ra * Rb)
    return tl.where(c2 > 0, 0.5 * theta / tl.where(c2 > 0, cn, 1.0), 0.0)


@device_function
def _corner(P, i, x0, x1, x2):
    """Vertex ``i`` of ``P`` minus the block's points."""
    return tl.load(P + 3 * i) - x0, tl.load(P + 3 * i + 1) - x1, tl.load(P + 3 * i + 2) - x2


@device_function
def _pick(j, v0, v1, v2, v3):
    """``v_j`` for a scalar ``j`` in 0..3."""
    return tl.where(j == 0, v0, tl.where(j == 1, v1, tl.where(j == 2, v2, v3)))


@triton.jit
def _corner_triangle(ax, ay, az, bx, by, bz, cx, cy, cz):
    """Mean value weights of the triangle ``(a, b, c)`` (corners minus the point), its geometry
    taken from the corners (as ``triangle_weights`` in the native kernel): ``(w_a, w_b, w_c, ok)``,
    ``ok`` False for a triangle of no area (no weights)."""
    e1x = bx - ax
    e1y = by - ay
    e1z = bz - az
    e2x = cx - ax
    e2y = cy - ay
    e2z = cz - az
    nx, ny, nz = _cross(e1x, e1y, e1z, e2x, e2y, e2z)
    A2 = tl.sqrt(nx * nx + ny * ny + nz * nz)
    ok = A2 > 0
    inv = 1.0 / tl.where(ok, A2, 1.0)
    # edges opposite each corner: E0 = b - c, E1 = c - a, E2 = a - b
    E0x = bx - cx
    E0y = by - cy
    E0z = bz - cz
    E1x = cx - ax
    E1y = cy - ay
    E1z = cz - az
    E2x = ax - bx
    E2y = ay - by
    E2z = az - bz
    g00 = _dot(E0x, E0y, E0z, E0x, E0y, E0z)
    g11 = _dot(E1x, E1y, E1z, E1x, E1y, E1z)
    g22 = _dot(E2x, E2y, E2z, E2x, E2y, E2z)
    g01 = _dot(E0x, E0y, E0z, E1x, E1y, E1z)
    g02 = _dot(E0x, E0y, E0z, E2x, E2y, E2z)
    g12 = _dot(E1x, E1y, E1z, E2x, E2y, E2z)
    w0, w1, w2, _s0, _s1, _s2, _h, _rmin, _R0, _R1, _R2, _split, _dead = face_form(
        ax, ay, az, bx, by, bz, cx, cy, cz, nx * inv, ny * inv, nz * inv, A2,
        tl.sqrt(g00), tl.sqrt(g11), tl.sqrt(g22), g00, g01, g02, g01, g11, g12, g02, g12, g22,
        0.0, SPLIT,
    )  # fmt: skip
    return w0, w1, w2, ok


@device_function
def _node(k, t, n, zero):
    """Node ``k`` of the adaptive grid of ``2n + 1`` nodes with node ``n`` at ``t`` (``k / n`` of
    the way to ``t``, then on to 1; ``k > 2n`` is the last node, 1, and ``k < 0`` the first, 0)."""
    s = tl.maximum(tl.minimum((zero + k) / n, 2.0), 0.0)
    return tl.where(s <= 1.0, s * t, t + (s - 1.0) * (1.0 - t))


@triton.jit
def _qmvc3d_kernel(
    X, xs, n, P, V, quads, Q, geom, area2, size, gauss, tol, N, W, flags, BLOCK: tl.constexpr,
    BATCHED: tl.constexpr = True,
):  # fmt: skip
    # one program: a block of points against cage b (program index b * blocks + block); the quads
    # and the Gauss table are shared, every other table has a leading cage axis. One cage (BATCHED
    # false, a compile-time constant): no cage offsets, so a single cage's launch keeps its registers.
    pid = tl.program_id(0)
    if BATCHED:
        nblk = tl.cdiv(n, BLOCK)
        cb = (pid // nblk).to(tl.int64)  # (the cage; the body's own b is a loop variable)
        offs = (pid % nblk) * BLOCK + tl.arange(0, BLOCK)
        P += cb * V * 3
        geom += cb * Q * 18
        area2 += cb * Q
        size += cb * Q
        tol = tl.load(tol + cb)
        X += cb * xs
        point = cb * n + offs.to(tl.int64)
    else:
        offs = pid * BLOCK + tl.arange(0, BLOCK)
        tol = tl.load(tol)
        point = offs.to(tl.int64)
    live = offs < n
    x0 = tl.load(X + 3 * offs, mask=live, other=0.0)
    x1 = tl.load(X + 3 * offs + 1, mask=live, other=0.0)
    x2 = tl.load(X + 3 * offs + 2, mask=live, other=0.0)
    row = W + point * V
    zero = tl.zeros_like(x0)
    done = (tl.load(flags + point, mask=live, other=1) == 1) | ~live  # final rows (on a triangle)
    hit = offs < 0  # on a quad: the bilinear values of the first quad holding the point
    h0 = tl.zeros_like(offs)
    h1 = tl.zeros_like(offs)
    h2 = tl.zeros_like(offs)
    h3 = tl.zeros_like(offs)
    hu = zero
    hv = zero
    # (tol is read from its float64 table; its square is taken per lane, in float64, where a tiny
    # cage's tolerance does not underflow)
    tolv = zero + tol
    tol2 = tolv * tolv
    K = 2 * N + 1
    for q in range(Q):
        i0 = tl.load(quads + 4 * q)
        i1 = tl.load(quads + 4 * q + 1)
        i2 = tl.load(quads + 4 * q + 2)
        i3 = tl.load(quads + 4 * q + 3)
        p0x, p0y, p0z = _corner(P, i0, x0, x1, x2)
        p1x, p1y, p1z = _corner(P, i1, x0, x1, x2)
        p2x, p2y, p2z = _corner(P, i2, x0, x1, x2)
        p3x, p3y, p3z = _corner(P, i3, x0, x1, x2)
        S0 = _dot(p0x, p0y, p0z, p0x, p0y, p0z)
        S1 = _dot(p1x, p1y, p1z, p1x, p1y, p1z)
        S2 = _dot(p2x, p2y, p2z, p2x, p2y, p2z)
        S3 = _dot(p3x, p3y, p3z, p3x, p3y, p3z)
        R0 = tl.sqrt(S0)
        R1 = tl.sqrt(S1)
        R2 = tl.sqrt(S2)
        R3 = tl.sqrt(S3)
        # the nearest corner within tol (-1: none)
        vertex = tl.where(S0 <= tol2, 0, -1)
        best = tl.where(S0 <= tol2, S0, BIG)
        vertex = tl.where((S1 <= tol2) & (S1 < best), 1, vertex)
        best = tl.where((S1 <= tol2) & (S1 < best), S1, best)
        vertex = tl.where((S2 <= tol2) & (S2 < best), 2, vertex)
        best = tl.where((S2 <= tol2) & (S2 < best), S2, best)
        vertex = tl.where((S3 <= tol2) & (S3 < best), 3, vertex)
        # c_ab = p_a x p_b, the kernel kappa and the rows of |kappa|^2 A^+ (Cramer form)
        c01x, c01y, c01z = _cross(p0x, p0y, p0z, p1x, p1y, p1z)
        c02x, c02y, c02z = _cross(p0x, p0y, p0z, p2x, p2y, p2z)
        c03x, c03y, c03z = _cross(p0x, p0y, p0z, p3x, p3y, p3z)
        c12x, c12y, c12z = _cross(p1x, p1y, p1z, p2x, p2y, p2z)
        c13x, c13y, c13z = _cross(p1x, p1y, p1z, p3x, p3y, p3z)
        c23x, c23y, c23z = _cross(p2x, p2y, p2z, p3x, p3y, p3z)
        k0 = _dot(p1x, p1y, p1z, c23x, c23y, c23z)
        k1 = _dot(p2x, p2y, p2z, c03x, c03y, c03z)
        k2 = _dot(p3x, p3y, p3z, c01x, c01y, c01z)
        k3 = -_dot(p0x, p0y, p0z, c12x, c12y, c12z)
        r0x = -k1 * c23x + k2 * c13x - k3 * c12x
        r0y = -k1 * c23y + k2 * c13y - k3 * c12y
        r0z = -k1 * c23z + k2 * c13z - k3 * c12z
        r1x = k0 * c23x - k2 * c03x + k3 * c02x
        r1y = k0 * c23y - k2 * c03y + k3 * c02y
        r1z = k0 * c23z - k2 * c03z + k3 * c02z
        r2x = -k0 * c13x + k1 * c03x - k3 * c01x
        r2y = -k0 * c13y + k1 * c03y - k3 * c01y
        r2z = -k0 * c13z + k1 * c03z - k3 * c01z
        r3x = k0 * c12x - k1 * c02x + k2 * c01x
        r3y = k0 * c12y - k1 * c02y + k2 * c01y
        r3z = k0 * c12z - k1 * c02z + k2 * c01z
        D = k0 * k0 + k1 * k1 + k2 * k2 + k3 * k3
        # the mean vector (Eq. 16): the quad's four boundary edges
        g01 = _edge_term(c01x, c01y, c01z, p0x, p0y, p0z, p1x, p1y, p1z, R0, R1)
        g12 = _edge_term(c12x, c12y, c12z, p1x, p1y, p1z, p2x, p2y, p2z, R1, R2)
        g23 = _edge_term(c23x, c23y, c23z, p2x, p2y, p2z, p3x, p3y, p3z, R2, R3)
        g03 = _edge_term(c03x, c03y, c03z, p0x, p0y, p0z, p3x, p3y, p3z, R0, R3)
        mx = g01 * c01x + g12 * c12x + g23 * c23x - g03 * c03x
        my = g01 * c01y + g12 * c12y + g23 * c23y - g03 * c03y
        mz = g01 * c01z + g12 * c12z + g23 * c23z - g03 * c03z
        kabs = tl.abs(k0) + tl.abs(k1) + tl.abs(k2) + tl.abs(k3)
        # kappa vanishes only for a planar quad and a point on its plane (|kappa|_1 = |h| sum 2 A_i)
        flat = kabs <= tol * tl.load(area2 + q)
        alpha = k0 + k1 + k2 + k3
        sgn = tl.where(alpha >= 0, 1.0, -1.0)
        lo = -1e-13 * kabs
        inside = (alpha != 0) & (k0 * sgn >= lo) & (k1 * sgn >= lo) & (k2 * sgn >= lo) & (k3 * sgn >= lo)
        inside = inside & (kabs > NOISE * (R1 * R2 * R3 + R0 * R2 * R3 + R0 * R1 * R3 + R0 * R1 * R2))
        # the sheet xi(u, v) - x = p0 + u b + v c + u v d and its normal N0 + u Nu + v Nv
        G = geom + 18 * q
        bx = tl.load(G)
        by = tl.load(G + 1)
        bz = tl.load(G + 2)
        ccx = tl.load(G + 3)
        ccy = tl.load(G + 4)
        ccz = tl.load(G + 5)
        ddx = tl.load(G + 6)
        ddy = tl.load(G + 7)
        ddz = tl.load(G + 8)
        N0x = tl.load(G + 9)
        N0y = tl.load(G + 10)
        N0z = tl.load(G + 11)
        Nux = tl.load(G + 12)
        Nuy = tl.load(G + 13)
        Nuz = tl.load(G + 14)
        Nvx = tl.load(G + 15)
        Nvy = tl.load(G + 16)
        Nvz = tl.load(G + 17)
        sz = tl.load(size + q)
        Rmax = tl.maximum(tl.maximum(R0, R1), tl.maximum(R2, R3))
        todo = ~done
        hull = todo & ~flat & ~inside & (vertex < 0)
        near_flat = todo & ~flat & ~inside & (kabs < NEAR_FLAT_C * sz * sz * Rmax)
        # the direction of the projection: the quad's normal (flat), the mean vector (inside the
        # tetrahedron, or at a corner), else the mean vector seen from the hull faces' weighted centre
        dx = tl.where(flat, N0x + 0.5 * (Nux + Nvx), mx)
        dy = tl.where(flat, N0y + 0.5 * (Nuy + Nvy), my)
        dz = tl.where(flat, N0z + 0.5 * (Nuz + Nvz), mz)
        q0x = p0x
        q0y = p0y
        q0z = p0z
        q1x = p1x
        q1y = p1y
        q1z = p1z
        q2x = p2x
        q2y = p2y
        q2z = p2z
        q3x = p3x
        q3y = p3y
        q3z = p3z
        # triangles: the four hull faces (0 1 3), (1 2 3), (0 2 1), (0 3 2), then the split
        # triangles (0 1 2), (0 2 3) near a flat quad's plane
        a0 = zero  # the hull faces' |weights| per corner
        a1 = zero
        a2 = zero
        a3 = zero
        wp0 = zero  # the split triangles' weights
        wp1 = zero
        wp2 = zero
        wp3 = zero
        wp_ok = near_flat
        for f in range(6):
            need = tl.where(f < 4, hull, near_flat)
            if tl.sum(need.to(tl.int32)) > 0:
                ja = (f == 1) * 1
                jb = 2 - (f == 0) * 1 - (f == 4) * 1 + (f == 3) * 1
                jc = 3 - (f == 2) * 2 - (f == 3) * 1 - (f == 4) * 1
                wa, wb, wc, ok = _corner_triangle(
                    _pick(ja, p0x, p1x, p2x, p3x), _pick(ja, p0y, p1y, p2y, p3y), _pick(ja, p0z, p1z, p2z, p3z),
                    _pick(jb, p0x, p1x, p2x, p3x), _pick(jb, p0y, p1y, p2y, p3y), _pick(jb, p0z, p1z, p2z, p3z),
                    _pick(jc, p0x, p1x, p2x, p3x), _pick(jc, p0y, p1y, p2y, p3y), _pick(jc, p0z, p1z, p2z, p3z),
                )  # fmt: skip
                if f < 4:
                    ea = tl.where(ok & (tl.abs(wa) < BIG), tl.abs(wa), 0.0)
                    eb = tl.where(ok & (tl.abs(wb) < BIG), tl.abs(wb), 0.0)
                    ec = tl.where(ok & (tl.abs(wc) < BIG), tl.abs(wc), 0.0)
                    a0 += tl.where(ja == 0, ea, 0.0)
                    a1 += tl.where(ja == 1, ea, 0.0) + tl.where(jb == 1, eb, 0.0) + tl.where(jc == 1, ec, 0.0)
                    a2 += tl.where(jb == 2, eb, 0.0) + tl.where(jc == 2, ec, 0.0)
                    a3 += tl.where(jb == 3, eb, 0.0) + tl.where(jc == 3, ec, 0.0)
                else:
                    wp_ok = wp_ok & ok & (tl.abs(wa) + tl.abs(wb) + tl.abs(wc) < BIG)
                    wp0 += wa
                    wp1 += tl.where(jb == 1, wb, 0.0)
                    wp2 += tl.where(jb == 2, wb, 0.0) + tl.where(jc == 2, wc, 0.0)
                    wp3 += tl.where(jc == 3, wc, 0.0)
        if tl.sum(hull.to(tl.int32)) > 0:
            den = a0 + a1 + a2 + a3
            moved = hull & (den > 0)
            sd = tl.where(moved, den, 1.0)
            ox = tl.where(moved, (a0 * p0x + a1 * p1x + a2 * p2x + a3 * p3x) / sd, 0.0)
            oy = tl.where(moved, (a0 * p0y + a1 * p1y + a2 * p2y + a3 * p3y) / sd, 0.0)
            oz = tl.where(moved, (a0 * p0z + a1 * p1z + a2 * p2z + a3 * p3z) / sd, 0.0)
            q0x = p0x - ox
            q0y = p0y - oy
            q0z = p0z - oz
            q1x = p1x - ox
            q1y = p1y - oy
            q1z = p1z - oz
            q2x = p2x - ox
            q2y = p2y - oy
            q2z = p2z - oz
            q3x = p3x - ox
            q3y = p3y - oy
            q3z = p3z - oz
            Q0 = tl.sqrt(_dot(q0x, q0y, q0z, q0x, q0y, q0z))
            Q1 = tl.sqrt(_dot(q1x, q1y, q1z, q1x, q1y, q1z))
            Q2 = tl.sqrt(_dot(q2x, q2y, q2z, q2x, q2y, q2z))
            Q3 = tl.sqrt(_dot(q3x, q3y, q3z, q3x, q3y, q3z))
            e01x, e01y, e01z = _cross(q0x, q0y, q0z, q1x, q1y, q1z)
            e12x, e12y, e12z = _cross(q1x, q1y, q1z, q2x, q2y, q2z)
            e23x, e23y, e23z = _cross(q2x, q2y, q2z, q3x, q3y, q3z)
            e30x, e30y, e30z = _cross(q3x, q3y, q3z, q0x, q0y, q0z)
            f01 = _edge_term(e01x, e01y, e01z, q0x, q0y, q0z, q1x, q1y, q1z, Q0, Q1)
            f12 = _edge_term(e12x, e12y, e12z, q1x, q1y, q1z, q2x, q2y, q2z, Q1, Q2)
            f23 = _edge_term(e23x, e23y, e23z, q2x, q2y, q2z, q3x, q3y, q3z, Q2, Q3)
            f30 = _edge_term(e30x, e30y, e30z, q3x, q3y, q3z, q0x, q0y, q0z, Q3, Q0)
            dx = tl.where(hull, f01 * e01x + f12 * e12x + f23 * e23x + f30 * e30x, dx)
            dy = tl.where(hull, f01 * e01y + f12 * e12y + f23 * e23y + f30 * e30y, dy)
            dz = tl.where(hull, f01 * e01z + f12 * e12z + f23 * e23z + f30 * e30z, dz)
        # (u, v) where the line through the point along d meets the sheet of the (moved) corners
        A1x = q3x - q0x
        A1y = q3y - q0y
        A1z = q3z - q0z
        B1x = q2x - q1x
        B1y = q2y - q1y
        B1z = q2z - q1z
        tx, ty, tz = _cross(q0x, q0y, q0z, q1x, q1y, q1z)
        e0 = _dot(tx, ty, tz, dx, dy, dz)
        tx, ty, tz = _cross(q0x, q0y, q0z, B1x, B1y, B1z)
        sx, sy, sz2 = _cross(A1x, A1y, A1z, q1x, q1y, q1z)
        e1 = _dot(tx, ty, tz, dx, dy, dz) + _dot(sx, sy, sz2, dx, dy, dz)
        tx, ty, tz = _cross(A1x, A1y, A1z, B1x, B1y, B1z)
        e2 = _dot(tx, ty, tz, dx, dy, dz)
        disc = e1 * e1 - 4.0 * e0 * e2
        sq = tl.sqrt(tl.where(disc > 0, disc, 0.0))
        qq = -0.5 * (e1 + tl.where(e1 >= 0, sq, -sq))
        v1 = tl.where(e2 != 0, qq / tl.where(e2 != 0, e2, 1.0), BIG)
        v2 = tl.where(qq != 0, e0 / tl.where(qq != 0, qq, 1.0), BIG)
        bad1 = tl.maximum(-v1, 0.0) + tl.maximum(v1 - 1.0, 0.0) + 1e-3 * tl.abs(v1 - 0.5)
        bad2 = tl.maximum(-v2, 0.0) + tl.maximum(v2 - 1.0, 0.0) + 1e-3 * tl.abs(v2 - 0.5)
        vi = tl.minimum(tl.maximum(tl.where(bad1 <= bad2, v1, v2), 0.0), 1.0)
        ax = q0x + vi * A1x
        ay = q0y + vi * A1y
        az = q0z + vi * A1z
        ex = q1x + vi * B1x - ax
        ey = q1y + vi * B1y - ay
        ez = q1z + vi * B1z - az
        d2 = _dot(dx, dy, dz, dx, dy, dz)
        dinv = tl.where(d2 > 0, 1.0 / tl.where(d2 > 0, d2, 1.0), 0.0)
        ed = _dot(ex, ey, ez, dx, dy, dz) * dinv
        ad = _dot(ax, ay, az, dx, dy, dz) * dinv
        ex = ex - ed * dx
        ey = ey - ed * dy
        ez = ez - ed * dz
        ax = ax - ad * dx
        ay = ay - ad * dy
        az = az - ad * dz
        ee = _dot(ex, ey, ez, ex, ey, ez)
        ui = tl.where(ee > 0, -_dot(ax, ay, az, ex, ey, ez) / tl.where(ee > 0, ee, 1.0), 0.5)
        ui = tl.minimum(tl.maximum(ui, 0.0), 1.0)
        # at a corner: its parameters
        u = tl.where(vertex >= 0, tl.where((vertex == 1) | (vertex == 2), 1.0, 0.0), ui)
        v = tl.where(vertex >= 0, tl.where(vertex >= 2, 1.0, 0.0), vi)
        xix = p0x + u * bx + v * ccx + u * v * ddx
        xiy = p0y + u * by + v * ccy + u * v * ddy
        xiz = p0z + u * bz + v * ccz + u * v * ddz
        onq = todo & ((vertex >= 0) | (_dot(xix, xiy, xiz, xix, xiy, xiz) <= tl.where(flat, 2.0, BAND2) * tol2))
        hit = hit | onq
        h0 = tl.where(onq, i0, h0)
        h1 = tl.where(onq, i1, h1)
        h2 = tl.where(onq, i2, h2)
        h3 = tl.where(onq, i3, h3)
        hu = tl.where(onq, u, hu)
        hv = tl.where(onq, v, hv)
        done = done | onq
        act = ~done & ~flat
        # quads seen small: the Gauss rule, blended in by log10(min |p_i| / size)
        ratio = tl.minimum(tl.minimum(R0, R1), tl.minimum(R2, R3)) / sz
        sb = (log(tl.where(ratio > 1.0, ratio, 1.0)) * INV_LN10 - FAR_LO) / FAR_SPAN
        sb = tl.minimum(tl.maximum(sb, 0.0), 1.0)
        beta = tl.where(ratio > 1.0, sb * sb * (3.0 - 2.0 * sb), 0.0)
        wg0 = zero
        wg1 = zero
        wg2 = zero
        wg3 = zero
        if tl.sum((act & (beta > 0)).to(tl.int32)) > 0:
            for a in range(4):
                gu = tl.load(gauss + a)
                gwa = tl.load(gauss + 4 + a)
                for b in range(4):
                    gv = tl.load(gauss + b)
                    fx = p0x + gu * bx + gv * ccx + gu * gv * ddx
                    fy = p0y + gu * by + gv * ccy + gu * gv * ddy
                    fz = p0z + gu * bz + gv * ccz + gu * gv * ddz
                    r2 = fx * fx + fy * fy + fz * fz
                    Nd = (N0x + gu * Nux + gv * Nvx) * fx + (N0y + gu * Nuy + gv * Nvy) * fy
                    Nd += (N0z + gu * Nuz + gv * Nvz) * fz
                    fw = Nd / (r2 * r2) * gwa * tl.load(gauss + 4 + b)
                    wg0 += (1.0 - gu) * (1.0 - gv) * fw
                    wg1 += gu * (1.0 - gv) * fw
                    wg2 += gu * gv * fw
                    wg3 += (1.0 - gu) * gv * fw
        # the least-norm solution, one refinement step (Eqs. 20, 28)
        invD = 1.0 / tl.where(D > 0, D, 1.0)
        wb0 = _dot(r0x, r0y, r0z, mx, my, mz) * invD
        wb1 = _dot(r1x, r1y, r1z, mx, my, mz) * invD
        wb2 = _dot(r2x, r2y, r2z, mx, my, mz) * invD
        wb3 = _dot(r3x, r3y, r3z, mx, my, mz) * invD
        rx = mx - (wb0 * p0x + wb1 * p1x + wb2 * p2x + wb3 * p3x)
        ry = my - (wb0 * p0y + wb1 * p1y + wb2 * p2y + wb3 * p3y)
        rz = mz - (wb0 * p0z + wb1 * p1z + wb2 * p2z + wb3 * p3z)
        wb0 += _dot(r0x, r0y, r0z, rx, ry, rz) * invD
        wb1 += _dot(r1x, r1y, r1z, rx, ry, rz) * invD
        wb2 += _dot(r2x, r2y, r2z, rx, ry, rz) * invD
        wb3 += _dot(r3x, r3y, r3z, rx, ry, rz) * invD
        # the Riemann estimate Omega (Eqs. 22-23) on the adaptive grid around (u, v), separable in
        # the bilinear basis
        S = zero
        Su = zero
        Sv = zero
        Suv = zero
        if tl.sum((act & (beta < 1.0)).to(tl.int32)) > 0:
            # (each node from its index: no loop carries a previous node. Compiled Triton picks a
            # loop's carried variables by a dry run of its body, where `prev = cur` gives prev the
            # live-in value of cur; both began as `zero`, one value, so prev looked unchanged, was
            # not carried and stayed 0: every Riemann weight was wrong on a GPU (0.19 on the data
            # set, 2026-12-04), while the interpreter, plain Python, was right)
            for a in range(K):
                un = _node(a, u, N, zero)
                ua = 0.5 * (_node(a + 1, u, N, zero) - _node(a - 1, u, N, zero))
                Pux = p0x + un * bx
                Puy = p0y + un * by
                Puz = p0z + un * bz
                Qux = ccx + un * ddx
                Quy = ccy + un * ddy
                Quz = ccz + un * ddz
                Rux = N0x + un * Nux
                Ruy = N0y + un * Nuy
                Ruz = N0z + un * Nuz
                acc0 = zero
                acc1 = zero
                for b in range(K):
                    vn = _node(b, v, N, zero)
                    va = 0.5 * (_node(b + 1, v, N, zero) - _node(b - 1, v, N, zero))
                    fx = Pux + vn * Qux
                    fy = Puy + vn * Quy
                    fz = Puz + vn * Quz
                    r2 = fx * fx + fy * fy + fz * fz
                    Nd = (Rux + vn * Nvx) * fx + (Ruy + vn * Nvy) * fy + (Ruz + vn * Nvz) * fz
                    fw = Nd * va / (r2 * r2)
                    acc0 += fw
                    acc1 += fw * vn
                acc0 = acc0 * ua
                acc1 = acc1 * ua
                S += acc0
                Sv += acc1
                Su += un * acc0
                Suv += un * acc1
        om0 = S - Su - Sv + Suv
        om1 = Su - Suv
        om2 = Suv
        om3 = Sv - Suv
        okk = om0 * k0 + om1 * k1 + om2 * k2 + om3 * k3
        ow = om0 * wb0 + om1 * wb1 + om2 * wb2 + om3 * wb3
        ww = wb0 * wb0 + wb1 * wb1 + wb2 * wb2 + wb3 * wb3
        lam = tl.where(ow != 0, okk * invD * ww / tl.where(ow != 0, ow, 1.0), 0.0)
        wq0 = wb0 + lam * k0
        wq1 = wb1 + lam * k1
        wq2 = wb2 + lam * k2
        wq3 = wb3 + lam * k3
        # near a flat quad's plane: the least-norm part from the split triangles' stable weights
        nf = wp_ok & act
        if tl.sum(nf.to(tl.int32)) > 0:
            invn = 1.0 / tl.sqrt(tl.where(D > 0, D, 1.0))
            kh0 = k0 * invn
            kh1 = k1 * invn
            kh2 = k2 * invn
            kh3 = k3 * invn
            pk = wp0 * kh0 + wp1 * kh1 + wp2 * kh2 + wp3 * kh3
            wc0 = wp0 - pk * kh0
            wc1 = wp1 - pk * kh1
            wc2 = wp2 - pk * kh2
            wc3 = wp3 - pk * kh3
            okh = om0 * kh0 + om1 * kh1 + om2 * kh2 + om3 * kh3
            ow2 = om0 * wc0 + om1 * wc1 + om2 * wc2 + om3 * wc3
            ww2 = wc0 * wc0 + wc1 * wc1 + wc2 * wc2 + wc3 * wc3
            lam2 = tl.where(ow2 != 0, okh * ww2 / tl.where(ow2 != 0, ow2, 1.0), 0.0)
            wq0 = tl.where(nf, wc0 + lam2 * kh0, wq0)
            wq1 = tl.where(nf, wc1 + lam2 * kh1, wq1)
            wq2 = tl.where(nf, wc2 + lam2 * kh2, wq2)
            wq3 = tl.where(nf, wc3 + lam2 * kh3, wq3)
        # restore A w = m (kappa's rounding error is amplified by a large lambda), or near a flat
        # quad's plane A w = A w_split
        for _ in range(NREFINE):
            rx = tl.where(nf, (wp0 - wq0) * p0x + (wp1 - wq1) * p1x + (wp2 - wq2) * p2x + (wp3 - wq3) * p3x,
                          mx - (wq0 * p0x + wq1 * p1x + wq2 * p2x + wq3 * p3x))  # fmt: skip
            ry = tl.where(nf, (wp0 - wq0) * p0y + (wp1 - wq1) * p1y + (wp2 - wq2) * p2y + (wp3 - wq3) * p3y,
                          my - (wq0 * p0y + wq1 * p1y + wq2 * p2y + wq3 * p3y))  # fmt: skip
            rz = tl.where(nf, (wp0 - wq0) * p0z + (wp1 - wq1) * p1z + (wp2 - wq2) * p2z + (wp3 - wq3) * p3z,
                          mz - (wq0 * p0z + wq1 * p1z + wq2 * p2z + wq3 * p3z))  # fmt: skip
            wq0 += _dot(r0x, r0y, r0z, rx, ry, rz) * invD
            wq1 += _dot(r1x, r1y, r1z, rx, ry, rz) * invD
            wq2 += _dot(r2x, r2y, r2z, rx, ry, rz) * invD
            wq3 += _dot(r3x, r3y, r3z, rx, ry, rz) * invD
        far = beta >= 1.0
        wq0 = tl.where(far, wg0, tl.where(beta > 0, (1.0 - beta) * wq0 + beta * wg0, wq0))
        wq1 = tl.where(far, wg1, tl.where(beta > 0, (1.0 - beta) * wq1 + beta * wg1, wq1))
        wq2 = tl.where(far, wg2, tl.where(beta > 0, (1.0 - beta) * wq2 + beta * wg2, wq2))
        wq3 = tl.where(far, wg3, tl.where(beta > 0, (1.0 - beta) * wq3 + beta * wg3, wq3))
        tl.store(row + i0, tl.load(row + i0, mask=act, other=0.0) + wq0, mask=act)
        tl.store(row + i1, tl.load(row + i1, mask=act, other=0.0) + wq1, mask=act)
        tl.store(row + i2, tl.load(row + i2, mask=act, other=0.0) + wq2, mask=act)
        tl.store(row + i3, tl.load(row + i3, mask=act, other=0.0) + wq3, mask=act)
    # points on a quad: the bilinear values of their parameters (Lagrange at a corner)
    if tl.sum(hit.to(tl.int32)) > 0:
        for c in range(V):
            tl.store(row + c, zero, mask=hit)
        tl.store(row + h0, (1.0 - hu) * (1.0 - hv), mask=hit)
        tl.store(row + h1, hu * (1.0 - hv), mask=hit)
        tl.store(row + h2, hu * hv, mask=hit)
        tl.store(row + h3, (1.0 - hu) * hv, mask=hit)
        tl.store(flags + point, tl.zeros_like(offs) + 1, mask=hit)


def triton_tables(verts: torch.Tensor, qdata: QuadData, n: int) -> dict[str, object]:
    """The kernel's arguments for one cage (a batch of one; float64, the cage's device): the
    vertices, the quads, per quad the sheet's ``b, c, d, N0, Nu, Nv`` ``(Q, 18)``, twice the sum of
    its corner triangles' areas and its size, the Gauss table, the on-cage tolerance and the grid
    parameter ``n``."""
    P = verts.to(torch.float64)
    tol = torch.full((1,), float(qdata.tol), dtype=torch.float64, device=P.device)
    return batch_tables(P[None], qdata.quads, tol, n)


def batch_tables(vertices: torch.Tensor, quads: torch.Tensor, tol: torch.Tensor, n: int) -> dict[str, object]:
    """The kernel's arguments for a batch of cages with one topology, each per-cage table computed
    for the ``B`` cages by one set of tensor operations (element by element the numbers of
    :func:`triton_tables`).

    Args:
        vertices: ``(B, V, 3)`` the cages' vertices (float64 compute), on the kernel's device.
        quads: ``(Q, 4)`` the shared quads.
        tol: ``(B,)`` absolute on-cage tolerances.
        n: the grid parameter of the Riemann sums.
    """
    P = vertices.to(torch.float64).contiguous()
    quads = quads.to(P.device)
    q = P[:, quads]  # (B, Q, 4, 3)
    b, c = q[..., 1, :] - q[..., 0, :], q[..., 3, :] - q[..., 0, :]
    d = q[..., 0, :] - q[..., 1, :] + q[..., 2, :] - q[..., 3, :]
    cross = torch.linalg.cross
    geom = torch.cat([b, c, d, cross(b, c), cross(b, d), cross(d, c)], dim=-1).contiguous()
    area2 = sum(
        cross(q[..., (i + 2) % 4, :] - q[..., (i + 1) % 4, :], q[..., (i + 3) % 4, :] - q[..., (i + 1) % 4, :]).norm(
            dim=-1
        )
        for i in range(4)
    )
    return {
        "P": P,
        "V": P.shape[1],
        "quads": quads.to(torch.int32).contiguous(),
        "Q": quads.shape[0],
        "geom": geom,
        "area2": area2.contiguous(),
        "size": quad_sizes(P, quads).contiguous(),
        "gauss": torch.tensor(GAUSS4[0] + GAUSS4[1], dtype=torch.float64, device=P.device),
        "tol": tol.to(P.device, torch.float64).reshape(-1).contiguous(),
        "N": int(n),
    }


def qmvc3d_triton(
    x: torch.Tensor, tables: dict[str, object], W: torch.Tensor, flags: torch.Tensor, block: int | None = None
) -> None:
    """Add the quads' raw weights of points ``x`` (float64, the tables' device) into ``W``
    (contiguous; the triangles' raw weights, or zeros), skipping rows with ``flags == 1`` (int32,
    final: on the cage); rows of points on a quad become its bilinear values and their flag 1.
    ``block``: points per program (32 on a GPU; large in the interpreter).

    One cage (tables of a batch of one): ``x`` ``(m, 3)``, ``W`` ``(m, V)``, ``flags`` ``(m,)``. A
    batch of ``B`` cages (:func:`batch_tables`): ``x`` ``(B, m, 3)``, or ``(1, m, 3)`` shared by every
    cage, ``W`` ``(B, m, V)``, ``flags`` ``(B, m)``.

    Raises:
        ValueError: points whose batch is neither 1 nor the cages'.
    """
    B = tables["P"].shape[0]  # type: ignore[attr-defined]
    X, _ = point_batch(x, B, "qmvc3d_triton")
    XB, m = X.shape[0], X.shape[1]
    if m == 0 or tables["Q"] == 0:
        return
    if block is None:
        block = min(4096, triton.next_power_of_2(max(m, 16))) if interpreted() else 32
    grid = (B * triton.cdiv(m, block),)
    _qmvc3d_kernel[grid](X, 0 if XB == 1 else 3 * m, m, **tables, W=W, flags=flags, BLOCK=block, BATCHED=B > 1,
                         num_warps=warps(block))  # fmt: skip
