"""Triton kernel of 3D Green coordinates (closed triangle cages): the formulas of the native kernel
(``torchcage/backends/native/gc3d.c``, ``tc_gc_point``; derivation in :mod:`.kernel3d`),
a block of points per program and a loop over the faces.

Per point–face pair: the edge integrals ``I_e`` (``log`` of the ratio that does not cancel), the
Van Oosterom–Strackee solid angle away from the face's plane and its corners, the edge sum near
them (with ``h`` and the foot's distances to the edge lines from the edges' perpendiculars, taken
from their nearer ends: the same bits for both faces of an edge), then ``psi`` and the corner terms
of ``phi``. Points on a face get the principal values plus the hat values of the largest face
holding them with the jump weight ``1 - omega / 4 pi``. Pairs of a thin face seen from a few widths
are flagged: the caller redoes those points with the torch kernel's swept form. Faces seen from far
(:mod:`.far_triangle`) take its Gauss rule, in the blocks where a point needs it.

Shapes: a batch of ``B`` cages with one topology (one cage: ``B = 1``), ``P (B, V, 3)``, ``tri
(T, 3)`` int32, per-face tables ``(B, T, ...)``, ``X (B or 1, n, 3)`` -> ``PHI (B, n, V)``, ``PSI
(B, n, T)`` (the bare integrals, as :func:`.dispatch.green_flat`) and ``flags (B, n)`` int32 (2:
redo with the torch kernel, else 1: on the cage).
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from torchcage._core.thin_triangle import THIN_ASPECT, THIN_DISTANCE
from torchcage.backends.triton import interpreted, point_batch, warps
from torchcage.backends.triton.common import atan2, log
from torchcage.families.green.far_triangle import FAR_RATIO
from torchcage.families.green.kernel3d import (
    PERPENDICULAR_PLANE_RATIO,
    PERPENDICULAR_VERTEX_RATIO,
    TriangleGreenData,
    batch_face_tables,
)
from torchcage.families.mean_value.triton.mvc3d import _thin_pair

__all__ = ["batch_tables", "gc3d_triton", "triton_tables"]

INV_4PI = tl.constexpr(0.07957747154594767)


@triton.jit
def _perpendicular(ajx, ajy, ajz, akx, aky, akz, Rj, Rk, ux, uy, uz):
    """The perpendicular from the point to the line of an edge (unit direction ``u``), from the
    edge's nearer end (its midpoint when both are as near): ``(wx, wy, wz)``."""
    mx = tl.where(Rj < Rk, ajx, tl.where(Rk < Rj, akx, 0.5 * (ajx + akx)))
    my = tl.where(Rj < Rk, ajy, tl.where(Rk < Rj, aky, 0.5 * (ajy + aky)))
    mz = tl.where(Rj < Rk, ajz, tl.where(Rk < Rj, akz, 0.5 * (ajz + akz)))
    mu = mx * ux + my * uy + mz * uz
    return mx - mu * ux, my - mu * uy, mz - mu * uz


@triton.jit
def _edge_log(ajx, ajy, ajz, Rj, Rk, lj, lk, ux, uy, uz, tiny, huge):
    """``I = int_e dl / r`` of the edge from ``a_j`` to ``a_k`` (``tc_edge_log_arg``: the ratio of
    sums that does not cancel, 0 on the edge itself, where every use multiplies it by 0; ``tiny`` and
    ``huge`` clamp the ratio's denominator and value: 1e-300 and 1e300 in float64 as the native
    kernel, 1e-30 and 1e30 in float32)."""
    cx = ajy * uz - ajz * uy
    cy = ajz * ux - ajx * uz
    cz = ajx * uy - ajy * ux
    c2 = cx * cx + cy * cy + cz * cz
    pk = Rk + lk
    mj = Rj - lj
    num = tl.where(lj >= 0, pk, tl.where(lk <= 0, mj, pk * mj))
    den = tl.where(lj >= 0, Rj + lj, tl.where(lk <= 0, Rk - lk, c2))
    r = num / tl.where(den > tiny, den, tiny)
    r = tl.where(num > 0, tl.minimum(r, huge), 1.0)
    return log(r)


