"""Glue to the native CPU kernel of 3D mean value coordinates (``torchcage/backends/native/mvc3d.c``):
its tables, keyed by ``tc_mvc3d``'s argument names (layouts in ``torchcage/backends/native/abi.py``),
and the call on a chunk of points. The kernel takes a batch of cages with one topology: the topology
tables are shared, the geometric ones carry a leading batch axis (one cage: a batch of one)."""

from __future__ import annotations

import ctypes

import torch

from torchcage._core.common import collapsed_gauss, unique_face_edges
from torchcage.backends import native as _native
from torchcage.families.mean_value.kernel3d import (
    CANCELLATION_RATIO,
    FAR_FIELD_ORDER,
    FAR_FIELD_RATIO,
    SPLIT_FORM_RATIO,
    TriangleCageData,
    face_constants,
)

__all__ = ["batch_tables", "native_chunk", "native_tables", "topology_tables"]


def topology_tables(tri: torch.Tensor, V: int) -> dict[str, object]:
    """``tc_mvc3d``'s topology arguments of triangles ``tri`` ``(T, 3)`` over ``V`` vertices, shared
    by every cage of a batch: the corners, the unique edges and, for the edge opposite each corner,
    its index ``fe`` and orientation ``fs`` (+1 when stored as ``(t[i+1], t[i+2])``), and the
    vertex-to-corner incidence as CSR (``inc_ptr``, ``inc_idx``); the scalar constants too.

    The tensors are cached by the triangles' content (a training loop builds a new cage with the
    same faces each step): the kernel only reads them; the dictionary is new at every call."""
    tri = tri.detach().cpu().contiguous()
    key = (V, tuple(tri.shape), tri.numpy().tobytes())
    cached = _TOPOLOGY.get(key)
    if cached is None:
        cached = _topology_tables(tri, V)
        if len(_TOPOLOGY) >= 8:
            _TOPOLOGY.pop(next(iter(_TOPOLOGY)))  # (the oldest first: dicts keep insertion order)
        _TOPOLOGY[key] = cached
    return dict(cached)


_TOPOLOGY: dict[tuple[int, tuple[int, ...], bytes], dict[str, object]] = {}


def _topology_tables(tri: torch.Tensor, V: int) -> dict[str, object]:
    T = tri.shape[0]
    uniq, inv, sign = unique_face_edges(tri)
    # Vertex -> face corners (index c * T + f), as CSR, to gather the corner weights per vertex.
    corner_vertex = tri.T.reshape(-1)
    inc_ptr = torch.zeros(V + 1, dtype=torch.long)
    inc_ptr[1:] = torch.cumsum(torch.bincount(corner_vertex, minlength=V), 0)
    return {
        "V": V,
        "tri": tri.T.to(torch.int32).contiguous(),
        "T": T,
        "edges": uniq.T.to(torch.int32).contiguous(),
        "E": uniq.shape[0],
        "fe": inv.T.to(torch.int32).contiguous(),
        "inc_ptr": inc_ptr.to(torch.int32),
        "inc_idx": torch.argsort(corner_vertex, stable=True).to(torch.int32),
        "fs": sign.T.contiguous(),
        "far_c": FAR_FIELD_RATIO,
        "cancel_c": CANCELLATION_RATIO,
        "near_c": SPLIT_FORM_RATIO,
    }


def _far_rule() -> dict[str, object]:
    """The far-field rule on the unit triangle (``collapsed_gauss``: ``far_bary`` ``(Q, 3)``,
    ``far_qw`` ``(Q,)``), shared by every face and cage: the kernel places the nodes on each face
    itself (the torch kernel's ``far_nodes``, ``far_coef``)."""
    bary, qw = collapsed_gauss(FAR_FIELD_ORDER, torch.float64, torch.device("cpu"))
    return {"far_bary": bary.contiguous(), "far_qw": qw.contiguous(), "Q": bary.shape[0]}


def native_tables(data: TriangleCageData) -> dict[str, object]:
    """``tc_mvc3d``'s arguments for one cage (a batch of one), built once from its constants."""
    tables = topology_tables(data.tri, data.vertices.shape[1])
    tables.update(
        {
            "B": 1,
            "P": data.vertices.contiguous()[None],
            "nrm": data.normal[:, :, 0].contiguous()[None],
            "two_area": data.two_area[:, 0].contiguous()[None],
            "ell": data.edge_len[:, :, 0].T.contiguous()[None],
            "gram": data.gram.contiguous()[None],
            **_far_rule(),
            "longest": data.longest[:, 0].contiguous()[None],
            "tol": torch.tensor([data.tol], dtype=torch.float64),
        }
    )
    return tables


def batch_tables(vertices: torch.Tensor, tri: torch.Tensor, tol: torch.Tensor) -> dict[str, object]:
    """``tc_mvc3d``'s arguments for a batch of cages with one topology, every geometric table of
    the ``B`` cages computed by one set of tensor operations (element by element the numbers of
    :func:`native_tables` on ``triangle_data`` of that cage).

    Args:
        vertices: ``(B, V, 3)`` float64 CPU vertices.
        tri: ``(T, 3)`` the shared triangles.
        tol: ``(B,)`` float64 absolute on-cage tolerances.
    """
    B, V = vertices.shape[0], vertices.shape[1]
    c = face_constants(vertices[:, tri], far=False)
    tables = topology_tables(tri, V)
    tables.update(
        {
            "B": B,
            "P": vertices.transpose(1, 2).contiguous(),
            "nrm": c["normal"].transpose(1, 2).contiguous(),
            "two_area": c["two_area"].contiguous(),
            "ell": c["edge_len"].contiguous(),
            "gram": c["gram"].contiguous(),
            **_far_rule(),
            "longest": c["longest"].contiguous(),
            "tol": tol.to(torch.float64).contiguous(),
        }
    )
    return tables


def native_chunk(
    x: torch.Tensor, tables: dict[str, object], lib: ctypes.CDLL, W: torch.Tensor, normalize: bool = True
) -> torch.Tensor:
    """The native kernel on a chunk of float64 points, coordinates (raw weights with
    ``normalize=False``) written into the contiguous ``W``; returns the uint8 flags: 1 on the cage
    (rows hold their interpolating values), with ``normalize`` 2 where the row is not finite (the
    total weight vanishes), else 0.

    One cage (``tables["B"] == 1``): ``x`` ``(n, 3)``, ``W`` ``(n, V)``, flags ``(n,)``. A batch of
    ``B`` cages: ``x`` ``(B, n, 3)``, or ``(1, n, 3)`` shared by every cage, ``W`` ``(B, n, V)``,
    flags ``(B, n)``.

    Raises:
        ValueError: points whose batch is neither 1 nor the cages' (or a wrong shape: ``_native.call``).
        MemoryError: the kernel could not allocate its per-thread scratch.
    """
    batched = x.dim() == 3
    X = x.contiguous() if batched else x.contiguous()[None]
    Wb = W if batched else W[None]
    B, XB, n = int(tables["B"]), X.shape[0], X.shape[1]  # type: ignore[call-overload]
    if XB not in (1, B):
        raise ValueError(f"tc_mvc3d: points for {XB} cages, but the tables hold {B}: give 1 (shared) or {B}")
    on = torch.empty((B, n), dtype=torch.uint8)
    _native.call(lib, "tc_mvc3d", **tables, X=X, XB=XB, n=n, W=Wb, on=on, normalize=int(normalize))
    _native.check_workspace_flags(on, "mean value")
    return on if batched else on[0]
