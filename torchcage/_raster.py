"""Rasterisation of a deformed 2D triangle mesh onto a pixel grid: which triangle covers each pixel
centre. Used by the forward mapping of :mod:`torchcage.image`; the choice is discrete (no
gradient), the caller recomputes barycentric coordinates differentiably.
"""

from __future__ import annotations

import torch

from torchcage.backends import native as _native

__all__ = ["rasterize_triangles"]


def rasterize_triangles(
    positions: torch.Tensor, triangles: torch.Tensor, height: int, width: int, values: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Index of a triangle covering each pixel centre, and per-vertex values interpolated there.

    Pixel ``(row, col)`` has its centre at ``x = col``, ``y = row``. A centre on a shared edge goes
    to one of the triangles; where triangles overlap (a folded mesh) one of them is chosen.

    Args:
        positions: ``(B, Nv, 2)`` vertex positions ``(x, y)`` in pixels (no gradient is recorded).
        triangles: ``(T, 3)`` vertex indices.
        height: rows ``H`` of the output grid.
        width: columns ``W`` of the output grid.
        values: ``(Nv, C)`` values at the vertices (no gradient is recorded).

    Returns:
        ``(B, H, W)`` int64 triangle indices, ``-1`` where no triangle covers the centre, and
        ``(B, H, W, C)`` float64 values interpolated linearly in that triangle (0 where none).

    Examples:
        >>> import torch
        >>> P = torch.tensor([[[0.0, 0.0], [3.0, 0.0], [0.0, 3.0]]], dtype=torch.float64)
        >>> which, val = rasterize_triangles(P, torch.tensor([[0, 1, 2]]), 3, 3, P[0])
        >>> which[0]
        tensor([[ 0,  0,  0],
                [ 0,  0,  0],
                [ 0,  0, -1]])
        >>> val[0, 1, 2].round(decimals=12).tolist()   # the positions themselves, at pixel (1, 2)
        [2.0, 1.0]
    """
    P = positions.detach().to(torch.float64)
    S = values.detach().to(torch.float64)
    B = P.shape[0]
    lib = _native.library() if P.device.type == "cpu" else None
    if lib is not None:
        out = torch.empty((B, height, width), dtype=torch.int32)
        val = torch.zeros((B, height, width, S.shape[1]), dtype=torch.float64)
        _native.call(
            lib,
            "tc_raster2d",
            P=P.contiguous(),
            B=B,
            Nv=P.shape[1],
            tri=triangles.to(torch.int32).contiguous(),
            T=triangles.shape[0],
            H=height,
            W=width,
            S=S.contiguous(),
            C=S.shape[1],
            out=out,
            val=val,
        )
        return out.to(torch.int64), val
    which = torch.stack([_rasterize_one(P[b], triangles, height, width) for b in range(B)])
    return which, _interpolate(P, triangles, which, S)


def _interpolate(P: torch.Tensor, tri: torch.Tensor, which: torch.Tensor, S: torch.Tensor) -> torch.Tensor:
    """Values ``S`` ``(Nv, C)`` interpolated at the pixel centres covered by ``which`` ``(B, H, W)``."""
    B, H, W = which.shape
    b_idx, r, c = torch.nonzero(which >= 0, as_tuple=True)
    t = tri[which[b_idx, r, c]]
    a, b, cc = (P[b_idx, t[:, k]] for k in range(3))
    area = (b - a)[:, 0] * (cc - a)[:, 1] - (b - a)[:, 1] * (cc - a)[:, 0]
    y = torch.stack([c, r], dim=1).to(P.dtype)

    def cross(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        return (q - p)[:, 0] * (y - p)[:, 1] - (q - p)[:, 1] * (y - p)[:, 0]

    la, lb = cross(b, cc) / area, cross(cc, a) / area
    val = torch.zeros((B, H, W, S.shape[1]), dtype=P.dtype, device=P.device)
    val[b_idx, r, c] = la[:, None] * S[t[:, 0]] + lb[:, None] * S[t[:, 1]] + (1 - la - lb)[:, None] * S[t[:, 2]]
    return val


def _rasterize_one(P: torch.Tensor, tri: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """Torch fallback for one pose: loops over the offsets inside the largest bounding box,
    vectorised over triangles (the same closed-interior test as the native kernel)."""
    P = P.to(torch.float64)
    a, b, c = P[tri[:, 0]], P[tri[:, 1]], P[tri[:, 2]]
    corners = torch.stack([a, b, c])
    lo = torch.ceil(corners.amin(dim=0)).clamp_min(0)
    hi = torch.floor(corners.amax(dim=0))
    hi = torch.minimum(hi, torch.tensor([W - 1, H - 1], dtype=P.dtype, device=P.device))
    area = (b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]
    keep = (lo <= hi).all(dim=1) & (area != 0)
    idx = torch.nonzero(keep).squeeze(1)
    a, b, c, lo, hi, s = a[idx], b[idx], c[idx], lo[idx], hi[idx], torch.sign(area[idx])
    out = torch.full((H, W), -1, dtype=torch.int64, device=P.device)
    if idx.numel() == 0:
        return out
    ext = (hi - lo).amax(dim=0).to(torch.int64).tolist()

    def edge(p: torch.Tensor, q: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return s * ((q[:, 0] - p[:, 0]) * (y - p[:, 1]) - (q[:, 1] - p[:, 1]) * (x - p[:, 0]))

    for dy in range(int(ext[1]) + 1):
        for dx in range(int(ext[0]) + 1):
            x, y = lo[:, 0] + dx, lo[:, 1] + dy
            ok = (x <= hi[:, 0]) & (y <= hi[:, 1])
            ok &= (edge(a, b, x, y) >= 0) & (edge(b, c, x, y) >= 0) & (edge(c, a, x, y) >= 0)
            out[y[ok].long(), x[ok].long()] = idx[ok]
    return out
