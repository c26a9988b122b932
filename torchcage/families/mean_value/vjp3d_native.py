"""Glue to the native CPU kernel of the joint vector-Jacobian product of 3D mean value
coordinates (``torchcage/backends/native/mvc3d_vjp.c``; the formulas in :mod:`.vjp3d`)."""

from __future__ import annotations

import ctypes

import torch

from torchcage.backends import native as _native
from torchcage.families.mean_value.derivatives_native import DERIVATIVE_FAR_FIELD_RATIO, DERIVATIVE_SPLIT_FORM_RATIO
from torchcage.families.mean_value.edge_line import EDGE_LINE_BAND
from torchcage.families.mean_value.kernel3d import CANCELLATION_RATIO, FAR_ALWAYS_RATIO, SPLIT_FORM_RATIO

__all__ = ["native_vjp", "native_vjp_batch", "native_vjp_near"]


def _shared_arguments(
    x: torch.Tensor, vertices: torch.Tensor, tri: torch.Tensor, gbar: torch.Tensor, tol: float
) -> dict[str, object]:
    """The inputs and thresholds both VJP kernels take, by their ABI names."""
    return {
        "P": vertices.contiguous(),
        "V": vertices.shape[0],
        "tri": tri.to(torch.int32).contiguous(),
        "T": tri.shape[0],
        "X": x.contiguous(),
        "n": x.shape[0],
        "G": gbar.contiguous(),
        "tol": tol,
        **_THRESHOLDS,
    }


#: The direct form's thresholds (the regular-point test), by their ABI names.
_THRESHOLDS = {"near_c": SPLIT_FORM_RATIO, "cancel_c": CANCELLATION_RATIO, "far_always": FAR_ALWAYS_RATIO}


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
        **_shared_arguments(x, vertices, tri, gbar, tol),
        GX=gx,
        GP=gP,
        reg=reg,
    )
    return gx, gP, reg.bool()


def native_vjp_batch(
    lib: ctypes.CDLL, x: torch.Tensor, vertices: torch.Tensor, tri: torch.Tensor, gbar: torch.Tensor, tol: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`native_vjp` of a batch of cages with one topology in one call: float64 CPU ``x``
    ``(B, n, 3)``, ``vertices`` ``(B, V, 3)``, ``gbar`` ``(B, n, V)``, ``tol`` ``(B,)`` ->
    ``(gx (B, n, 3), gP (B, V, 3), regular (B, n))``, element by element :func:`native_vjp`'s."""
    B, n, V = vertices.shape[0], x.shape[1], vertices.shape[1]
    gx = torch.empty((B, n, 3), dtype=torch.float64)
    gP = torch.empty((B, V, 3), dtype=torch.float64)
    reg = torch.empty((B, n), dtype=torch.uint8)
    _native.call(
        lib,
        "tc_mvc3d_vjp_batch",
        B=B,
        P=vertices.contiguous(),
        V=V,
        tri=tri.to(torch.int32).contiguous(),
        T=tri.shape[0],
        X=x.contiguous(),
        n=n,
        G=gbar.contiguous(),
        tol=tol.contiguous(),
        **_THRESHOLDS,
        GX=gx,
        GP=gP,
        reg=reg,
    )
    return gx, gP, reg.bool()


def native_vjp_near(
    lib: ctypes.CDLL,
    x: torch.Tensor,
    vertices: torch.Tensor,
    tri: torch.Tensor,
    gbar: torch.Tensor,
    tol: float,
    split_pairs: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The joint product split per face for points near a face's support plane, and in closed
    form for points on the cage (a face, an edge, a vertex: the largest holding face's interpolant)
    (``torchcage/backends/native/mvc3d_vjp_near.c``): float64 CPU ``x`` ``(n, 3)``, ``vertices``
    ``(V, 3)``, ``tri`` ``(T, 3)``, ``gbar`` ``(n, V)``; ``split_pairs``: the kernel differentiates
    the careful pairs too (forward mode of the split form), else it leaves them to the caller
    (``pair``).

    Returns:
        ``(gx (n, 3), gP (V, 3), split (n,) bool, pair (n, T) uint8, wbar (n, V), sn (n,), hs (n,))``:
        the products over the faces regular for each point that takes the split, or the closed
        form's (``split``; the other points are left to the caller); the faces left to the caller
        (``pair``: 1; 2 for the nearest face around the point's foot, whose distance is ``hs``; 3
        for any other face around it, near an edge); ``wbar = (gbar - gbar . lam) / W``; ``sn``
        the sum over every face but the one marked 2 of ``wbar . w_f``.
    """
    n, V, T = x.shape[0], vertices.shape[0], tri.shape[0]
    f64 = torch.float64
    gx, gP, sn, hs = (
        torch.empty((n, 3), dtype=f64),
        torch.empty((V, 3), dtype=f64),
        torch.empty(n, dtype=f64),
        torch.empty(n, dtype=f64),
    )
    status, pair, wbar = (
        torch.empty(n, dtype=torch.uint8),
        torch.empty((n, T), dtype=torch.uint8),
        torch.empty((n, V), dtype=f64),
    )
    _native.call(
        lib,
        "tc_mvc3d_vjp_near",
        **_shared_arguments(x, vertices, tri, gbar, tol),
        band=EDGE_LINE_BAND,
        near_d=DERIVATIVE_SPLIT_FORM_RATIO,
        far_d=DERIVATIVE_FAR_FIELD_RATIO,
        split_pairs=int(split_pairs),
        GX=gx,
        GP=gP,
        status=status,
        PAIR=pair,
        WB=wbar,
        SN=sn,
        HS=hs,
    )
    return gx, gP, status != 0, pair, wbar, sn, hs
