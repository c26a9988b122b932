"""Triton kernel of 3D mean value coordinates (closed triangle cages): the formulas of the native
kernel (``torchcage/backends/native/mvc3d.c``; derivation in :mod:`.kernel3d`), a block
of points per program and a loop over the faces.

Per point–face pair: the direct vector form ``w_i = N_i . m / (2 A h)``; the stable split form where
``|h| < SPLIT_FORM_RATIO min |a_i|``; points on a face (or a vertex) get the interpolating values
of the largest face holding them. Points whose face weights cancel (far outside) or that see a face
below ``1 / FAR_ALWAYS_RATIO`` of its distance take a second pass, with the collapsed Gauss rule on
the faces seen small. Far from the cage the weights are normalised by their first moment. Pairs of
a thin face seen from a few widths (``_thin_triangle.thin_pairs``) are flagged: the caller redoes
those points with the torch kernel's swept form.

A batch of ``B`` cages with one topology is one launch (a program per cage and block of points):
``tri (T, 3)`` int32 is shared, every other table carries a leading cage axis (``P (B, V, 3)``,
per-face tables ``(B, T, ...)``, per-cage scalars ``(B,)``); ``X (B, n, 3)``, or ``(1, n, 3)``
shared by every cage, -> ``W (B, n, V)`` (normalised) and ``flags (B, n)`` int32 (1: on the cage,
2: redo with the torch kernel). One cage is a batch of one.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from torchcage._core.common import FAR_MOMENT
from torchcage._core.thin_triangle import THIN_ASPECT, THIN_DISTANCE
from torchcage.backends.triton import interpreted, point_batch, warps
from torchcage.backends.triton.common import PI, atan, atan2
from torchcage.families.mean_value.kernel3d import (
    CANCELLATION_RATIO,
    FAR_ALWAYS_RATIO,
    FAR_FIELD_RATIO,
    PART_FAR_FIELD_RATIO,
    TriangleCageData,
    face_constants,
)

__all__ = ["batch_tables", "mvc3d_triton", "part_batch_tables", "part_tables", "triton_tables"]

TWO_PI = tl.constexpr(6.283185307179586)
#: The split form serves pairs with ``|h| < TRITON_SPLIT_FORM_RATIO min |a_i|``: wider than the
#: native kernel's band (``SPLIT_FORM_RATIO``, 0.01), where the direct form computed with this
#: kernel's arctangent lost 1e-10 of a face's weight on Bench at 0.013 (the split form is exact for
#: any ``|h| < min |a_i|``; the derivative kernel uses 0.05 for the same reason).
TRITON_SPLIT_FORM_RATIO = 0.05


@triton.jit
def _half_angle(nn, d, rr):
    """The angle between ``a_j`` and ``a_k`` from ``|a_j x a_k|``, ``a_j . a_k`` and ``|a_j| |a_k|``
    (``2 atan`` of the half-angle tangent, or its supplement)."""
    t = atan(nn / tl.where(rr + tl.abs(d) > 0, rr + tl.abs(d), 1.0))
    return tl.where(d < 0, PI - 2.0 * t, 2.0 * t)


@triton.jit
def _stable_edge(s_e, d_e, h, ell_e):
    """One edge of the split form: ``(sigma theta0, theta / |N|  (or 0 where N = 0), S_rest term,
    N > 0)``, as ``tc_stable_face``."""
    h2 = h * h
    s_abs = tl.abs(s_e)
    sigma = tl.where(s_e >= 0, 1.0, -1.0)
    qq = d_e - h2
    N = tl.sqrt(s_e * s_e + h2 * ell_e * ell_e)
    Nps = N + s_abs
    safe_Nps = tl.where(Nps > 0, Nps, 1.0)
    X = qq * ell_e * ell_e / safe_Nps - s_abs
    Y = d_e * qq + N * s_abs
    delta = atan2(h2 * X, Y)
    delta_h2 = tl.where(h2 > 0, delta / tl.where(h2 > 0, h2, 1.0), X / tl.where(Y != 0, Y, 1.0))
    theta0 = atan2(s_abs, qq)
    theta = theta0 + delta
    safe_N = tl.where(N > 0, N, 1.0)
    eps_h2 = ell_e * ell_e / (safe_N * safe_Nps)
    return sigma * theta0, theta / safe_N, sigma * (delta_h2 - theta * eps_h2), N > 0


@triton.jit
def face_form(
    a0x, a0y, a0z, a1x, a1y, a1z, a2x, a2y, a2z, nx, ny, nz, A2, l0, l1, l2,
    g00, g01, g02, g10, g11, g12, g20, g21, g22, tol, near_c,
):  # fmt: skip
    """Mean value weights of a triangle with corners ``a_i`` (minus the point; block tensors), unit
    normal ``n``, twice its area ``A2``, edge lengths ``l_e`` (edge ``e`` opposite corner ``e``) and
    edge Gram matrix ``g_ef = E_e . E_f`` (``E_e = a_{e+1} - a_{e+2}``): the direct vector form, or
    the split form where ``|h| < near_c min |a_i|`` (or within ``tol`` of a corner); a triangle of
    no area weighs nothing. Returns ``(w0, w1, w2, s0, s1, s2, h, rmin, R0, R1, R2, split, dead)``
    (``s_e = n . N_e``, ``h = n . a_0``)."""
    R0 = tl.sqrt(a0x * a0x + a0y * a0y + a0z * a0z)
    R1 = tl.sqrt(a1x * a1x + a1y * a1y + a1z * a1z)
    R2 = tl.sqrt(a2x * a2x + a2y * a2y + a2z * a2z)
    # N_e = a_{e+1} x a_{e+2}
    N0x = a1y * a2z - a1z * a2y
    N0y = a1z * a2x - a1x * a2z
    N0z = a1x * a2y - a1y * a2x
    N1x = a2y * a0z - a2z * a0y
    N1y = a2z * a0x - a2x * a0z
    N1z = a2x * a0y - a2y * a0x
    N2x = a0y * a1z - a0z * a1y
    N2y = a0z * a1x - a0x * a1z
    N2z = a0x * a1y - a0y * a1x
    nn0 = tl.sqrt(N0x * N0x + N0y * N0y + N0z * N0z)
    nn1 = tl.sqrt(N1x * N1x + N1y * N1y + N1z * N1z)
    nn2 = tl.sqrt(N2x * N2x + N2y * N2y + N2z * N2z)
    d0 = a1x * a2x + a1y * a2y + a1z * a2z
    d1 = a2x * a0x + a2y * a0y + a2z * a0z
    d2 = a0x * a1x + a0y * a1y + a0z * a1z
    # m = sum_e (theta_e / 2) N_e / |N_e| (0 where N_e = 0)
    t0 = 0.5 * _half_angle(nn0, d0, R1 * R2) / tl.where(nn0 > 0, nn0, 1.0)
    t1 = 0.5 * _half_angle(nn1, d1, R2 * R0) / tl.where(nn1 > 0, nn1, 1.0)
    t2 = 0.5 * _half_angle(nn2, d2, R0 * R1) / tl.where(nn2 > 0, nn2, 1.0)
    mx = t0 * N0x + t1 * N1x + t2 * N2x
    my = t0 * N0y + t1 * N1y + t2 * N2y
    mz = t0 * N0z + t1 * N1z + t2 * N2z
    h = nx * a0x + ny * a0y + nz * a0z
    det = A2 * h
    inv = 1.0 / tl.where(det != 0, det, 1.0)
    w0 = (N0x * mx + N0y * my + N0z * mz) * inv
    w1 = (N1x * mx + N1y * my + N1z * mz) * inv
    w2 = (N2x * mx + N2y * my + N2z * mz) * inv
    rmin = tl.minimum(tl.minimum(R0, R1), R2)
    # the split form near the support plane
    s0 = nx * N0x + ny * N0y + nz * N0z
    s1 = nx * N1x + ny * N1y + nz * N1z
    s2 = nx * N2x + ny * N2y + nz * N2z
    wa0, t0, r0, ok0 = _stable_edge(s0, d0, h, l0)
    wa1, t1, r1, ok1 = _stable_edge(s1, d1, h, l1)
    wa2, t2, r2, ok2 = _stable_edge(s2, d2, h, l2)
    t0 = tl.where(ok0, t0, 1.0 / tl.where(R1 * R2 > 0, R1 * R2, 1.0))
    t1 = tl.where(ok1, t1, 1.0 / tl.where(R2 * R0 > 0, R2 * R0, 1.0))
    t2 = tl.where(ok2, t2, 1.0 / tl.where(R0 * R1 > 0, R0 * R1, 1.0))
    S_rest = r0 + r1 + r2
    wind = tl.floor((wa0 + wa1 + wa2) / TWO_PI + 0.5)
    inv4A = 1.0 / (2.0 * tl.where(A2 > 0, A2, 1.0))
    safe_h = tl.where(h != 0, h, 1.0)
    sing = tl.where(wind != 0, TWO_PI * wind / safe_h, 0.0) * inv4A
    B0 = s0 * S_rest + t0 * g00 + t1 * g01 + t2 * g02
    B1 = s1 * S_rest + t0 * g10 + t1 * g11 + t2 * g12
    B2 = s2 * S_rest + t0 * g20 + t1 * g21 + t2 * g22
    split = (tl.abs(h) < near_c * rmin) | (rmin <= tol)
    # (a face of no area, such as a sliver rounded to float32, holds nothing and weighs nothing)
    dead = (tl.zeros_like(h) + A2) <= 0
    flat = ((wind == 0) & (h == 0)) | dead
    w0 = tl.where(flat, 0.0, tl.where(split, h * B0 * inv4A + s0 * sing, w0))
    w1 = tl.where(flat, 0.0, tl.where(split, h * B1 * inv4A + s1 * sing, w1))
    w2 = tl.where(flat, 0.0, tl.where(split, h * B2 * inv4A + s2 * sing, w2))
    return w0, w1, w2, s0, s1, s2, h, rmin, R0, R1, R2, split, dead


@triton.jit
def _face_weights(x0, x1, x2, f, P, tri, nrm, two_area, ell, gram, tol, near_c):
    """Weights of face ``f`` at a block of points (:func:`face_form`) with the pair's facts:
    ``(i0, i1, i2, w0, w1, w2, on_face, at_vertex, b0, b1, b2, rmin)``."""
    i0 = tl.load(tri + 3 * f)
    i1 = tl.load(tri + 3 * f + 1)
    i2 = tl.load(tri + 3 * f + 2)
    l0 = tl.load(ell + 3 * f)
    l1 = tl.load(ell + 3 * f + 1)
    l2 = tl.load(ell + 3 * f + 2)
    G = gram + 9 * f
    w0, w1, w2, s0, s1, s2, h, rmin, R0, R1, R2, split, dead = face_form(
        tl.load(P + 3 * i0) - x0, tl.load(P + 3 * i0 + 1) - x1, tl.load(P + 3 * i0 + 2) - x2,
        tl.load(P + 3 * i1) - x0, tl.load(P + 3 * i1 + 1) - x1, tl.load(P + 3 * i1 + 2) - x2,
        tl.load(P + 3 * i2) - x0, tl.load(P + 3 * i2 + 1) - x1, tl.load(P + 3 * i2 + 2) - x2,
        tl.load(nrm + 3 * f), tl.load(nrm + 3 * f + 1), tl.load(nrm + 3 * f + 2), tl.load(two_area + f),
        l0, l1, l2,
        tl.load(G), tl.load(G + 1), tl.load(G + 2), tl.load(G + 3), tl.load(G + 4), tl.load(G + 5),
        tl.load(G + 6), tl.load(G + 7), tl.load(G + 8), tol, near_c,
    )  # fmt: skip
    # on the face (within tol) or at a vertex
    at_vertex = rmin <= tol
    inside = (s0 >= -tol * l0) & (s1 >= -tol * l1) & (s2 >= -tol * l2)
    on_face = (split & (tl.abs(h) <= tol) & inside & ~dead) | at_vertex
    b0 = tl.where(at_vertex, tl.where(R0 <= tol, 1.0, 0.0), tl.maximum(s0, 0.0))
    b1 = tl.where(at_vertex, tl.where(R1 <= tol, 1.0, 0.0), tl.maximum(s1, 0.0))
    b2 = tl.where(at_vertex, tl.where(R2 <= tol, 1.0, 0.0), tl.maximum(s2, 0.0))
    return i0, i1, i2, w0, w1, w2, on_face, at_vertex, b0, b1, b2, rmin


@triton.jit
def _thin_pair(x0, x1, x2, f, P, tri, two_area, thin_distance):
    """Whether the point sees thin face ``f`` from ``thin_distance`` widths or more from its longest
    edge (``_thin_triangle.thin_pairs``)."""
    i0 = tl.load(tri + 3 * f)
    i1 = tl.load(tri + 3 * f + 1)
    i2 = tl.load(tri + 3 * f + 2)
    p0x = tl.load(P + 3 * i0)
    p0y = tl.load(P + 3 * i0 + 1)
    p0z = tl.load(P + 3 * i0 + 2)
    p1x = tl.load(P + 3 * i1)
    p1y = tl.load(P + 3 * i1 + 1)
    p1z = tl.load(P + 3 * i1 + 2)
    p2x = tl.load(P + 3 * i2)
    p2y = tl.load(P + 3 * i2 + 1)
    p2z = tl.load(P + 3 * i2 + 2)
    e01 = (p1x - p0x) * (p1x - p0x) + (p1y - p0y) * (p1y - p0y) + (p1z - p0z) * (p1z - p0z)
    e12 = (p2x - p1x) * (p2x - p1x) + (p2y - p1y) * (p2y - p1y) + (p2z - p1z) * (p2z - p1z)
    e20 = (p0x - p2x) * (p0x - p2x) + (p0y - p2y) * (p0y - p2y) + (p0z - p2z) * (p0z - p2z)
    # the longest edge A -> B (scalars)
    use01 = (e01 >= e12) & (e01 >= e20)
    use12 = (~use01) & (e12 >= e20)
    ax = tl.where(use01, p0x, tl.where(use12, p1x, p2x))
    ay = tl.where(use01, p0y, tl.where(use12, p1y, p2y))
    az = tl.where(use01, p0z, tl.where(use12, p1z, p2z))
    bx = tl.where(use01, p1x, tl.where(use12, p2x, p0x))
    by = tl.where(use01, p1y, tl.where(use12, p2y, p0y))
    bz = tl.where(use01, p1z, tl.where(use12, p2z, p0z))
    L2 = tl.maximum(tl.maximum(e01, e12), e20)
    dx = bx - ax
    dy = by - ay
    dz = bz - az
    rx = ax - x0
    ry = ay - x1
    rz = az - x2
    t = -(rx * dx + ry * dy + rz * dz) / L2
    t = tl.minimum(tl.maximum(t, 0.0), 1.0)
    qx = rx + t * dx
    qy = ry + t * dy
    qz = rz + t * dz
    A2 = tl.load(two_area + f)
    return (qx * qx + qy * qy + qz * qz) * L2 >= (thin_distance * A2) * (thin_distance * A2)


@triton.jit
def _far_face(x0, x1, x2, f, h, far_nodes, far_coef, Q, scale):
    """The collapsed Gauss rule ``h sum_q c_qi (scale / |p_q - x|^2)^2`` of face ``f`` (``scale``
    per point keeps ``1 / r^4`` within float32's range far away; the caller scales the other faces'
    weights by ``scale^2``)."""
    acc0 = tl.zeros_like(x0)
    acc1 = tl.zeros_like(x0)
    acc2 = tl.zeros_like(x0)
    for q in range(Q):
        base = (f * Q + q) * 3
        dx = tl.load(far_nodes + base) - x0
        dy = tl.load(far_nodes + base + 1) - x1
        dz = tl.load(far_nodes + base + 2) - x2
        r2 = dx * dx + dy * dy + dz * dz
        t = scale / r2
        i4 = t * t
        acc0 += tl.load(far_coef + base) * i4
        acc1 += tl.load(far_coef + base + 1) * i4
        acc2 += tl.load(far_coef + base + 2) * i4
    return h * acc0, h * acc1, h * acc2


@triton.jit
def _mvc3d_kernel(
    X, xs, n, P, V, tri, T, nrm, two_area, ell, gram, longest, thin, far_nodes, far_coef, Q,
    cen, far2, rad2, tol, near_c, far_c, cancel_c, far_always, thin_distance,
    W, flags, BLOCK: tl.constexpr, NORMALIZE: tl.constexpr = True,
):  # fmt: skip
    # one program: a block of points against cage b (program index b * blocks + block); the
    # topology (tri) is shared, every other table has a leading cage axis
    pid = tl.program_id(0)
    nblk = tl.cdiv(n, BLOCK)
    b = (pid // nblk).to(tl.int64)
    offs = (pid % nblk) * BLOCK + tl.arange(0, BLOCK)
    live = offs < n
    P += b * V * 3
    nrm += b * T * 3
    two_area += b * T
    ell += b * T * 3
    gram += b * T * 9
    longest += b * T
    thin += b * T
    far_nodes += b * T * Q * 3
    far_coef += b * T * Q * 3
    tol = tl.load(tol + b)
    X += b * xs
    x0 = tl.load(X + 3 * offs, mask=live, other=0.0)
    x1 = tl.load(X + 3 * offs + 1, mask=live, other=0.0)
    x2 = tl.load(X + 3 * offs + 2, mask=live, other=0.0)
    row = W + (b * n + offs) * V
    for v in range(V):
        tl.store(row + v, tl.zeros_like(x0), mask=live)
    total = tl.zeros_like(x0)
    abs_sum = tl.zeros_like(x0)
    tiny = offs < 0
    redo = offs < 0
    best_area = tl.zeros_like(x0) - 1.0
    best_vertex = offs < 0
    bi0 = tl.zeros_like(offs)
    bi1 = tl.zeros_like(offs)
    bi2 = tl.zeros_like(offs)
    bb0 = tl.zeros_like(x0)
    bb1 = tl.zeros_like(x0)
    bb2 = tl.zeros_like(x0)
    for f in range(T):
        i0, i1, i2, w0, w1, w2, on_face, at_vertex, b0, b1, b2, rmin = _face_weights(
            x0, x1, x2, f, P, tri, nrm, two_area, ell, gram, tol, near_c
        )
        A2 = tl.load(two_area + f)
        take = on_face & ~best_vertex & (at_vertex | (A2 > best_area))
        best_area = tl.where(take, A2, best_area)
        best_vertex = best_vertex | (on_face & at_vertex)
        bi0 = tl.where(take, i0, bi0)
        bi1 = tl.where(take, i1, bi1)
        bi2 = tl.where(take, i2, bi2)
        bb0 = tl.where(take, b0, bb0)
        bb1 = tl.where(take, b1, bb1)
        bb2 = tl.where(take, b2, bb2)
        tl.store(row + i0, tl.load(row + i0, mask=live, other=0.0) + w0, mask=live)
        tl.store(row + i1, tl.load(row + i1, mask=live, other=0.0) + w1, mask=live)
        tl.store(row + i2, tl.load(row + i2, mask=live, other=0.0) + w2, mask=live)
        total += w0 + w1 + w2
        abs_sum += tl.abs(w0 + w1 + w2)
        tiny = tiny | (tl.load(longest + f) * far_always < rmin)
        if tl.load(thin + f) != 0:
            redo = redo | _thin_pair(x0, x1, x2, f, P, tri, two_area, thin_distance)
    on = best_area >= 0.0
    # (a NaN or an overflow in the sums, far away in float32, counts as cancelling)
    far = (~(abs_sum <= cancel_c * tl.abs(total)) | tiny) & ~on & live
    # (the cage's centre and radii loaded here, after the face loop: fewer registers live through it)
    c0 = tl.load(cen + 3 * b)
    c1 = tl.load(cen + 3 * b + 1)
    c2 = tl.load(cen + 3 * b + 2)
    far2 = tl.load(far2 + b)
    rad2 = tl.load(rad2 + b)
    y0 = x0 - c0
    y1 = x1 - c1
    y2 = x2 - c2
    yy = y0 * y0 + y1 * y1 + y2 * y2
    # the far pass scales each point's weights by scale^2, scale = max(1, |y|^2 / radius^2) (raw
    # weights, unnormalised, keep their scale)
    if NORMALIZE:
        scale = tl.maximum(yy / rad2, 1.0)
    else:
        scale = tl.zeros_like(yy) + 1.0
    if tl.sum(far.to(tl.int32)) > 0:
        # the face weights cancel (far outside) or faces are seen very small: the faces seen small
        # take the quadrature, the others their forms again
        for v in range(V):
            tl.store(row + v, tl.zeros_like(x0), mask=far)
        for f in range(T):
            i0, i1, i2, w0, w1, w2, on_face, at_vertex, b0, b1, b2, rmin = _face_weights(
                x0, x1, x2, f, P, tri, nrm, two_area, ell, gram, tol, near_c
            )
            small = tl.load(longest + f) < far_c * rmin
            if tl.sum((far & small).to(tl.int32)) > 0:
                h = (
                    tl.load(nrm + 3 * f) * (tl.load(P + 3 * i0) - x0)
                    + tl.load(nrm + 3 * f + 1) * (tl.load(P + 3 * i0 + 1) - x1)
                    + tl.load(nrm + 3 * f + 2) * (tl.load(P + 3 * i0 + 2) - x2)
                )
                q0, q1, q2 = _far_face(x0, x1, x2, f, h, far_nodes, far_coef, Q, scale)
                w0 = tl.where(small, q0, w0 * scale * scale)
                w1 = tl.where(small, q1, w1 * scale * scale)
                w2 = tl.where(small, q2, w2 * scale * scale)
            else:
                w0 = w0 * scale * scale
                w1 = w1 * scale * scale
                w2 = w2 * scale * scale
            tl.store(row + i0, tl.load(row + i0, mask=far, other=0.0) + w0, mask=far)
            tl.store(row + i1, tl.load(row + i1, mask=far, other=0.0) + w1, mask=far)
            tl.store(row + i2, tl.load(row + i2, mask=far, other=0.0) + w2, mask=far)
    # normalise: the sum, or far away the first moment (W (P - c)) . y / |y|^2
    if NORMALIZE:
        distant = yy > far2
        s = tl.zeros_like(x0)
        mom = tl.zeros_like(x0)
        for v in range(V):
            wv = tl.load(row + v, mask=live, other=0.0)
            s += wv
            pv = (tl.load(P + 3 * v) - c0) * y0 + (tl.load(P + 3 * v + 1) - c1) * y1
            pv += (tl.load(P + 3 * v + 2) - c2) * y2
            mom += wv * pv
        den = tl.where(distant, mom / tl.where(distant, yy, 1.0), s)
        inv = 1.0 / den
    else:
        inv = tl.zeros_like(x0) + 1.0
    for v in range(V):
        wv = tl.load(row + v, mask=live, other=0.0)
        tl.store(row + v, tl.where(on, 0.0, wv * inv), mask=live)
    bsum = bb0 + bb1 + bb2
    bsum = tl.where(bsum > 0, bsum, 1.0)
    tl.store(row + bi0, tl.load(row + bi0, mask=live & on, other=0.0) + bb0 / bsum, mask=live & on)
    tl.store(row + bi1, tl.load(row + bi1, mask=live & on, other=0.0) + bb1 / bsum, mask=live & on)
    tl.store(row + bi2, tl.load(row + bi2, mask=live & on, other=0.0) + bb2 / bsum, mask=live & on)
    flag = tl.where(on, 1, tl.where(redo, 2, 0))
    tl.store(flags + b * n + offs, flag, mask=live)


def triton_tables(data: TriangleCageData) -> dict[str, object]:
    """The kernel's arguments for one cage (a batch of one), built once from the torch kernel's
    constants (compute dtype, the cage's device)."""
    v = data.vertices.T.contiguous()  # (V, 3)
    T = data.tri.shape[0]
    thin = torch.zeros(T, dtype=torch.int32, device=v.device)
    thin[data.thin] = 1
    tables = _topology(data.tri, v.shape[0], data.far_nodes.shape[1])
    tables.update(
        {
            "P": v[None],
            "nrm": torch.nan_to_num(data.normal[:, :, 0].T, nan=0.0).contiguous()[None],
            "two_area": data.two_area[:, 0].contiguous()[None],
            "ell": data.edge_len[:, :, 0].T.contiguous()[None],
            "gram": data.gram.contiguous()[None],
            "longest": data.longest[:, 0].contiguous()[None],
            "thin": thin[None],
            "far_nodes": data.far_nodes.contiguous()[None],
            "far_coef": data.far_coef.contiguous()[None],
            "tol": torch.full((1,), data.tol, dtype=v.dtype, device=v.device),
        }
    )
    tables.update(_far_tables(v[None]))
    return tables


def batch_tables(vertices: torch.Tensor, tri: torch.Tensor, tol: torch.Tensor) -> dict[str, object]:
    """The kernel's arguments for a batch of cages with one topology, every per-cage table of the
    ``B`` cages computed by one set of tensor operations (element by element the numbers of
    :func:`triton_tables` on ``triangle_cage_data`` of that cage, as ``native3d.batch_tables``).

    Args:
        vertices: ``(B, V, 3)`` vertices in the compute dtype, on the kernel's device.
        tri: ``(T, 3)`` the shared triangles.
        tol: ``(B,)`` absolute on-cage tolerances.

    Returns:
        The keyword arguments of the kernel but the points and outputs (per-cage tables with a
        leading axis ``B``).
    """
    B, V = vertices.shape[0], vertices.shape[1]
    tri = tri.to(vertices.device)
    c = face_constants(vertices[:, tri])  # (B, T, ...)
    two_area = c["two_area"]
    thin = (c["edges"].square().sum(-1).amax(-1) > THIN_ASPECT * two_area) & (two_area > 0)  # as triangle_data
    tables = _topology(tri, V, c["far_nodes"].shape[2])
    tables.update(
        {
            "P": vertices.contiguous(),
            "nrm": torch.nan_to_num(c["normal"], nan=0.0).contiguous(),
            "two_area": two_area.contiguous(),
            "ell": c["edge_len"].contiguous(),
            "gram": c["gram"].contiguous(),
            "longest": c["longest"].contiguous(),
            "thin": thin.to(torch.int32).contiguous(),
            "far_nodes": c["far_nodes"].contiguous(),
            "far_coef": c["far_coef"].contiguous(),
            "tol": tol.to(device=vertices.device, dtype=vertices.dtype).reshape(B).contiguous(),
        }
    )
    tables.update(_far_tables(vertices))
    return tables


def _topology(tri: torch.Tensor, V: int, Q: int) -> dict[str, object]:
    """The arguments shared by every cage of a batch: the triangles and the constants."""
    return {
        "V": V,
        "tri": tri.to(torch.int32).contiguous(),
        "T": tri.shape[0],
        "Q": Q,
        "near_c": TRITON_SPLIT_FORM_RATIO,
        "far_c": FAR_FIELD_RATIO,
        "cancel_c": CANCELLATION_RATIO,
        "far_always": FAR_ALWAYS_RATIO,
        "thin_distance": THIN_DISTANCE,
    }


def _far_tables(v: torch.Tensor) -> dict[str, torch.Tensor]:
    """Each cage's bounding-box centre ``cen`` ``(B, 3)``, squared radius ``rad2`` ``(B,)`` about
    it and the squared radius of its far region ``far2`` (``FAR_MOMENT`` radii), of ``v``
    ``(B, V, 3)``."""
    c = 0.5 * (v.amin(dim=1) + v.amax(dim=1))
    r2 = ((v - c[:, None]) ** 2).sum(dim=-1).amax(dim=-1)
    return {"cen": c.contiguous(), "rad2": r2.contiguous(), "far2": (FAR_MOMENT * FAR_MOMENT) * r2}


def part_tables(data: TriangleCageData) -> dict[str, object]:
    """:func:`triton_tables` for the triangles of a triquad cage (raw weights, ``normalize=False``):
    their own sum does not show the far field's cancellation, so faces seen small always take the
    quadrature (as the native kernel's part mode)."""
    return _part(triton_tables(data))


def part_batch_tables(vertices: torch.Tensor, tri: torch.Tensor, tol: torch.Tensor) -> dict[str, object]:
    """:func:`batch_tables` for the triangles of a batch of triquad cages (as :func:`part_tables`)."""
    return _part(batch_tables(vertices, tri, tol))


def _part(tables: dict[str, object]) -> dict[str, object]:
    tables["cancel_c"] = 0.0
    tables["far_c"] = PART_FAR_FIELD_RATIO
    return tables


def mvc3d_triton(
    x: torch.Tensor, tables: dict[str, object], block: int | None = None, normalize: bool = True
) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised mean value coordinates of points ``x`` (the tables' dtype and device) and their
    flags, int32: 1 on the cage, 2 where the caller must redo the point with the torch kernel (a
    thin face seen from a few widths). One launch for every cage of the tables.

    One cage (tables of a batch of one): ``x`` ``(n, 3)`` -> ``W`` ``(n, V)``, flags ``(n,)``. A
    batch of ``B`` cages (:func:`batch_tables`): ``x`` ``(B, n, 3)``, or ``(1, n, 3)`` shared by
    every cage -> ``W`` ``(B, n, V)``, flags ``(B, n)``.

    ``block``: points per program (64 on a GPU; the interpreter runs one op per call over the block,
    so there the block is large). ``normalize=False``: the raw weights (rows on the cage hold their
    final values), for the triangles of a triquad cage (tables from :func:`part_tables`).

    Raises:
        ValueError: points whose batch is neither 1 nor the cages'.
    """
    B = tables["P"].shape[0]  # type: ignore[attr-defined]
    X, batched = point_batch(x, B, "mvc3d_triton")
    XB, n = X.shape[0], X.shape[1]
    if block is None:
        block = min(4096, triton.next_power_of_2(max(n, 16))) if interpreted() else 64
    W = torch.empty((B, n, tables["V"]), dtype=x.dtype, device=x.device)
    flags = torch.empty((B, n), dtype=torch.int32, device=x.device)
    if n > 0:
        grid = (B * triton.cdiv(n, block),)
        # float32: no fused multiply-adds. The on-cage test needs the exact zero of a cross product of
        # collinear vectors (a point on an edge shared by coplanar faces, as a triangulated quad's
        # diagonal): fused, ``a b - c d`` with equal products leaves the rounding error of one (3e-9 on
        # the cube), far above the float64-scaled tolerance (4e-14), both faces refuse the point and its
        # row was 0.15 off on an H200 (2026-12-04). float64's residue (1e-17) is below it (passed there).
        fusion = x.dtype != torch.float32
        _mvc3d_kernel[grid](
            X, 0 if XB == 1 else 3 * n, n, **tables, W=W, flags=flags, BLOCK=block, NORMALIZE=normalize,
            num_warps=warps(block), enable_fp_fusion=fusion,
        )  # fmt: skip
    return (W, flags) if batched else (W[0], flags[0])
