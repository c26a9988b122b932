"""Glue to the native CPU kernel of 3D Green coordinates (``torchcage/backends/native/gc3d.c``): its
tables, keyed by ``tc_gc3d``'s argument names (layouts in ``torchcage/backends/native/abi.py``), and the
call on a chunk of points."""

from __future__ import annotations

import ctypes

import torch

from torchcage._core.common import unique_face_edges
from torchcage.backends import native as _native
from torchcage.families.green.far_triangle import FAR_RATIO
from torchcage.families.green.kernel3d import TriangleGreenData, batch_face_tables, triangle_green_geometry

__all__ = [
    "batch_chunk",
    "batch_subset_tables",
    "batch_tables",
    "native_chunk",
    "native_tables",
]


def native_tables(data: TriangleGreenData, vertices: torch.Tensor) -> dict[str, object]:
    """``tc_gc3d``'s per-cage arguments: among them the unique edges with their unit directions,
    for each face the edge opposite each corner, and the far-field rule (none, ``Q = 0``, where
    ``data`` has none)."""
    edges, face_edge, _ = unique_face_edges(data.tri)
    T = data.tri.shape[0]
    if data.far_nodes is not None and data.longest is not None:
        far = (data.longest, data.far_nodes, data.far_weights, data.far_bary)
    else:
        far = (data.two_area, data.p.new_zeros(T, 0, 3), data.p.new_zeros(T, 0), data.p.new_zeros(0, 3))
    edges = edges.T  # (2, E)
    direction = vertices[edges[1]] - vertices[edges[0]]
    return {
        "Pv": vertices.T.contiguous(),
        "V": vertices.shape[0],
        "tri": data.tri.T.to(torch.int32).contiguous(),
        "T": data.tri.shape[0],
        "edges": edges.to(torch.int32).contiguous(),
        "E": edges.shape[1],
        "eu": (direction / direction.norm(dim=1, keepdim=True)).T.contiguous(),
        "fe": face_edge.T.to(torch.int32).contiguous(),
        "nrm": data.normal.contiguous(),
        "two_area": data.two_area.contiguous(),
        "ell": (data.grad_bary.norm(dim=-1) * data.two_area[:, None]).contiguous(),
        "edir": data.edge_dir.contiguous(),
        "eout": data.edge_out.contiguous(),
        "gbary": data.grad_bary.contiguous(),
        "longest": far[0].contiguous(),
        "far_nodes": far[1].contiguous(),
        "far_w": far[2].contiguous(),
        "far_bary": far[3].contiguous(),
        "Q": far[3].shape[0],
        "far_c": FAR_RATIO,
        "tol": data.tol,
    }


def native_chunk(
    x: torch.Tensor,
    tables: dict[str, object],
    lib: ctypes.CDLL,
    phi: torch.Tensor,
    psi: torch.Tensor,
    on_face: torch.Tensor | None = None,
    alpha: torch.Tensor | None = None,
) -> None:
    """The native kernel on a chunk: ``x`` ``(n, 3)`` float64 into ``phi`` ``(n, V)`` and ``psi``
    ``(n, T)`` (contiguous float64 CPU tensors, written in place). With ``on_face`` ``(n,)`` int32
    and ``alpha`` ``(n, 3)`` float64 given, the triangles are part of a larger cage: ``phi`` keeps
    the principal values and those receive the first face each point lies on (-1: none) and the
    point's barycentric coordinates there, for the caller's jump term."""
    _native.call(lib, "tc_gc3d", **tables, X=x.contiguous(), n=x.shape[0], PHI=phi, PSI=psi, ONF=on_face, AL=alpha)
    mb = 8 * 8 * (5 * phi.shape[1] + 4 * psi.shape[1]) / 2**20
    _native.check_workspace(phi, "Green", f"about {mb:.0f} MB per thread")


def batch_tables(vertices: torch.Tensor, tri: torch.Tensor, tol: torch.Tensor) -> dict[str, object]:
    """``tc_gc3d_batch``'s per-cage arguments for a batch of cages with one topology: ``vertices``
    ``(B, V, 3)`` float64 (centred), ``tri`` ``(T, 3)``, ``tol`` ``(B,)`` the on-cage tolerances.
    Element by element the tables :func:`native_tables` builds for one cage (the same operations,
    over a leading batch axis)."""
    return _batch_arguments(vertices, tri, tol, *batch_face_tables(vertices, tri))


