"""Glue to the native CPU kernel of quad mean value coordinates (``torchcage/backends/native/qmvc3d.c``,
with ``tc_mvc3d`` for a triquad cage's triangles): the kernel on a chunk of points."""

from __future__ import annotations

import ctypes
from collections.abc import Callable

import torch

from torchcage._core.quad_quadrature import gauss_table
from torchcage.backends import native as _native
from torchcage.families.mean_value import native3d as _mvc3d_native
from torchcage.families.mean_value.kernel3d import PART_FAR_FIELD_RATIO, TriangleCageData
from torchcage.families.quad_mean_value.kernel import QuadData

__all__ = ["native_kernel", "native_tables"]


def native_tables(verts: torch.Tensor, qdata: QuadData, n: int, tol: float | None = None) -> dict[str, object]:
    """``tc_qmvc3d``'s per-cage arguments (``n``: the Riemann sum's grid parameter; ``tol``: the
    quadrature's relative tolerance, or ``None`` for the Riemann sum)."""
    P = verts.contiguous()
    quads = qdata.quads.to(torch.int32).contiguous()
    return {
        "P": P,
        "V": P.shape[0],
        "quads": quads,
        "Q": quads.shape[0],
        "size": qdata.size[:, 0].contiguous(),
        "tol": qdata.tol,
        "n": n,
        "qtol": 0.0 if tol is None else tol,
        "gl": gauss_table(),
    }


def native_kernel(
    lib: ctypes.CDLL,
    verts: torch.Tensor,
    tdata: TriangleCageData | None,
    qdata: QuadData | None,
    n: int,
    tol: float | None = None,
) -> Callable[[torch.Tensor], torch.Tensor]:
    """The native kernels (triangles: ``tc_mvc3d``, raw weights; quads: ``tc_qmvc3d``) as a chunk
    function ``x (m, 3) -> coordinates (m, V)``."""
    V = verts.shape[0]
    tri_tables = _mvc3d_native.native_tables(tdata) if tdata is not None else None
    quad_tables = native_tables(verts, qdata, n, tol) if qdata is not None else None
    if tri_tables is not None and quad_tables is not None:
        # The triangles are part of the cage: their own sum does not show the far field's
        # cancellation, so faces seen small always take the far-field rule.
        tri_tables["cancel_c"] = 0.0
        tri_tables["far_c"] = PART_FAR_FIELD_RATIO

    def kernel(x: torch.Tensor) -> torch.Tensor:
        x = x.contiguous()
        m = x.shape[0]
        out = torch.zeros((m, V), dtype=x.dtype)
        if tri_tables is not None:
            on = _mvc3d_native.native_chunk(x, tri_tables, lib, out, normalize=quad_tables is None)
        else:
            on = torch.zeros(m, dtype=torch.uint8)
        if quad_tables is not None:
            _native.call(lib, "tc_qmvc3d", **quad_tables, X=x, npts=m, W=out, on=on)
            _native.check_workspace(out, "quad mean value")
        return out

    return kernel
