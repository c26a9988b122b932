"""Glue to the native CPU kernel of 2D mean value coordinates (``torchcage/backends/native/mvc2d.c``):
its tables for a batch of polygons with one topology, and the call on a chunk of points."""

from __future__ import annotations

import ctypes

import torch

from torchcage.backends import native as _native

__all__ = ["batch_tables", "native_chunk"]


def batch_tables(vertices: torch.Tensor, edges: torch.Tensor, tol: torch.Tensor) -> dict[str, object]:
    """``tc_mvc2d``'s per-polygon arguments for a batch of ``B`` polygons with one topology.

    Args:
        vertices: ``(B, V, 2)`` vertices (cast to float64 on the CPU).
        edges: ``(E, 2)`` the shared directed edges.
        tol: ``(B,)`` absolute on-polygon tolerances.

    Examples:
        >>> square = torch.tensor([[[0.0, 0], [1, 0], [1, 1], [0, 1]]], dtype=torch.float64)
        >>> t = batch_tables(square, torch.tensor([[0, 1], [1, 2], [2, 3], [3, 0]]), torch.tensor([1e-12]))
        >>> t["B"], t["V"], t["E"]
        (1, 4, 4)
    """
    P = vertices.detach().to("cpu", torch.float64).contiguous()
    e = edges.to("cpu", torch.int32).contiguous()
    tol = tol.to("cpu", torch.float64).contiguous()
    return {"B": P.shape[0], "P": P, "V": P.shape[1], "edges": e, "E": e.shape[0], "tol": tol}


def native_chunk(x: torch.Tensor, tables: dict[str, object], lib: ctypes.CDLL, W: torch.Tensor) -> torch.Tensor:
    """The native kernel on a chunk of float64 points, coordinates written into the contiguous
    ``W``; returns the uint8 flags: 1 on the polygon (rows hold the interpolant along the edge), 2
    where a coordinate is not finite (the total weight vanishes: only outside), else 0.

    One polygon (``tables["B"] == 1``): ``x`` ``(n, 2)``, ``W`` ``(n, V)``, flags ``(n,)``. A batch
    of ``B`` polygons (:func:`batch_tables`): ``x`` ``(B, n, 2)``, or ``(1, n, 2)`` shared by every
    polygon, ``W`` ``(B, n, V)``, flags ``(B, n)``.

    Raises:
        ValueError: points whose batch is neither 1 nor the polygons' (or a wrong shape: ``_native.call``).
    """
    batched = x.dim() == 3
    X = x.contiguous() if batched else x.contiguous()[None]
    Wb = W if batched else W[None]
    B, XB, n = int(tables["B"]), X.shape[0], X.shape[1]  # type: ignore[call-overload]
    if XB not in (1, B):
        raise ValueError(f"tc_mvc2d: points for {XB} polygons, but the tables hold {B}: give 1 (shared) or {B}")
    on = torch.empty((B, n), dtype=torch.uint8)
    _native.call(lib, "tc_mvc2d", **tables, X=X, XB=XB, n=n, W=Wb, on=on)
    return on if batched else on[0]
