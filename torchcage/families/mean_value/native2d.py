"""Glue to the native CPU kernel of 2D mean value coordinates (``torchcage/backends/native/mvc2d.c``)."""

from __future__ import annotations

import ctypes

import torch

from torchcage._core.common import on_cage_tolerance
from torchcage.backends import native as _native
from torchcage.cage import Cage

__all__ = ["native_chunk", "native_tables"]


def native_tables(cage: Cage) -> dict[str, object]:
    """``tc_mvc2d``'s per-cage arguments (float64 vertices ``P`` ``(V, 2)``, int32 ``edges``)."""
    edges = cage.edges.to(torch.int32).contiguous()
    P = cage.vertices.detach().to(torch.float64).contiguous()
    return {"P": P, "V": P.shape[0], "edges": edges, "E": edges.shape[0], "tol": on_cage_tolerance(cage)}


def native_chunk(x: torch.Tensor, tables: dict[str, object], lib: ctypes.CDLL, W: torch.Tensor) -> torch.Tensor:
    """The native kernel on a chunk ``x`` ``(n, 2)`` float64, into the contiguous ``W`` ``(n, V)``;
    returns the ``(n,)`` uint8 on-polygon flags."""
    on = torch.empty((x.shape[0],), dtype=torch.uint8)
    _native.call(lib, "tc_mvc2d", **tables, X=x.contiguous(), n=x.shape[0], W=W, on=on)
    return on
