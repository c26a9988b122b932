"""Glue to the native CPU kernels of mean value coordinates with their analytic derivatives
(``torchcage/backends/native/mvcd3d.c``, ``mvcd2d.c``): their tables, keyed by the C argument names
(layouts in ``torchcage/backends/native/abi.py``), and the call on a chunk of points."""

from __future__ import annotations

import ctypes
import functools

import numpy as np
import torch

from torchcage._core.common import collapsed_gauss, on_cage_tolerance, unique_face_edges
from torchcage.backends import native as _native
from torchcage.cage import Cage
from torchcage.errors import CageError
from torchcage.families.mean_value import native2d

__all__ = ["DERIVATIVE_FAR_FIELD_ORDER", "DERIVATIVE_FAR_FIELD_RATIO", "DERIVATIVE_SPLIT_FORM_RATIO", "G_ORDER",
           "batch_tables", "face_tables", "native_chunk", "native_tables", "polygon_tables"]  # fmt: skip

#: Faces whose longest edge is below ``DERIVATIVE_FAR_FIELD_RATIO`` times their distance use the
#: far-field rule (measured against 60-digit references: the direct form's Hessians lose up to
#: 4e-10 relative at 0.125, nothing visible at 0.25).
DERIVATIVE_FAR_FIELD_RATIO = 0.25
#: Gauss–Legendre order per direction of the far-field rule (error about ``(ratio/4)^(2 order)``).
DERIVATIVE_FAR_FIELD_ORDER = 6
#: Pairs with ``|h| < DERIVATIVE_SPLIT_FORM_RATIO * min |a_i|`` use the split form (the direct
#: form's Hessians lose 1e-10 relative at 0.01, 1e-12 at 0.05, nothing visible at 0.2).
DERIVATIVE_SPLIT_FORM_RATIO = 0.05
#: Gauss–Legendre nodes of ``G(t) = int_0^1 dy / (1 + t y^2)``, ``t <= 1``.
G_ORDER = 16


def _gauss01(order: int) -> tuple[torch.Tensor, torch.Tensor]:
    y, w = _leggauss(order)
    return torch.tensor((y + 1) / 2), torch.tensor(w / 2)


@functools.lru_cache(maxsize=8)
def _leggauss(order: int):
    """Gauss–Legendre nodes and weights on ``[-1, 1]``, computed once per order (read only)."""
    return np.polynomial.legendre.leggauss(order)


def native_tables(cage: Cage) -> dict[str, object]:
    """``tc_mvcd3d``'s or ``tc_mvcd2d``'s arguments for one cage, float64 on the CPU: a batch of
    one (:func:`batch_tables`, :func:`polygon_tables`).

    Raises:
        CageError: a 3D cage with quads.
    """
    P = cage.vertices.detach().to("cpu", torch.float64).contiguous()
    tol = on_cage_tolerance(cage)
    if cage.dim == 2:
        return polygon_tables(P[None], cage.edges, torch.tensor([tol], dtype=torch.float64))
    if cage.has_quads:  # (as triangle_geometry refuses them)
        raise CageError(
            f"this needs a triangle cage, but the cage has {cage.quads.shape[0]} quads; use "
            "quad_mean_value_coordinates for quad/triquad cages, or cage.triangulated()"
        )
    return batch_tables(P[None], cage.triangles.cpu(), torch.tensor([tol], dtype=torch.float64))


def batch_tables(vertices: torch.Tensor, tri: torch.Tensor, tol: torch.Tensor) -> dict[str, object]:
    """``tc_mvcd3d``'s arguments for a batch of triangle cages with one topology: the geometric
    tables of the ``B`` cages by one set of tensor operations, with a leading batch axis
    (:func:`face_tables`), and the faces' edge ids.

    Args:
        vertices: ``(B, V, 3)`` float64 CPU vertices.
        tri: ``(T, 3)`` the shared triangles.
        tol: ``(B,)`` float64 absolute on-cage tolerances.
    """
    tables = face_tables(vertices, tri, tol)
    edges, face_edge, _ = unique_face_edges(tri)
    tables["fe"], tables["NE"] = face_edge.to(torch.int32).contiguous(), edges.shape[0]
    return tables


