"""Glue to the native CPU kernel of 3D mean value coordinates (``torchcage/backends/native/mvc3d.c``):
its tables, keyed by ``tc_mvc3d``'s argument names (layouts in ``torchcage/backends/native/abi.py``), and
the call on a chunk of points."""

from __future__ import annotations

import ctypes

import torch

from torchcage._core.common import unique_face_edges
from torchcage.backends import native as _native
from torchcage.families.mean_value.kernel3d import (
    CANCELLATION_RATIO,
    FAR_FIELD_RATIO,
    SPLIT_FORM_RATIO,
    TriangleCageData,
)

__all__ = ["native_chunk", "native_tables"]


def native_tables(data: TriangleCageData) -> dict[str, object]:
    """``tc_mvc3d``'s per-cage arguments, built once: among them the unique edges and, for the
    edge opposite each corner, its index ``fe`` and orientation ``fs`` (+1 when stored as
    ``(t[i+1], t[i+2])``), and the vertex-to-corner incidence as CSR (``inc_ptr``, ``inc_idx``)."""
    tri = data.tri
    V, T = data.vertices.shape[1], tri.shape[0]
    uniq, inv, sign = unique_face_edges(tri)
    # Vertex -> face corners (index c * T + f), as CSR, to gather the corner weights per vertex.
    corner_vertex = tri.T.reshape(-1)
    inc_ptr = torch.zeros(V + 1, dtype=torch.long)
    inc_ptr[1:] = torch.cumsum(torch.bincount(corner_vertex, minlength=V), 0)
    return {
        "P": data.vertices.contiguous(),
        "V": V,
        "tri": tri.T.to(torch.int32).contiguous(),
        "T": T,
        "edges": uniq.T.to(torch.int32).contiguous(),
        "E": uniq.shape[0],
        "fe": inv.T.to(torch.int32).contiguous(),
        "inc_ptr": inc_ptr.to(torch.int32),
        "inc_idx": torch.argsort(corner_vertex, stable=True).to(torch.int32),
        "fs": sign.to(data.vertices.dtype).T.contiguous(),
        "nrm": data.normal[:, :, 0].contiguous(),
        "two_area": data.two_area[:, 0].contiguous(),
        "ell": data.edge_len[:, :, 0].T.contiguous(),
        "gram": data.gram.contiguous(),
        "far_nodes": data.far_nodes.contiguous(),
        "far_coef": data.far_coef.contiguous(),
        "longest": data.longest[:, 0].contiguous(),
        "Q": data.far_nodes.shape[1],
        "far_c": FAR_FIELD_RATIO,
        "cancel_c": CANCELLATION_RATIO,
        "near_c": SPLIT_FORM_RATIO,
        "tol": data.tol,
    }


def native_chunk(
    x: torch.Tensor, tables: dict[str, object], lib: ctypes.CDLL, W: torch.Tensor, normalize: bool = True
) -> torch.Tensor:
    """The native kernel on a chunk: ``x`` ``(n, 3)`` float64 -> coordinates (raw weights with
    ``normalize=False``) written into the contiguous ``W`` ``(n, V)``; returns the ``(n,)`` uint8
    on-cage flags (rows on the cage hold their interpolating values)."""
    on = torch.empty((x.shape[0],), dtype=torch.uint8)
    _native.call(lib, "tc_mvc3d", **tables, X=x.contiguous(), n=x.shape[0], W=W, on=on, normalize=int(normalize))
    return on
