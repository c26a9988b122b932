"""Triton kernel of the analytic gradients and Hessians of 2D mean value coordinates (closed
polygons): the formulas of the native kernel (``torchcage/backends/native/mvcd2d.c``), a block of points
per program and a loop over the edges.

Edge ``(j, k)`` adds ``t / r_j`` to ``w_j`` and ``t / r_k`` to ``w_k``, ``t = tan(alpha / 2)`` in
its cancellation-free form (``c / (r_j r_k + d)`` where ``d >= 0``, ``(r_j r_k - d) / c``
elsewhere), every quantity a second-order jet: value, gradient ``(x, y)`` and Hessian
``(xx, yy, xy)``, six block tensors. As in the native kernel, every weight is multiplied by
``c*``, the ``c`` of the obtuse edge of smallest ``|c|`` (the same coordinates once normalised),
and that edge's ``t c*`` is ``r_j r_k - d``: next to an edge the weights and their total then stay
O(1). The kernel writes the weights' jets ``(n, V, 6)``; :func:`mvcd2d_triton` normalises them in
torch on the same device (by the total, or far away by the first moment, as the native kernel).

Shapes: ``P (V, 2)``, ``edges (E, 2)`` int32, ``X (n, 2)`` -> ``lam (n, V)``, ``grad (n, V, 2)``,
``hess (n, V, 2, 2)`` and ``flags (n,)`` (1: on the polygon, where the rows hold the linear
interpolant along the edge and its derivative; 2: the total weight vanishes). A batch of ``B``
polygons with one topology is one launch (:func:`mvcd2d_triton_batch`): ``P (B, V, 2)``, points
``(B or 1, n, 2)``, every output with a leading ``B``.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from torchcage._core.common import FAR_MOMENT, on_cage_tolerance
from torchcage.backends.triton import interpreted, point_batch, warps
from torchcage.cage import Cage

__all__ = ["batch_tables", "derivative_tables", "mvcd2d_triton", "mvcd2d_triton_batch"]


@triton.jit
def _jmul(av, ax, ay, axx, ayy, axy, bv, bx, by, bxx, byy, bxy):
    """The product of two jets (value, gradient x y, Hessian xx yy xy)."""
    return (
        av * bv,
        av * bx + bv * ax,
        av * by + bv * ay,
        av * bxx + bv * axx + 2.0 * ax * bx,
        av * byy + bv * ayy + 2.0 * ay * by,
        av * bxy + bv * axy + ax * by + ay * bx,
    )


@triton.jit
def _jf1(v, x, y, xx, yy, xy, f, f1, f2):
    """``f(a)`` of a jet ``a`` from ``f``, ``f'`` and ``f''`` at its value."""
    return f, f1 * x, f1 * y, f1 * xx + f2 * x * x, f1 * yy + f2 * y * y, f1 * xy + f2 * x * y


@triton.jit
def _jrecip(v, x, y, xx, yy, xy):
    r = 1.0 / v
    return _jf1(v, x, y, xx, yy, xy, r, -r * r, 2.0 * r * r * r)


@triton.jit
def _jsqrt(v, x, y, xx, yy, xy):
    s = tl.sqrt(v)
    i = 1.0 / tl.where(s > 0, s, 1.0)
    return _jf1(v, x, y, xx, yy, xy, s, 0.5 * i, -0.25 * i * i * i)


@triton.jit
def _jdiv(av, ax, ay, axx, ayy, axy, bv, bx, by, bxx, byy, bxy):
    rv, rx, ry, rxx, ryy, rxy = _jrecip(bv, bx, by, bxx, byy, bxy)
    return _jmul(av, ax, ay, axx, ayy, axy, rv, rx, ry, rxx, ryy, rxy)


