"""Glue to the native CPU kernel of quad Green coordinates (``torchcage/backends/native/qgc3d.c``, with
``tc_gc3d_batch`` for a triquad cage's triangles): a batch of cages with one topology (one cage: a
batch of one), one call of each kernel per chunk of points for every cage, and the jump term on the
cage."""

from __future__ import annotations

import ctypes
from collections.abc import Callable

import torch

from torchcage._core.alloc import empty_output
from torchcage._core.common import chunks
from torchcage._core.quad_quadrature import gauss_table
from torchcage.backends import native as _native
from torchcage.families.green.native3d import batch_chunk, batch_subset_tables
from torchcage.families.quad_green.kernel import quad_systems, tessellation_pattern
from torchcage.families.quad_mean_value.kernel import quad_sizes

__all__ = ["native_coordinates", "native_quad_tables"]

#: Points per chunk, over the cages of a batch.
NATIVE_CHUNK = 1 << 14

_SPLIT_KEYS = ("Pv", "tri", "edges", "eu", "fe", "nrm", "two_area", "ell", "edir", "eout", "gbary")


def native_quad_tables(
    vertices: torch.Tensor, quads: torch.Tensor, tol: torch.Tensor, n: int, qtol: float | None = None
) -> dict[str, object]:
    """``tc_qgc3d``'s arguments for a batch of cages with one topology: the quads' constants and,
    prefixed ``s_``, the Green kernel tables of the triangles ``(q0 q1 q2)``, ``(q0 q2 q3)`` of every
    quad (rows ``2q``, ``2q + 1``): outside a quad's tetrahedron they give its invariants (see
    qgc3d.c).

    Args:
        vertices: ``(B, V, 3)`` float64 CPU vertices (centred).
        quads: ``(Q, 4)`` the shared quads.
        tol: ``(B,)`` float64 absolute on-cage tolerances.
        n: the Riemann sum's tessellation parameter (``K = n + 1``).
        qtol: the quadrature's relative tolerance, or ``None`` for the Riemann sum.
    """
    split = torch.stack([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]], dim=1).reshape(-1, 3)
    s = batch_subset_tables(vertices, split, tol)
    origin, _, pinv, null = quad_systems(vertices, quads)
    K = n + 1
    pattern = tessellation_pattern(K)
    P = vertices.contiguous()
    return {
        "B": P.shape[0],
        "P": P,
        "V": P.shape[1],
        "quads": quads.to(torch.int32).contiguous(),
        "Q": quads.shape[0],
        "size": quad_sizes(P, quads).contiguous(),
        "pinv": pinv.contiguous(),
        "null": null.contiguous(),
        "origin": origin.contiguous(),
        "pattern": pattern.to(torch.int32).contiguous(),
        "Pn": pattern.shape[0],
        "K": K,
        "tol": tol.to(torch.float64).contiguous(),
        "qtol": 0.0 if qtol is None else qtol,
        "gl": gauss_table(),
        **{f"s_{k}": s[k] for k in _SPLIT_KEYS},
        "s_E": s["E"],
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
) -> tuple[torch.Tensor, torch.Tensor]:
    """Quad Green coordinates by the native kernels, before the unit sum: the triangles' ``phi``
    (principal values) and ``psi`` (``tc_gc3d_batch``), the quads' (``tc_qgc3d``), and on the cage
    the jump of the double layer, ``1 - sum(phi)``, on the interpolating basis functions of the point
    (the limit from inside).

    Args:
        lib: the native library.
        x: ``(B, N, 3)`` float64 CPU points, centred as the cages and snapped to their vertices.
        vertices: ``(B, V, 3)`` the centred cages (float64).
        triangles: ``(T, 3)`` and ``quads``: ``(Q, 4)`` the shared faces.
        tol: ``(B,)`` float64 absolute on-cage tolerances.
        n: the Riemann sum's tessellation parameter; ``qtol``: the quadrature's tolerance or ``None``.
        chunk_size: points per chunk (default ``16,384 / B``: the chunk's temporaries, several of
            ``(B, chunk, V)``, stay those of 16,384 points of one cage).
        progress: ``True`` for a progress bar, or a callable ``progress(done, total)``.

    Returns:
        ``(phi (B, N, V), psi (B, N, T + 4Q))`` float64.

    Raises:
        MemoryError: a kernel could not allocate its per-thread scratch.

    Examples:
        >>> import torch, torchcage
        >>> from torchcage.backends import native
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
        >>> v = cube.vertices.to(torch.float64)[None]
        >>> x = torch.tensor([[[0.1, 0.2, -0.3]]], dtype=torch.float64)
        >>> lib = native.library()
        >>> out = native_coordinates(lib, x, v, cube.triangles, cube.quads, torch.tensor([1e-12]), 2) if lib else None
        >>> lib is None or bool(torch.allclose(out[0].sum(-1), torch.ones(1, 1, dtype=torch.float64)))
        True
    """
    B, V, N = vertices.shape[0], vertices.shape[1], x.shape[1]
    T, Q = triangles.shape[0], quads.shape[0]
    x = x.expand(B, N, 3)
    tri_tables = batch_subset_tables(vertices, triangles, tol) if T else None
    quad_tables = native_quad_tables(vertices, quads, tol, n, qtol) if Q else None
    size = chunk_size or max(64, NATIVE_CHUNK // B)  # (bounds the chunk's temporaries, as for one cage)
    parts = [
        _chunk(lib, x[:, sl].contiguous(), V, triangles, quads, tri_tables, quad_tables)
        for sl in chunks(N, size, progress, desc="quad Green coordinates")
    ]
    if len(parts) == 1:
        return parts[0]
    phi = empty_output(B, N, V, dtype=torch.float64)
    psi = empty_output(B, N, T + 4 * Q, dtype=torch.float64)
    torch.cat([p[0] for p in parts], dim=1, out=phi)
    torch.cat([p[1] for p in parts], dim=1, out=psi)
    return phi, psi


def _chunk(
    lib: ctypes.CDLL,
    x: torch.Tensor,
    V: int,
    triangles: torch.Tensor,
    quads: torch.Tensor,
    tri_tables: dict[str, object] | None,
    quad_tables: dict[str, object] | None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(phi (B, m, V), psi (B, m, T + 4Q))`` of a chunk ``x`` ``(B, m, 3)``."""
    B, m = x.shape[0], x.shape[1]
    f64 = torch.float64
    psis = []
    if tri_tables is not None:
        phi = torch.empty(B, m, V, dtype=f64)
        psi_t = torch.empty(B, m, triangles.shape[0], dtype=f64)
        onf = torch.empty(B, m, dtype=torch.int32)
        alpha = torch.empty(B, m, 3, dtype=f64)
        batch_chunk(x, tri_tables, lib, phi, psi_t, onf, alpha)
        onf = onf.long()
        hat = torch.zeros(B, m, V, dtype=f64).scatter_add(2, triangles[onf.clamp_min(0)], alpha)
        on = onf >= 0
        psis.append(psi_t)
    else:
        phi = torch.zeros(B, m, V, dtype=f64)
        on = torch.zeros(B, m, dtype=torch.bool)
        hat = torch.zeros(B, m, V, dtype=f64)
    if quad_tables is not None:
        Q = quads.shape[0]
        phi_q = torch.zeros(B, m, V, dtype=f64)
        psi_q = torch.empty(B, m, 4 * Q, dtype=f64)
        onq = torch.empty(B, m, dtype=torch.int32)
        uv = torch.zeros(B, m, 2, dtype=f64)
        _native.call(lib, "tc_qgc3d", **quad_tables, X=x, XB=B, n=m, PHI=phi_q, PSIQ=psi_q, ONQ=onq, UV=uv)
        _native.check_workspace(phi_q, "quad Green")
        onq = onq.long()
        u, v = uv[..., 0:1], uv[..., 1:2]
        b = torch.cat([(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v], dim=-1)
        hat_q = torch.zeros(B, m, V, dtype=f64).scatter_add(2, quads[onq.clamp_min(0)], b)
        phi = phi + phi_q
        psis.append(psi_q)
        hat = torch.where(on[..., None], hat, hat_q)
        on = on | (onq >= 0)
    if bool(on.any()):
        # On the cage: the principal values plus the jump of the double layer, 1 - sum(phi), on the
        # interpolating basis functions of the point (the limit from inside).
        phi = phi + torch.where(on[..., None], (1 - phi.sum(dim=-1, keepdim=True)) * hat, 0.0)
    return phi, torch.cat(psis, dim=-1)
