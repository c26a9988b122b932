"""Glue to the native CPU kernel of the derivatives of 3D Green coordinates
(``torchcage/backends/native/gcd3d.c``): the values' tables (:mod:`.native3d`) and the call."""

from __future__ import annotations

import ctypes

import torch

from torchcage.backends import native as _native
from torchcage.families.green.kernel3d import TriangleGreenData
from torchcage.families.green.native3d import native_tables

__all__ = ["derivatives"]


def derivatives(
    x: torch.Tensor,
    data: TriangleGreenData,
    vertices: torch.Tensor,
    lib: ctypes.CDLL,
    order: int,
    grad_phi: torch.Tensor,
    grad_psi: torch.Tensor,
    hess_phi: torch.Tensor,
    hess_psi: torch.Tensor,
) -> torch.Tensor:
    """The native kernel on float64 CPU points ``x`` ``(n, 3)``, writing ``grad_phi (n, V, 3)``,
    ``grad_psi (n, T, 3)`` and, for ``order=2``, ``hess_phi (n, V, 3, 3)``, ``hess_psi (n, T, 3,
    3)`` in place (contiguous float64). Returns the ``(n,)`` bool mask of rows it served (the others
    are zero: points on the cage, thin faces seen from a few widths)."""
    ok = torch.empty(x.shape[0], dtype=torch.int32)
    second = order == 2
    _native.call(
        lib,
        "tc_gcd3d",
        **native_tables(data, vertices),
        X=x.contiguous(),
        n=x.shape[0],
        order=order,
        GPHI=grad_phi,
        GPSI=grad_psi,
        HPHI=hess_phi if second else None,
        HPSI=hess_psi if second else None,
        OK=ok,
    )
    _native.check_workspace(grad_phi, "Green derivatives")
    return ok.bool()