def batch_subset_tables(vertices: torch.Tensor, tri: torch.Tensor, tol: torch.Tensor) -> dict[str, object]:
    """``tc_gc3d_batch``'s arguments, without the far-field rule (``Q = 0``), for triangles ``tri``
    ``(T, 3)`` that need not close a cage (a triquad cage's triangles, the split triangles of its
    quads) over a batch of cages ``vertices`` ``(B, V, 3)`` float64 with tolerances ``tol`` ``(B,)``:
    :func:`native_tables` of each element's ``TriangleGreenData`` without a far-field rule, by one
    set of tensor operations."""
    p = vertices[:, tri]  # (B, T, 3, 3)
    geometry = triangle_green_geometry(p)
    B, T, two_area = vertices.shape[0], tri.shape[0], geometry[1]
    none = (vertices.new_zeros(B, T, 0, 3), vertices.new_zeros(B, T, 0), vertices.new_zeros(0, 3))
    return _batch_arguments(vertices, tri, tol, geometry, two_area, none)  # (longest: unread without a rule)


def _batch_arguments(
    vertices: torch.Tensor,
    tri: torch.Tensor,
    tol: torch.Tensor,
    geometry: tuple[torch.Tensor, ...],
    longest: torch.Tensor,
    far: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
) -> dict[str, object]:
    """``tc_gc3d_batch``'s arguments from the faces' ``geometry`` ``(normal, two_area, edge_dir,
    edge_out, grad_bary)`` (each ``(B, T, ...)``), ``longest`` ``(B, T)`` and the far-field rule
    ``far`` ``(nodes (B, T, Q, 3), weights (B, T, Q), bary (Q, 3))``."""
    normal, two_area, edge_dir, edge_out, grad_bary = geometry
    nodes, weights, bary = far
    edges, face_edge, _ = unique_face_edges(tri)
    edges = edges.T  # (2, E)
    direction = vertices[:, edges[1]] - vertices[:, edges[0]]  # (B, E, 3)
    return {
        "B": vertices.shape[0],
        "Pv": vertices.transpose(1, 2).contiguous(),
        "V": vertices.shape[1],
        "tri": tri.T.to(torch.int32).contiguous(),
        "T": tri.shape[0],
        "edges": edges.to(torch.int32).contiguous(),
        "E": edges.shape[1],
        "eu": (direction / direction.norm(dim=-1, keepdim=True)).transpose(1, 2).contiguous(),
        "fe": face_edge.T.to(torch.int32).contiguous(),
        "nrm": normal.contiguous(),
        "two_area": two_area.contiguous(),
        "ell": (grad_bary.norm(dim=-1) * two_area[..., None]).contiguous(),
        "edir": edge_dir.contiguous(),
        "eout": edge_out.contiguous(),
        "gbary": grad_bary.contiguous(),
        "longest": longest.contiguous(),
        "far_nodes": nodes.contiguous(),
        "far_w": weights.contiguous(),
        "far_bary": bary.contiguous(),
        "Q": bary.shape[0],
        "far_c": FAR_RATIO,
        "tol": tol.to(torch.float64).contiguous(),
    }


def batch_chunk(
    x: torch.Tensor,
    tables: dict[str, object],
    lib: ctypes.CDLL,
    phi: torch.Tensor,
    psi: torch.Tensor,
    on_face: torch.Tensor | None = None,
    alpha: torch.Tensor | None = None,
) -> None:
    """The native kernel on a chunk of every cage's points: ``x`` ``(B, n, 3)`` float64 into ``phi``
    ``(B, n, V)`` and ``psi`` ``(B, n, T)`` (contiguous float64 CPU tensors, written in place). With
    ``on_face`` ``(B, n)`` int32 and ``alpha`` ``(B, n, 3)`` given, the triangles are part of larger
    cages, as in :func:`native_chunk`."""
    _native.call(
        lib, "tc_gc3d_batch", **tables, X=x.contiguous(), n=x.shape[1], PHI=phi, PSI=psi, ONF=on_face, AL=alpha
    )
    mb = 8 * 8 * (5 * phi.shape[-1] + 4 * psi.shape[-1]) / 2**20
    _native.check_workspace(phi, "Green", f"about {mb:.0f} MB per thread")
