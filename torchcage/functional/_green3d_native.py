"""Glue to the native CPU kernel of 3D Green coordinates (``torchcage/_native/gc3d.c``): its
tables in the layouts it expects, and the call on a chunk of points."""

from __future__ import annotations

import torch

from .. import _native
from ._green3d import TriangleGreenData, triangle_frame
from ._mvc3d_native import unique_face_edges


def native_tables(data: TriangleGreenData, vertices: torch.Tensor) -> dict[str, torch.Tensor]:
    """Tables for ``tc_gc3d`` (layouts in gc3d.c): among them the unique edges with their unit
    directions and, for each face, the edge opposite each corner."""
    edges, face_edge, _ = unique_face_edges(data.tri)
    edges = edges.T  # (2, E)
    direction = vertices[edges[1]] - vertices[edges[0]]
    return {
        "Pv": vertices.T.contiguous(),
        "tri": data.tri.T.to(torch.int32).contiguous(),
        "edges": edges.to(torch.int32).contiguous(),
        "eu": (direction / direction.norm(dim=1, keepdim=True)).T.contiguous(),
        "fe": face_edge.T.to(torch.int32).contiguous(),
        "nrm": data.normal.contiguous(),
        "two_area": data.two_area.contiguous(),
        "ell": (data.grad_bary.norm(dim=-1) * data.two_area[:, None]).contiguous(),
        "edir": data.edge_dir.contiguous(),
        "eout": data.edge_out.contiguous(),
        "gbary": data.grad_bary.contiguous(),
    }


def native_subset_tables(vertices: torch.Tensor, tri: torch.Tensor, tol: float) -> dict[str, torch.Tensor]:
    """:func:`native_tables` of triangles ``tri`` ``(T, 3)`` over ``vertices`` ``(V, 3)`` float64
    that need not close a cage (a triquad cage's triangles, the split triangles of its quads)."""
    p = vertices[tri]
    return native_tables(TriangleGreenData(p, *triangle_frame(p), tri, tol), vertices)


def native_chunk(
    x: torch.Tensor,
    tables: dict[str, torch.Tensor],
    lib: object,
    phi: torch.Tensor,
    psi: torch.Tensor,
    tol: float,
    on_face: torch.Tensor | None = None,
    alpha: torch.Tensor | None = None,
) -> None:
    """The native kernel on a chunk: ``x`` ``(n, 3)`` float64 into ``phi`` ``(n, V)`` and ``psi``
    ``(n, T)`` (contiguous float64 CPU tensors, written in place). With ``on_face`` ``(n,)`` int32
    and ``alpha`` ``(n, 3)`` float64 given, the triangles are part of a larger cage: ``phi`` keeps
    the principal values and those receive the first face each point lies on (-1: none) and the
    point's barycentric coordinates there, for the caller's jump term."""
    x = x.contiguous()
    t = tables
    args = [t["Pv"], phi.shape[1], t["tri"], psi.shape[1], t["edges"], t["edges"].shape[1], t["eu"], t["fe"],
            t["nrm"], t["two_area"], t["ell"], t["edir"], t["eout"], t["gbary"], x, x.shape[0], tol,
            torch.get_num_threads(), phi, psi, on_face, alpha]  # fmt: skip
    _native.call(lib.tc_gc3d, args)  # type: ignore[attr-defined]