@triton.jit
def _acc(row, v, live, wv, wx, wy, wxx, wyy, wxy):
    """``ACC[p, v, :] += w`` for the block's points."""
    base = row + 6 * v
    tl.store(base, tl.load(base, mask=live, other=0.0) + wv, mask=live)
    tl.store(base + 1, tl.load(base + 1, mask=live, other=0.0) + wx, mask=live)
    tl.store(base + 2, tl.load(base + 2, mask=live, other=0.0) + wy, mask=live)
    tl.store(base + 3, tl.load(base + 3, mask=live, other=0.0) + wxx, mask=live)
    tl.store(base + 4, tl.load(base + 4, mask=live, other=0.0) + wyy, mask=live)
    tl.store(base + 5, tl.load(base + 5, mask=live, other=0.0) + wxy, mask=live)


@triton.jit
def _mvcd2d_kernel(X, xs, n, P, V, edges, E, tol, ACC, flags, ends, BLOCK: tl.constexpr):
    # one program: a block of points against polygon b (program index b * blocks + block); the
    # edges are shared, the vertices and the tolerance have a leading polygon axis
    pid = tl.program_id(0)
    nblk = tl.cdiv(n, BLOCK)
    b = (pid // nblk).to(tl.int64)
    offs = (pid % nblk) * BLOCK + tl.arange(0, BLOCK)
    live = offs < n
    P += b * V * 2
    tol = tl.load(tol + b)
    X += b * xs
    x0 = tl.load(X + 2 * offs, mask=live, other=0.0)
    x1 = tl.load(X + 2 * offs + 1, mask=live, other=0.0)
    point = b * n + offs.to(tl.int64)
    row = ACC + point * (6 * V)
    zero = tl.zeros_like(x0)
    for q in range(6 * V):
        tl.store(row + q, zero, mask=live)
    # c* (value and gradient; c is affine in x): the obtuse edge (d < 0) of smallest |c| != 0
    best = tl.full(x0.shape, -1, tl.int32)
    cbest = zero + float("inf")
    sv = zero + 1.0
    sx = zero
    sy = zero
    for q in range(E):
        j = tl.load(edges + 2 * q)
        k = tl.load(edges + 2 * q + 1)
        pjx = tl.load(P + 2 * j)
        pjy = tl.load(P + 2 * j + 1)
        pkx = tl.load(P + 2 * k)
        pky = tl.load(P + 2 * k + 1)
        aj0 = pjx - x0
        aj1 = pjy - x1
        cv = aj0 * (pky - pjy) - aj1 * (pkx - pjx)
        dv = aj0 * (pkx - x0) + aj1 * (pky - x1)
        take = (dv < 0) & (cv != 0) & (tl.abs(cv) < cbest)
        cbest = tl.where(take, tl.abs(cv), cbest)
        best = tl.where(take, q, best)
        sv = tl.where(take, cv, sv)
        sx = tl.where(take, pjy - pky, sx)
        sy = tl.where(take, -(pjx - pkx), sy)
    on = offs < 0
    oj = tl.zeros_like(offs)
    ok = tl.zeros_like(offs)
    for q in range(E):
        j = tl.load(edges + 2 * q)
        k = tl.load(edges + 2 * q + 1)
        pjx = tl.load(P + 2 * j)
        pjy = tl.load(P + 2 * j + 1)
        pkx = tl.load(P + 2 * k)
        pky = tl.load(P + 2 * k + 1)
        aj0 = pjx - x0
        aj1 = pjy - x1
        ak0 = pkx - x0
        ak1 = pky - x1
        E0 = pjx - pkx
        E1 = pjy - pky
        ell = tl.sqrt(E0 * E0 + E1 * E1)
        # c = a_j x (p_k - p_j), exact far away; d = a_j . a_k; r = |a|
        cv = -aj0 * E1 + aj1 * E0
        dv = aj0 * ak0 + aj1 * ak1
        dx = -(aj0 + ak0)
        dy = -(aj1 + ak1)
        two = zero + 2.0
        rjv, rjx, rjy, rjxx, rjyy, rjxy = _jsqrt(aj0 * aj0 + aj1 * aj1, -2.0 * aj0, -2.0 * aj1, two, two, zero)
        rkv, rkx, rky, rkxx, rkyy, rkxy = _jsqrt(ak0 * ak0 + ak1 * ak1, -2.0 * ak0, -2.0 * ak1, two, two, zero)
        hit = (rjv <= tol) | (rkv <= tol) | ((tl.abs(cv) <= tol * ell) & (dv <= 0))
        take = hit & ~on
        oj = tl.where(take, j, oj)
        ok = tl.where(take, k, ok)
        on = on | hit
        rrv, rrx, rry, rrxx, rryy, rrxy = _jmul(rjv, rjx, rjy, rjxx, rjyy, rjxy, rkv, rkx, rky, rkxx, rkyy, rkxy)
        # the three forms of t: r_j r_k - d (the c* edge), c* c / (rr + d) (d >= 0), c* (rr - d) / c
        mv = rrv - dv
        mx = rrx - dx
        my = rry - dy
        mxx = rrxx - 2.0
        myy = rryy - 2.0
        mxy = rrxy
        safe_c = tl.where(cv != 0, cv, 1.0)
        acute = dv >= 0
        nv = tl.where(acute, cv, mv)
        nx = tl.where(acute, E1, mx)
        ny = tl.where(acute, -E0, my)
        nxx = tl.where(acute, zero, mxx)
        nyy = tl.where(acute, zero, myy)
        nxy = tl.where(acute, zero, mxy)
        pv = tl.where(acute, rrv + dv, safe_c)
        pv = tl.where(pv != 0, pv, 1.0)
        px = tl.where(acute, rrx + dx, E1)
        py = tl.where(acute, rry + dy, -E0)
        pxx = tl.where(acute, rrxx + 2.0, zero)
        pyy = tl.where(acute, rryy + 2.0, zero)
        pxy = tl.where(acute, rrxy, zero)
        qv, qx, qy, qxx, qyy, qxy = _jdiv(nv, nx, ny, nxx, nyy, nxy, pv, px, py, pxx, pyy, pxy)
        tv, tx, ty, txx, tyy, txy = _jmul(sv, sx, sy, zero, zero, zero, qv, qx, qy, qxx, qyy, qxy)
        own = best == q
        tv = tl.where(own, mv, tv)
        tx = tl.where(own, mx, tx)
        ty = tl.where(own, my, ty)
        txx = tl.where(own, mxx, txx)
        tyy = tl.where(own, myy, tyy)
        txy = tl.where(own, mxy, txy)
        rjv = tl.where(rjv > 0, rjv, 1.0)
        rkv = tl.where(rkv > 0, rkv, 1.0)
        wv, wx, wy, wxx, wyy, wxy = _jdiv(tv, tx, ty, txx, tyy, txy, rjv, rjx, rjy, rjxx, rjyy, rjxy)
        _acc(row, j, live & ~on, wv, wx, wy, wxx, wyy, wxy)
        wv, wx, wy, wxx, wyy, wxy = _jdiv(tv, tx, ty, txx, tyy, txy, rkv, rkx, rky, rkxx, rkyy, rkxy)
        _acc(row, k, live & ~on, wv, wx, wy, wxx, wyy, wxy)
    tl.store(flags + point, tl.where(on, 1, 0), mask=live)
    tl.store(ends + 2 * point, oj, mask=live)
    tl.store(ends + 2 * point + 1, ok, mask=live)


def derivative_tables(cage: Cage, dtype: torch.dtype) -> dict[str, object]:
    """The kernel's arguments for one polygon (a batch of one; ``dtype``, the cage's device)."""
    tol = torch.tensor([on_cage_tolerance(cage)], dtype=dtype, device=cage.device)
    return batch_tables(cage.vertices.detach().to(dtype)[None], cage.edges, tol)


def batch_tables(vertices: torch.Tensor, edges: torch.Tensor, tol: torch.Tensor) -> dict[str, object]:
    """The kernel's arguments for a batch of polygons with one topology (no host synchronisation).

    Args:
        vertices: ``(B, V, 2)`` vertices (float64: the jets of far points overflow in float32), on
            the kernel's device.
        edges: ``(E, 2)`` the shared directed edges.
        tol: ``(B,)`` absolute on-polygon tolerances.
    """
    v = vertices.detach().contiguous()
    e = edges.to(device=v.device, dtype=torch.int32).contiguous()
    return {"P": v, "V": v.shape[1], "edges": e, "E": e.shape[0], "tol": tol.to(v.device, v.dtype).contiguous()}


def _jet_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Product of jets ``(..., 6)`` (value, x, y, xx, yy, xy), broadcast."""
    av, ax, ay, axx, ayy, axy = a.unbind(-1)
    bv, bx, by, bxx, byy, bxy = b.unbind(-1)
    return torch.stack(
        [av * bv, av * bx + bv * ax, av * by + bv * ay, av * bxx + bv * axx + 2 * ax * bx,
         av * byy + bv * ayy + 2 * ay * by, av * bxy + bv * axy + ax * by + ay * bx], dim=-1,
    )  # fmt: skip


def _jet_recip(a: torch.Tensor) -> torch.Tensor:
    v, x, y, xx, yy, xy = a.unbind(-1)
    r = 1.0 / v
    f1, f2 = -r * r, 2 * r * r * r
    return torch.stack([r, f1 * x, f1 * y, f1 * xx + f2 * x * x, f1 * yy + f2 * y * y, f1 * xy + f2 * x * y], -1)


def mvcd2d_triton(
    x: torch.Tensor, cage: Cage, order: int, block: int | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Coordinates ``lam (n, V)``, gradients ``(n, V, 2)``, Hessians ``(n, V, 2, 2)`` (empty for
    ``order=1``) and flags ``(n,)`` (uint8: 1 on the polygon, 2 the total weight vanishes) of points
    ``x (n, 2)``, computed in float64 on the points' device (as every backend of the derivatives:
    in float32 the jets of far points overflow).

    The public way in is ``F.mean_value_derivatives(points, polygon, backend="triton")`` (or
    ``"auto"`` for CUDA points), and the autograd Functions take it for 2D CUDA points.
    """
    tables = derivative_tables(cage.with_vertices(cage.vertices.to(x.device)), torch.float64)
    lam, grad, hess, flags = mvcd2d_triton_batch(x.detach().to(torch.float64)[None], tables, order, block)
    return lam[0], grad[0], hess[0] if order == 2 else hess, flags[0]


def mvcd2d_triton_batch(
    x: torch.Tensor, tables: dict[str, object], order: int, block: int | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`mvcd2d_triton` for a batch of ``B`` polygons with one topology in one launch: float64
    points ``x`` ``(B, n, 2)``, or ``(1, n, 2)`` shared by every polygon, on the tables' device
    (:func:`batch_tables`) -> ``lam (B, n, V)``, ``grad (B, n, V, 2)``, ``hess (B, n, V, 2, 2)``
    (empty for ``order=1``) and the uint8 flags ``(B, n)``. Element by element the numbers of
    :func:`mvcd2d_triton` on each polygon, to rounding.

    Raises:
        ValueError: points whose batch is neither 1 nor the polygons'.
    """
    P = tables["P"]
    B, V = P.shape[0], tables["V"]  # type: ignore[attr-defined]
    X, _ = point_batch(x, B, "mvcd2d_triton_batch", "polygons", dim=2)
    XB, n = X.shape[0], X.shape[1]
    dtype, dev = torch.float64, X.device
    acc = torch.empty((B, n, V, 6), dtype=dtype, device=dev)
    flags = torch.empty((B, n), dtype=torch.int32, device=dev)
    ends = torch.empty((B, n, 2), dtype=torch.int32, device=dev)
    if block is None:
        block = min(1024, triton.next_power_of_2(max(n, 16))) if interpreted() else 128
    if n:
        _mvcd2d_kernel[(B * triton.cdiv(n, block),)](
            X, 0 if XB == 1 else 2 * n, n, **tables, ACC=acc, flags=flags, ends=ends, BLOCK=block,
            num_warps=warps(block),
        )  # fmt: skip
    on = flags == 1
    c = 0.5 * (P.amin(dim=1) + P.amax(dim=1))  # (B, 2): each bounding box's centre
    Pc = P - c[:, None]  # (B, V, 2)
    far2 = FAR_MOMENT * FAR_MOMENT * (Pc**2).sum(dim=-1).amax(dim=-1)  # (B,)
    y = X - c[:, None]  # (B, n, 2)
    y2 = (y * y).sum(dim=-1)
    far = (y2 > far2[:, None]) & ~on
    # the total as a jet: the sum of the weights, or far away their first moment (P - c) . y / |y|^2
    total = acc.sum(dim=2)  # (B, n, 6)
    if bool(far.any()):
        bi, ni = torch.nonzero(far, as_tuple=True)
        a = acc[bi, ni]  # (m, V, 6)
        # (m, 2, 6); one cage: its vertices shared by the rows, as the single-cage kernel always did
        S = torch.einsum("nvk,vd->ndk", a, Pc[0]) if B == 1 else torch.einsum("mvk,mvd->mdk", a, Pc[bi])
        yf, y2f = y[bi, ni], y2[bi, ni]
        yj = torch.zeros(a.shape[0], 2, 6, dtype=dtype, device=dev)
        yj[:, 0, 0], yj[:, 0, 1] = yf[:, 0], 1.0
        yj[:, 1, 0], yj[:, 1, 2] = yf[:, 1], 1.0
        num = _jet_mul(S, yj).sum(dim=1)
        den = torch.zeros_like(num)
        den[:, 0], den[:, 1], den[:, 2], den[:, 3], den[:, 4] = y2f, 2 * yf[:, 0], 2 * yf[:, 1], 2.0, 2.0
        total[bi, ni] = _jet_mul(num, _jet_recip(den))
    bad = ~on & ~((total[..., 0] != 0) & torch.isfinite(total[..., 0]))
    safe = torch.where(bad[..., None], torch.ones_like(total), total)
    lam6 = _jet_mul(acc, _jet_recip(safe)[:, :, None, :])  # (B, n, V, 6)
    lam = lam6[..., 0]
    grad = lam6[..., 1:3].clone()
    hess = torch.empty((B, n, V, 2, 2) if order == 2 else (0,), dtype=dtype, device=dev)
    if order == 2:
        hess[..., 0, 0], hess[..., 1, 1] = lam6[..., 3], lam6[..., 4]
        hess[..., 0, 1] = hess[..., 1, 0] = lam6[..., 5]
    if bool(on.any()):  # on the polygon: the linear interpolant along the edge, its derivative
        bi, ni = torch.nonzero(on, as_tuple=True)
        j, k = ends[bi, ni, 0].long(), ends[bi, ni, 1].long()
        pj, e = P[bi, j], P[bi, k] - P[bi, j]
        l2 = (e * e).sum(dim=1)
        t = (((X[bi if XB > 1 else torch.zeros_like(bi), ni] - pj) * e).sum(dim=1) / l2).clamp(0.0, 1.0)
        lam[bi, ni] = 0.0
        grad[bi, ni] = 0.0
        lam[bi, ni, j] = 1.0 - t
        lam[bi, ni, k] = t
        inner = (t > 0) & (t < 1)
        g = torch.where(inner[:, None], e / l2[:, None], torch.zeros_like(e))
        grad[bi, ni, k] = g
        grad[bi, ni, j] = -g
        if order == 2:
            hess[bi, ni] = 0.0
    out = torch.where(on, 1, torch.where(bad, 2, 0)).to(torch.uint8)
    return lam, grad, hess, out
