"""Triton kernel of 2D mean value coordinates (closed polygons): the formulas of the native kernel
(``torchcage/backends/native/mvc2d.c``: half-angle tangents in their non-cancelling form, linear
interpolation on the polygon, the first moment as the total far away), a block of points per
program and a loop over the edges.

Shapes: ``P (V, 2)``, ``edges (E, 2)`` int32 (counter-clockwise), ``X (n, 2)`` -> ``W (n, V)``
(normalised) and ``flags (n,)`` int32 (1: on the polygon).
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from torchcage._core.common import FAR_MOMENT, on_cage_tolerance
from torchcage.backends.triton import interpreted, warps
from torchcage.cage import Cage

__all__ = ["mvc2d_triton", "triton_tables"]


@triton.jit
def _mvc2d_kernel(X, n, P, V, edges, E, c0, c1, far2, tol, W, flags, BLOCK: tl.constexpr):
    offs = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = offs < n
    x0 = tl.load(X + 2 * offs, mask=live, other=0.0)
    x1 = tl.load(X + 2 * offs + 1, mask=live, other=0.0)
    row = W + offs.to(tl.int64) * V
    for v in range(V):
        tl.store(row + v, tl.zeros_like(x0), mask=live)
    on = offs < 0
    oj = tl.zeros_like(offs)
    ok = tl.zeros_like(offs)
    ot = tl.zeros_like(x0)
    for q in range(E):
        j = tl.load(edges + 2 * q)
        k = tl.load(edges + 2 * q + 1)
        pjx = tl.load(P + 2 * j)
        pjy = tl.load(P + 2 * j + 1)
        pkx = tl.load(P + 2 * k)
        pky = tl.load(P + 2 * k + 1)
        ajx = pjx - x0
        ajy = pjy - x1
        akx = pkx - x0
        aky = pky - x1
        ex = pkx - pjx
        ey = pky - pjy
        Rj = tl.sqrt(ajx * ajx + ajy * ajy)
        Rk = tl.sqrt(akx * akx + aky * aky)
        cross = ajx * ey - ajy * ex
        dot = ajx * akx + ajy * aky
        RR = Rj * Rk
        ell2 = ex * ex + ey * ey
        ell = tl.sqrt(ell2)
        t = -(ajx * ex + ajy * ey) / ell2
        hit = ((tl.abs(cross) / ell <= tol) & (t >= -tol / ell) & (t <= 1 + tol / ell)) | (Rj <= tol) | (Rk <= tol)
        tt = tl.where(Rj <= tol, 0.0, tl.where(Rk <= tol, 1.0, tl.minimum(tl.maximum(t, 0.0), 1.0)))
        take = hit & ~on
        oj = tl.where(take, j, oj)
        ok = tl.where(take, k, ok)
        ot = tl.where(take, tt, ot)
        on = on | hit
        num = tl.where(dot >= 0, cross, tl.where(cross != 0, RR - dot, 0.0))
        den = tl.where(dot >= 0, RR + dot, tl.where(cross != 0, cross, 1.0))
        tan_half = num / tl.where(den != 0, den, 1.0)
        wj = tan_half / tl.where(Rj > 0, Rj, 1.0)
        wk = tan_half / tl.where(Rk > 0, Rk, 1.0)
        tl.store(row + j, tl.load(row + j, mask=live, other=0.0) + wj, mask=live)
        tl.store(row + k, tl.load(row + k, mask=live, other=0.0) + wk, mask=live)
    y0 = x0 - c0
    y1 = x1 - c1
    yy = y0 * y0 + y1 * y1
    distant = yy > far2
    s = tl.zeros_like(x0)
    mom = tl.zeros_like(x0)
    for v in range(V):
        wv = tl.load(row + v, mask=live, other=0.0)
        s += wv
        mom += wv * ((tl.load(P + 2 * v) - c0) * y0 + (tl.load(P + 2 * v + 1) - c1) * y1)
    den = tl.where(distant, mom / tl.where(distant, yy, 1.0), s)
    inv = 1.0 / den
    for v in range(V):
        wv = tl.load(row + v, mask=live, other=0.0)
        tl.store(row + v, tl.where(on, 0.0, wv * inv), mask=live)
    tl.store(row + oj, tl.load(row + oj, mask=live & on, other=0.0) + (1.0 - ot), mask=live & on)
    tl.store(row + ok, tl.load(row + ok, mask=live & on, other=0.0) + ot, mask=live & on)
    tl.store(flags + offs, tl.where(on, 1, 0), mask=live)


def triton_tables(cage: Cage, dtype: torch.dtype) -> dict[str, object]:
    """The kernel's per-polygon arguments (``dtype``, the cage's device)."""
    v = cage.vertices.to(dtype).contiguous()
    lo, hi = v.min(dim=0).values, v.max(dim=0).values
    c = 0.5 * (lo + hi)
    r2 = float(((v - c) ** 2).sum(dim=1).max())
    edges = cage.edges.to(torch.int32).contiguous()
    return {"P": v, "V": v.shape[0], "edges": edges, "E": edges.shape[0], "c0": float(c[0]), "c1": float(c[1]),
            "far2": FAR_MOMENT * FAR_MOMENT * r2, "tol": on_cage_tolerance(cage)}  # fmt: skip


def mvc2d_triton(
    x: torch.Tensor, tables: dict[str, object], block: int | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised 2D mean value coordinates ``(n, V)`` of points ``x`` ``(n, 2)`` (the tables' dtype
    and device) and their flags ``(n,)`` int32 (1 on the polygon)."""
    n = x.shape[0]
    if block is None:
        block = min(4096, triton.next_power_of_2(max(n, 16))) if interpreted() else 128
    W = torch.empty((n, tables["V"]), dtype=x.dtype, device=x.device)
    flags = torch.empty(n, dtype=torch.int32, device=x.device)
    if n:
        grid = (triton.cdiv(n, block),)
        _mvc2d_kernel[grid](x.contiguous(), n, **tables, W=W, flags=flags, BLOCK=block, num_warps=warps(block))
    return W, flags
