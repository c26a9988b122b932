r"""Green coordinates for triquad cages (QGC): the public function. The kernel is ``_qgc3d``."""

from __future__ import annotations

from collections.abc import Callable

import torch

from ..cage import Cage
from ._common import ON_CAGE_TOLERANCE, check_points, chunks, result_dtype
from ._green3d import triangle_frame, triangle_integrals
from ._qgc3d import QuadGreenData, quad_green_chunk, quad_green_data
from .quad_mean_value import check_quads

__all__ = ["quad_green_coordinates"]


def _chunk(
    x: torch.Tensor, tri_p: torch.Tensor, tri_geometry: tuple, triangles: torch.Tensor, qdata: QuadGreenData | None,
    V: int, tol: float,
) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """``(phi (m, V), psi (m, T + 4Q))`` of a chunk ``x`` ``(m, 3)``."""
    m, T = x.shape[0], triangles.shape[0]
    Q = 0 if qdata is None else qdata.quads.shape[0]
    phi = torch.zeros(m, V, dtype=x.dtype, device=x.device)
    psi = torch.zeros(m, T + 4 * Q, dtype=x.dtype, device=x.device)
    on = torch.zeros(m, dtype=torch.bool, device=x.device)
    hat = torch.zeros(m, V, dtype=x.dtype, device=x.device)
    if T:
        a = tri_p[None] - x[:, None, None, :]  # (m, T, 3, 3)
        phi_face, psi_t, _, on_face, alpha = triangle_integrals(a, tuple(g[None] for g in tri_geometry), tol)
        for i in range(3):
            phi.index_add_(1, triangles[:, i], phi_face[..., i])
        psi[:, :T] = psi_t
        on_t = on_face.any(dim=1)
        if bool(on_t.any()):
            f = on_face.to(torch.int8).argmax(dim=1)
            bary = alpha[torch.arange(m, device=x.device), f].clamp_min(0.0)
            bary = bary / bary.sum(dim=1, keepdim=True).clamp_min(1e-300)
            hat = torch.where(on_t[:, None], hat.scatter_add(1, triangles[f], bary), hat)
            on = on | on_t
    if qdata is not None:
        Phi, on_q, b = quad_green_chunk(x, qdata)  # (Q, m, 8), (Q, m), (Q, m, 4)
        quads = qdata.quads
        for k in range(4):
            phi.index_add_(1, quads[:, k], Phi[..., k].T)
        psi[:, T:] = Phi[..., 4:].permute(1, 0, 2).reshape(m, 4 * Q)
        has = on_q.any(dim=0) & ~on
        if bool(has.any()):
            f = on_q.to(torch.int8).argmax(dim=0)
            bq = b[f, torch.arange(m, device=x.device)]
            hq = torch.zeros(m, V, dtype=x.dtype, device=x.device).scatter_add(1, quads[f], bq)
            hat = torch.where(has[:, None], hq, hat)
            on = on | has
    if bool(on.any()):
        # On the cage: the principal values plus the jump of the double layer, 1 - sum(phi), on the
        # interpolating basis functions of the point (the limit from inside).
        phi = phi + torch.where(on[:, None], (1 - phi.sum(dim=1, keepdim=True)) * hat, 0.0)
    return phi, psi


def quad_green_coordinates(
    points: torch.Tensor,
    cage: Cage,
    n: int = 2,
    *,
    chunk_size: int | None = None,
    dtype: torch.dtype | None = None,
    progress: bool | Callable[[int, int], None] = False,
    allow_invalid: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Green coordinates for triquad cages (Thiery and Boubekeur 2022).

    Triangles keep Lipman's Green coordinates; each quad, a bilinear patch, adds to its corners'
    ``phi`` and has four normal coordinates, one per corner. At rest, for points inside the cage,

    ``phi @ V + psi[:, :T] @ n + sum_{q,k} psi[:, T + 4q + k] N_{q,k} = x``

    with ``n`` the unit outward triangle normals and ``N_{q,k} = (q_{k+1} - q_k) x (q_{k+3} - q_k)``
    the unnormalised corner normals of quad ``q`` (:meth:`Cage.quad_corner_normals`). This
    identity (linear precision) is exact by construction; the rest of each quad's coordinates is
    estimated by an adaptive Riemann sum on ``4 (n+1)^2`` sub-triangles of the quad.

    Args:
        points: ``(*, 3)`` points inside the cage.
        cage: a closed 3D cage of triangles and/or valid quads.
        n: tessellation parameter, ``n >= 1`` (cost grows like ``(n+1)^2``).
        chunk_size: points per chunk (memory grows with ``chunk_size x quads x (n+1)^2``).
        dtype: compute dtype. Default: float64, returned in the dtype of the inputs.
        progress: ``True`` for a progress bar, or a callable ``progress(done, total)``.
        allow_invalid: compute even if some quads fail the validity predicate (with a warning).

    Gradients: differentiable with respect to the points and the cage vertices (torch kernel).

    Returns:
        ``(phi, psi)``: ``(*, V)`` and ``(*, T + 4Q)``; column ``T + 4q + k`` of ``psi`` belongs to
        corner ``k`` of quad ``q``.

    Raises:
        CageError: a 2D cage, or invalid quads (unless ``allow_invalid``).
        PointsError: points of the wrong shape or device, NaN or inf.

    Example:
        >>> import torch, torchcage
        >>> from torchcage import functional as F
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))          # 6 quads
        >>> x = torch.tensor([[0.1, 0.2, -0.3]], dtype=torch.float64)
        >>> phi, psi = F.quad_green_coordinates(x, cube)
        >>> phi.shape, psi.shape
        (torch.Size([1, 8]), torch.Size([1, 24]))
        >>> N = cube.quad_corner_normals().reshape(-1, 3)
        >>> torch.allclose(phi @ cube.vertices + psi @ N, x)
        True
    """
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    flat = check_points(points, cage)
    check_quads(cage, allow_invalid)
    compute, out_dtype = result_dtype(flat, cage, dtype)
    x = flat.to(compute)
    verts = cage.vertices.to(compute)
    tol = ON_CAGE_TOLERANCE * cage.scale
    T, Q, V = cage.triangles.shape[0], cage.quads.shape[0], cage.num_vertices
    tri_p = verts[cage.triangles]
    tri_geometry = triangle_frame(tri_p)
    qdata = quad_green_data(verts, cage.quads, tol, n) if Q else None
    size = chunk_size or max(8, (1 << 17) // (max(Q, 1) * 4 * (n + 1) ** 2 + T))
    phis, psis = [], []
    for sl in chunks(x.shape[0], size, progress, desc="quad Green coordinates"):
        ph, ps = _chunk(x[sl], tri_p, tri_geometry, cage.triangles, qdata, V, tol)
        phis.append(ph)
        psis.append(ps)
    phi = torch.cat(phis) if phis else x.new_zeros((0, V))
    psi = torch.cat(psis) if psis else x.new_zeros((0, T + 4 * Q))
    lead = points.shape[:-1]
    return phi.to(out_dtype).reshape(*lead, V), psi.to(out_dtype).reshape(*lead, T + 4 * Q)