@triton.jit
def _edge_angle(d, lj, lk, Rj, Rk, h):
    """One edge's term of the solid angle's edge sum (no cancellation near the plane)."""
    habs = tl.abs(h)
    R0sq = d * d + h * h
    return atan2(d * lk, R0sq + habs * Rk) - atan2(d * lj, R0sq + habs * Rj)


@triton.jit
def _far_face(x0, x1, x2, far, f, h, far_nodes, far_w, far_bary, Q, psi, om, p0, p1, p2):
    """Face ``f``'s ``psi``, solid angle and corner terms by the far-field rule (module
    ``functional/_far_triangle``) in the lanes ``far``, the closed forms' values elsewhere."""
    s1 = tl.zeros_like(x0)
    s3 = tl.zeros_like(x0)
    b0 = tl.zeros_like(x0)
    b1 = tl.zeros_like(x0)
    b2 = tl.zeros_like(x0)
    for q in range(Q):
        node = far_nodes + 3 * (Q * f + q)
        ax = tl.load(node) - x0
        ay = tl.load(node + 1) - x1
        az = tl.load(node + 2) - x2
        ir = 1.0 / tl.sqrt(ax * ax + ay * ay + az * az)
        w1 = tl.load(far_w + Q * f + q) * ir
        w3 = w1 * ir * ir
        s1 += w1
        s3 += w3
        b0 += w3 * tl.load(far_bary + 3 * q)
        b1 += w3 * tl.load(far_bary + 3 * q + 1)
        b2 += w3 * tl.load(far_bary + 3 * q + 2)
    psi = tl.where(far, s1 * INV_4PI, psi)
    om = tl.where(far, h * s3, om)
    p0 = tl.where(far, h * b0 * INV_4PI, p0)
    p1 = tl.where(far, h * b1 * INV_4PI, p1)
    p2 = tl.where(far, h * b2 * INV_4PI, p2)
    return psi, om, p0, p1, p2


