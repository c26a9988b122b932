"""Glue to the native CPU kernel of the joint vector-Jacobian product of 3D mean value
coordinates (``torchcage/backends/native/mvc3d_vjp.c``; the formulas in :mod:`.vjp3d`)."""

from __future__ import annotations

import ctypes

import torch

from torchcage.backends import native as _native
from torchcage.families.mean_value.kernel3d import CANCELLATION_RATIO, FAR_ALWAYS_RATIO, SPLIT_FORM_RATIO

__all__ = ["native_vjp"]


def native_vjp(
    lib: ctypes.CDLL, x: torch.Tensor, vertices: torch.Tensor, tri: torch.Tensor, gbar: torch.Tensor, tol: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`._mvc3d_vjp.direct_vjp` by the native kernel: float64 CPU ``x`` ``(n, 3)``, ``vertices``
    ``(V, 3)``, ``tri`` ``(T, 3)``, ``gbar`` ``(n, V)`` -> ``(gx (n, 3), gP (V, 3), regular (n,))``."""
    n, V = x.shape[0], vertices.shape[0]
    gx = torch.empty((n, 3), dtype=torch.float64)
    gP = torch.empty((V, 3), dtype=torch.float64)
    reg = torch.empty(n, dtype=torch.uint8)
    _native.call(
        lib,
        "tc_mvc3d_vjp",
        P=vertices.contiguous(),
        V=V,
        tri=tri.to(torch.int32).contiguous(),
        T=tri.shape[0],
        X=x.contiguous(),
        n=n,
        G=gbar.contiguous(),
        tol=tol,
        near_c=SPLIT_FORM_RATIO,
        cancel_c=CANCELLATION_RATIO,
        far_always=FAR_ALWAYS_RATIO,
        GX=gx,
        GP=gP,
        reg=reg,
    )
    return gx, gP, reg.bool()
