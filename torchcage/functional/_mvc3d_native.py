"""Glue to the native CPU kernel of 3D mean value coordinates (``torchcage/_native/mvc3d.c``):
its tables in the layouts it expects, and the call on a chunk of points."""

from __future__ import annotations

import torch

from .. import _native
from ._mvc3d import CANCELLATION, FAR_FIELD, NEAR_PLANE, TriangleCageData


def unique_face_edges(tri: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Unique edges of triangles ``tri`` ``(T, 3)``: ``(edges (E, 2)`` sorted pairs,
    ``face_edge (T, 3)`` the index of the edge opposite each corner, ``sign (T, 3)`` +1 where that
    edge is stored as ``(t[i+1], t[i+2])``, else -1 (float64)``)``."""
    opp = torch.stack([tri.roll(-1, dims=1), tri.roll(-2, dims=1)], dim=-1)  # (T, 3, 2)
    lo, hi = opp.min(dim=-1).values, opp.max(dim=-1).values
    uniq, inv = torch.unique(torch.stack([lo, hi], dim=-1).reshape(-1, 2), dim=0, return_inverse=True)
    sign = torch.where(opp[..., 0] == lo, 1.0, -1.0).to(torch.float64)
    return uniq, inv.reshape(-1, 3), sign


def native_tables(data: TriangleCageData) -> dict[str, torch.Tensor]:
    """Tables for the native kernel, built once per cage: among them the unique edges and, for the
    edge opposite each corner, its index ``face_edge`` and orientation ``face_sign`` (+1 when
    stored as ``(t[i+1], t[i+2])``), and the vertex-to-corner incidence as CSR."""
    tri = data.tri
    V = data.vertices.shape[1]
    uniq, inv, sign = unique_face_edges(tri)
    sign = sign.to(data.vertices.dtype)
    # Vertex -> face corners (index c * T + f), as CSR, to gather the corner weights per vertex.
    corner_vertex = tri.T.reshape(-1)
    inc_idx = torch.argsort(corner_vertex, stable=True)
    inc_ptr = torch.zeros(V + 1, dtype=torch.long)
    inc_ptr[1:] = torch.cumsum(torch.bincount(corner_vertex, minlength=V), 0)
    # Structure-of-arrays layouts, as the native kernel expects (see tc_mvc3d in mvc3d.c).
    return {
        "P": data.vertices.contiguous(),
        "tri": tri.T.to(torch.int32).contiguous(),
        "edges": uniq.T.to(torch.int32).contiguous(),
        "face_edge": inv.T.to(torch.int32).contiguous(),
        "inc_ptr": inc_ptr.to(torch.int32),
        "inc_idx": inc_idx.to(torch.int32),
        "face_sign": sign.T.contiguous(),
        "normal": data.normal[:, :, 0].contiguous(),
        "two_area": data.two_area[:, 0].contiguous(),
        "ell": data.edge_len[:, :, 0].T.contiguous(),
        "gram": data.gram.contiguous(),
        "far_nodes": data.far_nodes.contiguous(),
        "far_coef": data.far_coef.contiguous(),
        "longest": data.longest[:, 0].contiguous(),
    }


def native_chunk(
    x: torch.Tensor,
    data: TriangleCageData,
    tables: dict[str, torch.Tensor],
    lib: object,
    W: torch.Tensor,
    normalize: bool = True,
) -> torch.Tensor:
    """The native CPU kernel on a chunk: ``x`` ``(n, 3)`` float64 -> coordinates (raw weights with
    ``normalize=False``) written into the contiguous ``W`` ``(n, V)``; returns the ``(n,)`` uint8
    on-cage flags (rows on the cage hold their interpolating values)."""
    x = x.contiguous()
    n, V = x.shape[0], data.vertices.shape[1]
    on = torch.empty((n,), dtype=torch.uint8)
    nat = tables
    args = [
        nat["P"], V, nat["tri"], data.tri.shape[0], nat["edges"], nat["edges"].shape[1], nat["face_edge"],
        nat["inc_ptr"], nat["inc_idx"],
        nat["face_sign"], nat["normal"], nat["two_area"], nat["ell"], nat["gram"], nat["far_nodes"],
        nat["far_coef"], nat["longest"], nat["far_nodes"].shape[1], FAR_FIELD, CANCELLATION, x, n, data.tol,
        NEAR_PLANE,
        torch.get_num_threads(), W, on, int(normalize),
    ]  # fmt: skip
    _native.call(lib.tc_mvc3d, args)  # type: ignore[attr-defined]
    return on