@triton.jit
def _gc3d_kernel(
    X, xs, n, P, V, tri, T, nrm, two_area, ell, edir, eout, gbary, thin, far2, far_nodes, far_w, far_bary, Q, tol,
    plane_c, vertex_c, thin_distance, tiny: tl.constexpr, huge: tl.constexpr, PHI, PSI, flags, BLOCK: tl.constexpr,
    BATCHED: tl.constexpr = True,
):  # fmt: skip
    # one program: a block of points against cage b (program index b * blocks + block); the
    # topology (tri) and the quadrature's barycentrics are shared, every other table has a leading
    # cage axis. One cage (BATCHED false, a compile-time constant): no cage offsets, which take 34
    # more registers per thread (sm_90, float64: 234 batched against 200 for one cage).
    pid = tl.program_id(0)
    if BATCHED:
        nblk = tl.cdiv(n, BLOCK)
        b = (pid // nblk).to(tl.int64)
        offs = (pid % nblk) * BLOCK + tl.arange(0, BLOCK)
        P += b * V * 3
        nrm += b * T * 3
        two_area += b * T
        ell += b * T * 3
        edir += b * T * 9
        eout += b * T * 9
        gbary += b * T * 9
        thin += b * T
        far2 += b * T
        far_nodes += b * T * Q * 3
        far_w += b * T * Q
        tol = tl.load(tol + b)
        X += b * xs
        point = b * n + offs.to(tl.int64)
    else:
        offs = pid * BLOCK + tl.arange(0, BLOCK)
        tol = tl.load(tol)
        point = offs.to(tl.int64)
    live = offs < n
    x0 = tl.load(X + 3 * offs, mask=live, other=0.0)
    x1 = tl.load(X + 3 * offs + 1, mask=live, other=0.0)
    x2 = tl.load(X + 3 * offs + 2, mask=live, other=0.0)
    row = PHI + point * V
    prow = PSI + point * T
    for v in range(V):
        tl.store(row + v, tl.zeros_like(x0), mask=live)
    om_sum = tl.zeros_like(x0)
    redo = offs < 0
    best_area = tl.zeros_like(x0) - 1.0
    bi0 = tl.zeros_like(offs)
    bi1 = tl.zeros_like(offs)
    bi2 = tl.zeros_like(offs)
    bb0 = tl.zeros_like(x0)
    bb1 = tl.zeros_like(x0)
    bb2 = tl.zeros_like(x0)
    for f in range(T):
        i0 = tl.load(tri + 3 * f)
        i1 = tl.load(tri + 3 * f + 1)
        i2 = tl.load(tri + 3 * f + 2)
        a0x = tl.load(P + 3 * i0) - x0
        a0y = tl.load(P + 3 * i0 + 1) - x1
        a0z = tl.load(P + 3 * i0 + 2) - x2
        a1x = tl.load(P + 3 * i1) - x0
        a1y = tl.load(P + 3 * i1 + 1) - x1
        a1z = tl.load(P + 3 * i1 + 2) - x2
        a2x = tl.load(P + 3 * i2) - x0
        a2y = tl.load(P + 3 * i2 + 1) - x1
        a2z = tl.load(P + 3 * i2 + 2) - x2
        R0 = tl.sqrt(a0x * a0x + a0y * a0y + a0z * a0z)
        R1 = tl.sqrt(a1x * a1x + a1y * a1y + a1z * a1z)
        R2 = tl.sqrt(a2x * a2x + a2y * a2y + a2z * a2z)
        nx = tl.load(nrm + 3 * f)
        ny = tl.load(nrm + 3 * f + 1)
        nz = tl.load(nrm + 3 * f + 2)
        A2 = tl.load(two_area + f)
        # edge e runs from corner e + 1 to e + 2: u (direction), m (outward in-plane normal)
        E = edir + 9 * f
        O = eout + 9 * f
        u0x = tl.load(E)
        u0y = tl.load(E + 1)
        u0z = tl.load(E + 2)
        u1x = tl.load(E + 3)
        u1y = tl.load(E + 4)
        u1z = tl.load(E + 5)
        u2x = tl.load(E + 6)
        u2y = tl.load(E + 7)
        u2z = tl.load(E + 8)
        m0x = tl.load(O)
        m0y = tl.load(O + 1)
        m0z = tl.load(O + 2)
        m1x = tl.load(O + 3)
        m1y = tl.load(O + 4)
        m1z = tl.load(O + 5)
        m2x = tl.load(O + 6)
        m2y = tl.load(O + 7)
        m2z = tl.load(O + 8)
        h = nx * a0x + ny * a0y + nz * a0z
        d0 = a1x * m0x + a1y * m0y + a1z * m0z
        d1 = a2x * m1x + a2y * m1y + a2z * m1z
        d2 = a0x * m2x + a0y * m2y + a0z * m2z
        rmin = tl.minimum(tl.minimum(R0, R1), R2)
        rmax = tl.maximum(tl.maximum(R0, R1), R2)
        dead = (tl.zeros_like(h) + A2) <= 0
        near = (tl.abs(h) < plane_c * rmin) | (tl.abs(h) <= tol) | (rmin < vertex_c * rmax) | dead
        # near the plane or a corner: h and the d_e from the edges' perpendiculars
        w0x, w0y, w0z = _perpendicular(a1x, a1y, a1z, a2x, a2y, a2z, R1, R2, u0x, u0y, u0z)
        w1x, w1y, w1z = _perpendicular(a2x, a2y, a2z, a0x, a0y, a0z, R2, R0, u1x, u1y, u1z)
        w2x, w2y, w2z = _perpendicular(a0x, a0y, a0z, a1x, a1y, a1z, R0, R1, u2x, u2y, u2z)
        q0 = w0x * w0x + w0y * w0y + w0z * w0z
        q1 = w1x * w1x + w1y * w1y + w1z * w1z
        q2 = w2x * w2x + w2y * w2y + w2z * w2z
        h0 = w0x * nx + w0y * ny + w0z * nz
        h1 = w1x * nx + w1y * ny + w1z * nz
        h2 = w2x * nx + w2y * ny + w2z * nz
        hn = tl.where((q0 <= q1) & (q0 <= q2), h0, tl.where(q1 <= q2, h1, h2))
        h = tl.where(near, hn, h)
        d0 = tl.where(near, w0x * m0x + w0y * m0y + w0z * m0z, d0)
        d1 = tl.where(near, w1x * m1x + w1y * m1y + w1z * m1z, d1)
        d2 = tl.where(near, w2x * m2x + w2y * m2y + w2z * m2z, d2)
        # the edge integrals
        lj0 = a1x * u0x + a1y * u0y + a1z * u0z
        lk0 = a2x * u0x + a2y * u0y + a2z * u0z
        lj1 = a2x * u1x + a2y * u1y + a2z * u1z
        lk1 = a0x * u1x + a0y * u1y + a0z * u1z
        lj2 = a0x * u2x + a0y * u2y + a0z * u2z
        lk2 = a1x * u2x + a1y * u2y + a1z * u2z
        I0 = _edge_log(a1x, a1y, a1z, R1, R2, lj0, lk0, u0x, u0y, u0z, tiny, huge)
        I1 = _edge_log(a2x, a2y, a2z, R2, R0, lj1, lk1, u1x, u1y, u1z, tiny, huge)
        I2 = _edge_log(a0x, a0y, a0z, R0, R1, lj2, lk2, u2x, u2y, u2z, tiny, huge)
        # the solid angle: Van Oosterom-Strackee away from the plane and the corners, else the edge sum
        c12x = a1y * a2z - a1z * a2y
        c12y = a1z * a2x - a1x * a2z
        c12z = a1x * a2y - a1y * a2x
        den = (
            R0 * R1 * R2
            + (a0x * a1x + a0y * a1y + a0z * a1z) * R2
            + (a0x * a2x + a0y * a2y + a0z * a2z) * R1
            + (a1x * a2x + a1y * a2y + a1z * a2z) * R0
        )
        om_far = 2.0 * atan2(a0x * c12x + a0y * c12y + a0z * c12z, den)
        beta = (
            _edge_angle(d0, lj0, lk0, R1, R2, h)
            + _edge_angle(d1, lj1, lk1, R2, R0, h)
            + _edge_angle(d2, lj2, lk2, R0, R1, h)
        )
        om = tl.where(near, tl.where(h >= 0, beta, -beta), om_far)
        on_face = (tl.abs(h) <= tol) & (d0 >= -tol) & (d1 >= -tol) & (d2 >= -tol) & ~dead
        om = tl.where(on_face | dead, 0.0, om)
        # psi and the corner terms (h K dropped on the plane; an edge through the point drops its I)
        dI = tl.where(d0 != 0, d0 * I0, 0.0) + tl.where(d1 != 0, d1 * I1, 0.0) + tl.where(d2 != 0, d2 * I2, 0.0)
        psi = tl.where(dead, 0.0, (dI - h * om) * INV_4PI)
        Kx = -(m0x * I0 + m1x * I1 + m2x * I2)
        Ky = -(m0y * I0 + m1y * I1 + m2y * I2)
        Kz = -(m0z * I0 + m1z * I1 + m2z * I2)
        hk = tl.where(tl.abs(h) <= tol, 0.0, h)
        G = gbary + 9 * f
        l0 = tl.load(ell + 3 * f)
        l1 = tl.load(ell + 3 * f + 1)
        l2 = tl.load(ell + 3 * f + 2)
        inv_A2 = 1.0 / tl.where(dead, 1.0, A2)
        al0 = d0 * l0 * inv_A2
        al1 = d1 * l1 * inv_A2
        al2 = d2 * l2 * inv_A2
        p0 = (al0 * om + hk * (tl.load(G) * Kx + tl.load(G + 1) * Ky + tl.load(G + 2) * Kz)) * INV_4PI
        p1 = (al1 * om + hk * (tl.load(G + 3) * Kx + tl.load(G + 4) * Ky + tl.load(G + 5) * Kz)) * INV_4PI
        p2 = (al2 * om + hk * (tl.load(G + 6) * Kx + tl.load(G + 7) * Ky + tl.load(G + 8) * Kz)) * INV_4PI
        p0 = tl.where(dead, 0.0, p0)
        p1 = tl.where(dead, 0.0, p1)
        p2 = tl.where(dead, 0.0, p2)
        # seen from far (the nearest corner far_c longest edges away): the Gauss rule, where a lane needs it
        far = (rmin * rmin >= tl.load(far2 + f)) & live
        if tl.max(far.to(tl.int32), axis=0) > 0:
            psi, om, p0, p1, p2 = _far_face(
                x0, x1, x2, far, f, h, far_nodes, far_w, far_bary, Q, psi, om, p0, p1, p2
            )  # fmt: skip
        tl.store(prow + f, psi, mask=live)
        tl.store(row + i0, tl.load(row + i0, mask=live, other=0.0) + p0, mask=live)
        tl.store(row + i1, tl.load(row + i1, mask=live, other=0.0) + p1, mask=live)
        tl.store(row + i2, tl.load(row + i2, mask=live, other=0.0) + p2, mask=live)
        om_sum += om
        # the largest face holding the point: its hat values enter with the jump weight
        take = on_face & (A2 > best_area)
        best_area = tl.where(take, A2, best_area)
        bi0 = tl.where(take, i0, bi0)
        bi1 = tl.where(take, i1, bi1)
        bi2 = tl.where(take, i2, bi2)
        bb0 = tl.where(take, tl.maximum(al0, 0.0), bb0)
        bb1 = tl.where(take, tl.maximum(al1, 0.0), bb1)
        bb2 = tl.where(take, tl.maximum(al2, 0.0), bb2)
        if tl.load(thin + f) != 0:
            redo = redo | _thin_pair(x0, x1, x2, f, P, tri, two_area, thin_distance)
    on = best_area >= 0.0
    bsum = bb0 + bb1 + bb2
    jump = (1.0 - om_sum * INV_4PI) / tl.where(bsum > 0, bsum, 1.0)
    tl.store(row + bi0, tl.load(row + bi0, mask=live & on, other=0.0) + jump * bb0, mask=live & on)
    tl.store(row + bi1, tl.load(row + bi1, mask=live & on, other=0.0) + jump * bb1, mask=live & on)
    tl.store(row + bi2, tl.load(row + bi2, mask=live & on, other=0.0) + jump * bb2, mask=live & on)
    # (redo first: on the cage too, the thin face's principal value needs the swept form)
    flag = tl.where(redo, 2, tl.where(on, 1, 0))
    tl.store(flags + point, flag, mask=live)


def triton_tables(data: TriangleGreenData, vertices: torch.Tensor) -> dict[str, object]:
    """The kernel's arguments for one cage (a batch of one), from the torch kernel's constants
    (compute dtype, the cage's device)."""
    if data.far_nodes is None or data.longest is None:
        raise ValueError("the Triton Green kernel needs the far-field rule's tables (triangle_green_data)")
    geometry = (data.normal, data.two_area, data.edge_dir, data.edge_out, data.grad_bary)
    far = (data.far_nodes[None], data.far_weights[None], data.far_bary)
    tol = torch.full((1,), data.tol, dtype=vertices.dtype, device=vertices.device)
    return _arguments(vertices[None], data.tri, tol, tuple(t[None] for t in geometry), data.longest[None], far)


def batch_tables(vertices: torch.Tensor, tri: torch.Tensor, tol: torch.Tensor) -> dict[str, object]:
    """The kernel's arguments for a batch of cages with one topology, every per-cage table of the
    ``B`` cages computed by one set of tensor operations (element by element the numbers of
    :func:`triton_tables` on ``triangle_green_data`` of that cage, as ``native3d.batch_tables``).

    Args:
        vertices: ``(B, V, 3)`` centred vertices in the compute dtype, on the kernel's device.
        tri: ``(T, 3)`` the shared triangles.
        tol: ``(B,)`` absolute on-cage tolerances.
    """
    tri = tri.to(vertices.device)
    return _arguments(vertices, tri, tol, *batch_face_tables(vertices, tri))


def _arguments(
    vertices: torch.Tensor,
    tri: torch.Tensor,
    tol: torch.Tensor,
    geometry: tuple[torch.Tensor, ...],
    longest: torch.Tensor,
    far: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
) -> dict[str, object]:
    """The kernel's arguments from the faces' ``geometry`` ``(normal, two_area, edge_dir, edge_out,
    grad_bary)`` (each ``(B, T, ...)``), ``longest`` ``(B, T)`` and the far-field rule ``far``
    ``(nodes (B, T, Q, 3), weights (B, T, Q), bary (Q, 3))`` of the cages ``vertices`` ``(B, V, 3)``."""
    normal, two_area, edge_dir, edge_out, grad_bary = geometry
    nodes, weights, bary = far
    live = two_area > 0
    ell = grad_bary.norm(dim=-1) * two_area[..., None]
    thin = (live & (ell.square().amax(dim=-1) > THIN_ASPECT * two_area)).to(torch.int32)  # (_thin_triangle's)
    far2 = torch.where(live & (longest > 0), (FAR_RATIO * longest) ** 2, torch.inf)
    return {
        "P": vertices.contiguous(),
        "V": vertices.shape[1],
        "tri": tri.to(torch.int32).contiguous(),
        "T": tri.shape[0],
        "nrm": normal.contiguous(),
        "two_area": two_area.contiguous(),
        "ell": ell.contiguous(),
        "edir": edge_dir.contiguous(),
        "eout": edge_out.contiguous(),
        "gbary": grad_bary.contiguous(),
        "thin": thin.contiguous(),
        "far2": far2.contiguous(),
        "far_nodes": nodes.contiguous(),
        "far_w": weights.contiguous(),
        "far_bary": bary.contiguous(),
        "Q": bary.shape[0],
        "tol": tol.to(vertices.device, vertices.dtype).contiguous(),
        "plane_c": PERPENDICULAR_PLANE_RATIO,
        "vertex_c": PERPENDICULAR_VERTEX_RATIO,
        "thin_distance": THIN_DISTANCE,
        # (compile-time constants: a Python float argument reaches a compiled kernel as an fp32
        # scalar, where 1e-300 is 0 and 1e300 inf; the interpreter keeps it in float64)
        "tiny": 1e-300 if vertices.dtype == torch.float64 else 1e-30,
        "huge": 1e300 if vertices.dtype == torch.float64 else 1e30,
    }


def gc3d_triton(
    x: torch.Tensor, tables: dict[str, object], block: int | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The bare Green integrals of points ``x`` (the tables' dtype and device) and their flags,
    int32: 2 where the caller must redo the point with the torch kernel (a thin face seen from a
    few widths, on the cage or off it), else 1 on the cage. One launch for every cage of the tables.

    One cage (tables of a batch of one): ``x`` ``(n, 3)`` -> ``phi (n, V)``, ``psi (n, T)``, flags
    ``(n,)``. A batch of ``B`` cages (:func:`batch_tables`): ``x`` ``(B, n, 3)``, or ``(1, n, 3)``
    shared by every cage -> ``phi (B, n, V)``, ``psi (B, n, T)``, flags ``(B, n)``.

    ``block``: points per program (64 on a GPU; the interpreter runs one op per call over the
    block, so there the block is large).

    Raises:
        ValueError: points whose batch is neither 1 nor the cages'.
    """
    B = tables["P"].shape[0]  # type: ignore[attr-defined]
    X, batched = point_batch(x, B, "gc3d_triton")
    XB, n = X.shape[0], X.shape[1]
    if block is None:
        block = min(4096, triton.next_power_of_2(max(n, 16))) if interpreted() else 64
    phi = torch.empty((B, n, tables["V"]), dtype=x.dtype, device=x.device)
    psi = torch.empty((B, n, tables["T"]), dtype=x.dtype, device=x.device)
    flags = torch.empty((B, n), dtype=torch.int32, device=x.device)
    if n > 0:
        _gc3d_kernel[(B * triton.cdiv(n, block),)](
            X, 0 if XB == 1 else 3 * n, n, **tables, PHI=phi, PSI=psi, flags=flags, BLOCK=block, BATCHED=B > 1,
            num_warps=warps(block),
        )  # fmt: skip
    return (phi, psi, flags) if batched else (phi[0], psi[0], flags[0])
