"""Triton kernel of 2D mean value coordinates (closed polygons): the formulas of the native kernel
(``torchcage/backends/native/mvc2d.c``: half-angle tangents in their non-cancelling form, linear
interpolation on the polygon, the first moment as the total far away), a block of points per
program and a loop over the edges.

Shapes: a batch of ``B`` polygons with one topology (one polygon: ``B = 1``), ``P (B, V, 2)``,
``edges (E, 2)`` int32 (counter-clockwise), per-polygon ``cen (B, 2)``, ``far2``, ``tol (B,)``,
``X (B or 1, n, 2)`` -> ``W (B, n, V)`` (normalised) and ``flags (B, n)`` int32 (1: on the polygon).
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from torchcage._core.common import FAR_MOMENT, on_cage_tolerance
from torchcage.backends.triton import interpreted, point_batch, warps
from torchcage.cage import Cage

__all__ = ["batch_tables", "mvc2d_triton", "triton_tables"]


@triton.jit
def _mvc2d_kernel(X, xs, n, P, V, edges, E, cen, far2, tol, W, flags, BLOCK: tl.constexpr):
    # one program: a block of points against polygon b (program index b * blocks + block); the
    # edges are shared, every other table has a leading polygon axis
    pid = tl.program_id(0)
    nblk = tl.cdiv(n, BLOCK)
    b = (pid // nblk).to(tl.int64)
    offs = (pid % nblk) * BLOCK + tl.arange(0, BLOCK)
    live = offs < n
    P += b * V * 2
    c0 = tl.load(cen + 2 * b)
    c1 = tl.load(cen + 2 * b + 1)
    far2 = tl.load(far2 + b)
    tol = tl.load(tol + b)
    X += b * xs
    x0 = tl.load(X + 2 * offs, mask=live, other=0.0)
    x1 = tl.load(X + 2 * offs + 1, mask=live, other=0.0)
    point = b * n + offs.to(tl.int64)
    row = W + point * V
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
    tl.store(flags + point, tl.where(on, 1, 0), mask=live)


def triton_tables(cage: Cage, dtype: torch.dtype) -> dict[str, object]:
    """The kernel's arguments for one polygon (a batch of one; ``dtype``, the cage's device)."""
    tol = torch.tensor([on_cage_tolerance(cage)], dtype=dtype, device=cage.device)
    return batch_tables(cage.vertices.to(dtype)[None], cage.edges, tol)


def batch_tables(vertices: torch.Tensor, edges: torch.Tensor, tol: torch.Tensor) -> dict[str, object]:
    """The kernel's arguments for a batch of polygons with one topology, by one set of tensor
    operations (no host synchronisation).

    Args:
        vertices: ``(B, V, 2)`` vertices in the compute dtype, on the kernel's device.
        edges: ``(E, 2)`` the shared directed edges.
        tol: ``(B,)`` absolute on-polygon tolerances.
    """
    v = vertices.contiguous()
    c = 0.5 * (v.amin(dim=1) + v.amax(dim=1))  # (B, 2): each bounding box's centre
    r2 = ((v - c[:, None]) ** 2).sum(dim=-1).amax(dim=-1)  # (B,)
    e = edges.to(v.device, torch.int32).contiguous()
    far2 = (FAR_MOMENT * FAR_MOMENT * r2).contiguous()
    return {"P": v, "V": v.shape[1], "edges": e, "E": e.shape[0], "cen": c.contiguous(), "far2": far2,
            "tol": tol.to(v.device, v.dtype).contiguous()}  # fmt: skip


def mvc2d_triton(
    x: torch.Tensor, tables: dict[str, object], block: int | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised 2D mean value coordinates of points ``x`` (the tables' dtype and device) and
    their flags, int32 (1 on the polygon). One launch for every polygon of the tables.

    One polygon (tables of a batch of one): ``x`` ``(n, 2)`` -> ``W`` ``(n, V)``, flags ``(n,)``. A
    batch of ``B`` polygons (:func:`batch_tables`): ``x`` ``(B, n, 2)``, or ``(1, n, 2)`` shared by
    every polygon -> ``W`` ``(B, n, V)``, flags ``(B, n)``.

    Raises:
        ValueError: points whose batch is neither 1 nor the polygons'.
    """
    B = tables["P"].shape[0]  # type: ignore[attr-defined]
    X, batched = point_batch(x, B, "mvc2d_triton", "polygons", dim=2)
    XB, n = X.shape[0], X.shape[1]
    if block is None:
        block = min(4096, triton.next_power_of_2(max(n, 16))) if interpreted() else 128
    W = torch.empty((B, n, tables["V"]), dtype=x.dtype, device=x.device)
    flags = torch.empty((B, n), dtype=torch.int32, device=x.device)
    if n:
        grid = (B * triton.cdiv(n, block),)
        _mvc2d_kernel[grid](X, 0 if XB == 1 else 2 * n, n, **tables, W=W, flags=flags, BLOCK=block,
                            num_warps=warps(block))  # fmt: skip
    return (W, flags) if batched else (W[0], flags[0])
