"""Glue to the native CPU kernels of mean value coordinates with their analytic derivatives
(``torchcage/backends/native/mvcd3d.c``, ``mvcd2d.c``): their tables, keyed by the C argument names
(layouts in ``torchcage/backends/native/abi.py``), and the call on a chunk of points."""

from __future__ import annotations

import ctypes
import functools

import numpy as np
import torch

from torchcage._core.common import collapsed_gauss, on_cage_tolerance, triangle_geometry, unique_face_edges
from torchcage.backends import native as _native
from torchcage.cage import Cage

__all__ = ["DERIVATIVE_FAR_FIELD_ORDER", "DERIVATIVE_FAR_FIELD_RATIO", "DERIVATIVE_SPLIT_FORM_RATIO", "G_ORDER",
           "native_chunk", "native_tables"]  # fmt: skip

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
    """``tc_mvcd3d``'s (3D) or ``tc_mvcd2d``'s (2D) per-cage arguments, float64 on the CPU."""
    P = cage.vertices.detach().to("cpu", torch.float64).contiguous()
    tol = on_cage_tolerance(cage)
    if cage.dim == 2:
        edges = cage.edges.cpu().to(torch.int32).contiguous()
        return {"P": P, "V": P.shape[0], "edges": edges, "NE": edges.shape[0], "tol": tol}
    p, normal, two_area = triangle_geometry(
        cage, torch.float64, "use quad_mean_value_coordinates for quad/triquad cages, or cage.triangulated()"
    )
    p, normal, two_area = p.cpu(), normal.cpu(), two_area.cpu()
    E = p.roll(-1, dims=1) - p.roll(-2, dims=1)  # (T, 3, 3): E_e = p_{e+1} - p_{e+2}
    ell = E.norm(dim=-1)
    bary, qw = collapsed_gauss(DERIVATIVE_FAR_FIELD_ORDER, torch.float64, torch.device("cpu"))
    gy, gw = _gauss01(G_ORDER)
    tri = cage.triangles.cpu()
    edges, face_edge, _ = unique_face_edges(tri)
    far_nodes = torch.einsum("qi,tic->tqc", bary, p).contiguous()
    return {
        "P": P,
        "V": P.shape[0],
        "tri": tri.to(torch.int32).contiguous(),
        "T": tri.shape[0],
        "fe": face_edge.to(torch.int32).contiguous(),
        "NE": edges.shape[0],
        "E": E.contiguous(),
        "nrm": normal.contiguous(),
        "two_area": two_area.contiguous(),
        "ell": ell.contiguous(),
        "gram": (E @ E.transpose(1, 2)).contiguous(),
        "longest": ell.max(dim=1).values.contiguous(),
        "far_nodes": far_nodes,
        "far_coef": ((two_area[:, None, None] * qw[None, :, None]) * bary[None]).contiguous(),
        "Q": far_nodes.shape[1],
        "far_c": DERIVATIVE_FAR_FIELD_RATIO,
        "near_c": DERIVATIVE_SPLIT_FORM_RATIO,
        "gl_y": gy.contiguous(),
        "gl_w": gw.contiguous(),
        "ng": G_ORDER,
        "tol": tol,
    }


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
    """The kernel on a chunk ``x`` ``(n, D)`` float64 into the contiguous ``lam (n, V)``, ``grad
    (n, V, D)``, ``hess (n, V, D, D)`` (``None`` for ``order=1``) and the uint8 flags ``on (n,)``
    (1: on the cage, 2: the total weight vanishes)."""
    name = "tc_mvcd3d" if x.shape[1] == 3 else "tc_mvcd2d"
    _native.call(lib, name, **tables, X=x.contiguous(), n=x.shape[0], order=order, L=lam, G=grad, H=hess, on=on)
