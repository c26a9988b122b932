"""Glue to the native CPU kernel of quad Green coordinates (``torchcage/backends/native/qgc3d.c``, with
``tc_gc3d`` for a triquad cage's triangles): each part's share of a chunk of points."""

from __future__ import annotations

import ctypes

import torch

from torchcage._core.quad_quadrature import gauss_table
from torchcage.backends import native as _native
from torchcage.families.green.native3d import native_chunk, native_subset_tables
from torchcage.families.quad_green.kernel import QuadGreenData

__all__ = ["native_quad_part", "native_quad_tables", "native_tri_part"]


def native_quad_tables(verts: torch.Tensor, qdata: QuadGreenData, tol: float | None = None) -> dict[str, object]:
    """``tc_qgc3d``'s per-cage arguments: the quads' constants and, prefixed ``s_``, the Green
    kernel tables of the triangles ``(q0 q1 q2)``, ``(q0 q2 q3)`` of every quad (rows ``2q``,
    ``2q + 1``): outside a quad's tetrahedron they give its invariants (see qgc3d.c). ``tol``: the
    quadrature's relative tolerance, or ``None`` for the Riemann sum."""
    quads = qdata.quads
    split = torch.stack([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]], dim=1).reshape(-1, 3)
    s = native_subset_tables(verts, split, qdata.tol)
    P = verts.contiguous()
    return {
        "P": P,
        "V": P.shape[0],
        "quads": quads.to(torch.int32).contiguous(),
        "Q": quads.shape[0],
        "size": qdata.proj.size[:, 0].contiguous(),
        "pinv": qdata.pinv.contiguous(),
        "null": qdata.null.contiguous(),
        "origin": qdata.origin.contiguous(),
        "pattern": qdata.pattern.to(torch.int32).contiguous(),
        "Pn": qdata.pattern.shape[0],
        "K": qdata.K,
        "tol": qdata.tol,
        "qtol": 0.0 if tol is None else tol,
        "gl": gauss_table(),
        **{
            f"s_{k}": s[k]
            for k in ("Pv", "tri", "edges", "eu", "fe", "nrm", "two_area", "ell", "edir", "eout", "gbary")
        },
        "s_E": s["E"],
    }


def native_quad_part(
    x: torch.Tensor, qdata: QuadGreenData, tables: dict[str, object], lib: ctypes.CDLL
) -> tuple[torch.Tensor, ...]:  # fmt: skip
    """The quads' ``phi`` ``(m, V)`` and ``psi`` ``(m, 4Q)``, the first quad each point lies on (or
    -1) and the interpolating values ``(m, V)`` there, for a chunk ``x`` ``(m, 3)`` float64."""
    x = x.contiguous()
    m, V, Q = x.shape[0], int(tables["V"]), int(tables["Q"])  # type: ignore[call-overload]
    phi = torch.zeros(m, V, dtype=x.dtype)
    psi = torch.empty(m, 4 * Q, dtype=x.dtype)
    onq = torch.empty(m, dtype=torch.int32)
    uv = torch.zeros(m, 2, dtype=x.dtype)
    _native.call(lib, "tc_qgc3d", **tables, X=x, n=m, PHI=phi, PSIQ=psi, ONQ=onq, UV=uv)
    _native.check_workspace(phi, "quad Green")
    onq = onq.long()
    u, v = uv[:, 0:1], uv[:, 1:2]
    b = torch.cat([(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v], dim=1)
    hat = torch.zeros(m, V, dtype=x.dtype).scatter_add(1, qdata.quads[onq.clamp_min(0)], b)
    return phi, psi, onq, hat


def native_tri_part(
    x: torch.Tensor, tables: dict[str, object], triangles: torch.Tensor, lib: ctypes.CDLL
) -> tuple[torch.Tensor, ...]:  # fmt: skip
    """The triangles' ``phi`` ``(m, V)`` (principal values on the cage) and ``psi`` ``(m, T)``,
    whether each point lies on a triangle, and its hat values ``(m, V)`` there (``tables``:
    :func:`native_subset_tables` of the cage's triangles)."""
    m, V = x.shape[0], int(tables["V"])  # type: ignore[call-overload]
    phi = torch.empty(m, V, dtype=x.dtype)
    psi = torch.empty(m, triangles.shape[0], dtype=x.dtype)
    onf = torch.empty(m, dtype=torch.int32)
    alpha = torch.empty(m, 3, dtype=x.dtype)
    native_chunk(x, tables, lib, phi, psi, onf, alpha)
    onf = onf.long()
    hat = torch.zeros(m, V, dtype=x.dtype).scatter_add(1, triangles[onf.clamp_min(0)], alpha)
    return phi, psi, onf >= 0, hat