def face_tables(vertices: torch.Tensor, tri: torch.Tensor, tol: torch.Tensor) -> dict[str, object]:
    """:func:`batch_tables` but the edge ids (the native kernel's only), on the vertices' device:
    what the Triton kernel takes too.

    Args:
        vertices: ``(B, V, 3)`` float64 vertices.
        tri: ``(T, 3)`` the shared triangles (on the vertices' device).
        tol: ``(B,)`` float64 absolute on-cage tolerances.
    """
    dev = vertices.device
    p = vertices[:, tri]  # (B, T, 3, 3)
    cross = torch.linalg.cross(p[:, :, 1] - p[:, :, 0], p[:, :, 2] - p[:, :, 0], dim=-1)
    two_area = cross.norm(dim=-1)
    normal = cross / two_area[..., None]
    E = p.roll(-1, dims=2) - p.roll(-2, dims=2)  # (B, T, 3, 3): E_e = p_{e+1} - p_{e+2}
    ell = E.norm(dim=-1)
    bary, qw = collapsed_gauss(DERIVATIVE_FAR_FIELD_ORDER, torch.float64, dev)
    gy, gw = (t.to(dev) for t in _gauss01(G_ORDER))
    far_nodes = torch.einsum("qi,btic->btqc", bary, p).contiguous()
    return {
        "B": vertices.shape[0],
        "P": vertices.contiguous(),
        "V": vertices.shape[1],
        "tri": tri.to(torch.int32).contiguous(),
        "T": tri.shape[0],
        "E": E.contiguous(),
        "nrm": normal.contiguous(),
        "two_area": two_area.contiguous(),
        "ell": ell.contiguous(),
        "gram": (E @ E.transpose(-1, -2)).contiguous(),
        "longest": ell.amax(dim=-1).contiguous(),
        "far_nodes": far_nodes,
        "far_coef": ((two_area[..., None, None] * qw[:, None]) * bary).contiguous(),
        "Q": far_nodes.shape[2],
        "far_c": DERIVATIVE_FAR_FIELD_RATIO,
        "near_c": DERIVATIVE_SPLIT_FORM_RATIO,
        "gl_y": gy.contiguous(),
        "gl_w": gw.contiguous(),
        "ng": G_ORDER,
        "tol": tol.to(dev, torch.float64).contiguous(),
    }


def polygon_tables(vertices: torch.Tensor, edges: torch.Tensor, tol: torch.Tensor) -> dict[str, object]:
    """``tc_mvcd2d``'s arguments for a batch of polygons with one topology.

    Args:
        vertices: ``(B, V, 2)`` vertices (cast to float64 on the CPU).
        edges: ``(E, 2)`` the shared directed edges.
        tol: ``(B,)`` absolute on-polygon tolerances.

    Examples:
        >>> square = torch.tensor([[[0.0, 0], [1, 0], [1, 1], [0, 1]]] * 2, dtype=torch.float64)
        >>> t = polygon_tables(square, torch.tensor([[0, 1], [1, 2], [2, 3], [3, 0]]), torch.full((2,), 1e-12))
        >>> t["B"], t["V"], t["NE"]
        (2, 4, 4)
    """
    tables = native2d.batch_tables(vertices, edges, tol)  # (the same arguments as tc_mvc2d's ...)
    tables["NE"] = tables.pop("E")  # (... but for the edge count's name)
    return tables


def native_chunk(
    x: torch.Tensor,
    tables: dict[str, object],
    lib: ctypes.CDLL,
    order: int,
    lam: torch.Tensor,
    grad: torch.Tensor,
    hess: torch.Tensor | None,
    on: torch.Tensor,
) -> None:
    """The kernel on a chunk into the contiguous outputs, for a batch of ``B`` cages of dimension
    ``D`` (:func:`batch_tables`, :func:`polygon_tables`; one cage is a batch of one): ``x`` ``(B or
    1, n, D)``, ``lam (B, n, V)``, ``grad (B, n, V, D)``, ``hess (B, n, V, D, D)`` (``None`` for
    ``order=1``), uint8 flags ``on (B, n)``: 1 on the cage, 2 where the total weight vanishes.

    Raises:
        ValueError: points for neither one nor ``B`` cages.
        MemoryError: the kernel could not allocate its per-thread scratch.
    """
    X = x.contiguous()
    B = int(tables["B"])  # type: ignore[call-overload]
    name = "tc_mvcd2d" if X.shape[-1] == 2 else "tc_mvcd3d"
    if X.shape[0] not in (1, B):
        raise ValueError(f"{name}: points for {X.shape[0]} cages, but the tables hold {B}: give 1 (shared) or {B}")
    _native.call(lib, name, **tables, X=X, XB=X.shape[0], n=X.shape[1], order=order, L=lam, G=grad, H=hess, on=on)
    _native.check_workspace_flags(on, "mean value derivatives")
