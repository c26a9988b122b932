"""Glue to the native CPU kernel of quad mean value coordinates (``torchcage/backends/native/qmvc3d.c``,
with ``tc_mvc3d`` for a triquad cage's triangles): a batch of cages with one topology (one cage: a
batch of one), one call per chunk of points for every cage."""

from __future__ import annotations

import ctypes
from collections.abc import Callable

import torch

from torchcage._core.alloc import zeros_output
from torchcage._core.common import chunks
from torchcage._core.quad_quadrature import gauss_table
from torchcage.backends import native as _native
from torchcage.families.mean_value import native3d as _mvc3d_native
from torchcage.families.mean_value.kernel3d import PART_FAR_FIELD_RATIO
from torchcage.families.quad_mean_value.kernel import quad_sizes

__all__ = ["native_coordinates", "native_tables"]

#: Points per chunk (over the cages of a batch) when a progress bar asks for chunks.
NATIVE_CHUNK = 1 << 14


def native_tables(
    vertices: torch.Tensor, quads: torch.Tensor, tol: torch.Tensor, n: int, qtol: float | None = None
) -> dict[str, object]:
    """``tc_qmvc3d``'s arguments for a batch of cages with one topology.

    Args:
        vertices: ``(B, V, 3)`` float64 CPU vertices (centred).
        quads: ``(Q, 4)`` the shared quads.
        tol: ``(B,)`` float64 absolute on-cage tolerances.
        n: the Riemann sum's grid parameter.
        qtol: the quadrature's relative tolerance, or ``None`` for the Riemann sum.
    """
    P = vertices.contiguous()
    q = quads.to(torch.int32).contiguous()
    return {
        "B": P.shape[0],
        "P": P,
        "V": P.shape[1],
        "quads": q,
        "Q": q.shape[0],
        "size": quad_sizes(P, quads).contiguous(),
        "tol": tol.to(torch.float64).contiguous(),
        "n": n,
        "qtol": 0.0 if qtol is None else qtol,
        "gl": gauss_table(),
    }


def native_coordinates(
    lib: ctypes.CDLL,
    x: torch.Tensor,
    vertices: torch.Tensor,
    triangles: torch.Tensor,
    quads: torch.Tensor,
    tol: torch.Tensor,
    n: int,
    qtol: float | None = None,
    chunk_size: int | None = None,
    progress: bool | Callable[[int, int], None] = False,
) -> torch.Tensor:
    """Quad mean value coordinates by the native kernels (triangles: ``tc_mvc3d``'s raw weights;
    quads: ``tc_qmvc3d``, which adds theirs and normalises each row), before the far field's
    normalisation and without the check of undefined rows.

    Args:
        lib: the native library.
        x: ``(B, N, 3)`` centred float64 CPU points, one set per cage, or ``(1, N, 3)``, shared.
        vertices: ``(B, V, 3)`` the centred cages (float64).
        triangles: ``(T, 3)`` and ``quads``: ``(Q, 4)`` the shared faces.
        tol: ``(B,)`` float64 absolute on-cage tolerances (the uncentred cages').
        n: the Riemann sum's grid parameter; ``qtol``: the quadrature's tolerance (``tol=``) or ``None``.
        chunk_size: points per chunk. By default one call for every point, or with a progress
            bar chunks of ``16,384 / B`` points (a batch's chunks go through temporaries: their
            rows are not contiguous).
        progress: ``True`` for a progress bar, or a callable ``progress(done, total)``.

    Returns:
        ``(B, N, V)`` float64 coordinates (rows whose total weight vanishes are not finite).

    Raises:
        ValueError: points for neither one nor ``B`` cages.
        MemoryError: the kernel could not allocate its per-thread scratch.

    Examples:
        >>> import torch, torchcage
        >>> from torchcage.backends import native
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
        >>> v = cube.vertices.to(torch.float64)[None]
        >>> x = torch.tensor([[[0.1, 0.2, -0.3]]], dtype=torch.float64)
        >>> lib = native.library()
        >>> w = native_coordinates(lib, x, v, cube.triangles, cube.quads, torch.tensor([1e-12]), 4) if lib else None
        >>> lib is None or bool(torch.allclose(w @ v, x))
        True
    """
    B, V, N = vertices.shape[0], vertices.shape[1], x.shape[1]
    if x.shape[0] not in (1, B):
        raise ValueError(f"tc_qmvc3d: points for {x.shape[0]} cages, but {B} cages: give 1 (shared) or {B}")
    tri_tables = _mvc3d_native.batch_tables(vertices, triangles, tol) if triangles.shape[0] else None
    quad_tables = native_tables(vertices, quads, tol, n, qtol) if quads.shape[0] else None
    if tri_tables is not None and quad_tables is not None:
        # The triangles are part of the cage: their own sum does not show the far field's
        # cancellation, so faces seen small always take the far-field rule.
        tri_tables["cancel_c"] = 0.0
        tri_tables["far_c"] = PART_FAR_FIELD_RATIO
    out = zeros_output(B, N, V, dtype=torch.float64)
    size = chunk_size or (max(64, NATIVE_CHUNK // B) if progress else max(N, 1))
    for sl in chunks(N, size, progress, desc="quad mean value coordinates"):
        direct = B == 1 or (sl.start == 0 and sl.stop == N)  # (contiguous rows: written in place)
        xs = x[:, sl].contiguous()
        W = out[:, sl] if direct else torch.zeros((B, xs.shape[1], V), dtype=torch.float64)
        if tri_tables is not None:
            on = _mvc3d_native.native_chunk(xs, tri_tables, lib, W, normalize=quad_tables is None)
        else:
            on = torch.zeros((B, xs.shape[1]), dtype=torch.uint8)
        if quad_tables is not None:
            _native.call(lib, "tc_qmvc3d", **quad_tables, X=xs, XB=xs.shape[0], npts=xs.shape[1], W=W, on=on)
            _native.check_workspace_flags(on, "quad mean value")
        if not direct:
            out[:, sl] = W
    return out
