r"""Green coordinates for triquad cages (QGC): the public function. The kernel is ``kernel``."""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch

from torchcage._core.alloc import cat_output
from torchcage._core.batch import over_cage_batch
from torchcage._core.common import (
    ON_CAGE_TOLERANCE,
    VERTEX_SNAP,
    as_inputs,
    chunks,
    on_cage_tolerances,
    snap_to_vertices,
    snap_to_vertices_batch,
    unit_sum,
)
from torchcage._core.compiled import CompiledOp, through_op
from torchcage.backends import Op, resolve, select
from torchcage.cage import Cage
from torchcage.errors import warn_outside
from torchcage.families.green.kernel3d import triangle_green_geometry, triangle_integrals
from torchcage.families.quad_green.kernel import QuadGreenData, qgc3d_chunk, quad_green_data
from torchcage.families.quad_green.native import native_coordinates
from torchcage.families.quad_mean_value.api import check_quads, check_tol, prepare_quad_call, quad_batch_call

__all__ = ["quad_green_coordinates"]

#: Points given in a dtype coarser than float64 lie on the cage when they are within this many units
#: of that dtype's rounding (``eps * (size + largest coordinate)``) of it: a float32 point placed on
#: a face rounds to up to ``eps_32 |x|`` off it, half the time outside (where the bare integrals
#: give 0, not the limit from inside).
INPUT_ROUNDING = 8.0

#: The kernels of quad Green coordinates: native C (float64 CPU points) or torch.
QGC = Op("quad Green coordinates")


def input_rounding_tolerance(dtype: torch.dtype, cage: Cage) -> float:
    """The distance ``INPUT_ROUNDING * eps(dtype) * (size + largest coordinate)`` within which points
    given in ``dtype`` are taken on the cage; 0 for float64 (the kernels' own tolerance serves).

    Examples:
        >>> import torch, torchcage
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
        >>> input_rounding_tolerance(torch.float64, cube), input_rounding_tolerance(torch.float32, cube) > 1e-6
        (0.0, True)
    """
    eps = torch.finfo(dtype).eps
    if eps <= torch.finfo(torch.float64).eps:
        return 0.0
    v = cage.vertices.detach()
    return INPUT_ROUNDING * eps * (cage.scale + float(v.abs().max()))


def _quad_part_torch(
    x: torch.Tensor, qdata: QuadGreenData, V: int, quad_tol: float | None = None
) -> tuple[torch.Tensor, ...]:
    """Quads' ``phi`` ``(m, V)`` and ``psi`` ``(m, 4Q)``, the first quad each point lies on (or -1)
    and the interpolating values ``(m, V)`` there, with the torch kernel."""
    m = x.shape[0]
    Phi, on_q, b = qgc3d_chunk(x, qdata, quad_tol)  # (Q, m, 8), (Q, m), (Q, m, 4)
    quads = qdata.quads
    phi = torch.zeros(m, V, dtype=x.dtype, device=x.device)
    for k in range(4):
        phi = phi.index_add(1, quads[:, k], Phi[..., k].T)
    psi = Phi[..., 4:].permute(1, 0, 2).reshape(m, 4 * quads.shape[0])
    f = on_q.to(torch.int8).argmax(dim=0)
    onq = torch.where(on_q.any(dim=0), f, -1)
    hat = torch.zeros(m, V, dtype=x.dtype, device=x.device).scatter_add(
        1, quads[f], b[f, torch.arange(m, device=x.device)]
    )
    return phi, psi, onq, hat


def _tri_part_torch(
    x: torch.Tensor, tri_p: torch.Tensor, tri_geometry: tuple, triangles: torch.Tensor, V: int, tol: float
) -> tuple[torch.Tensor, ...]:  # fmt: skip
    """Triangles' ``phi`` ``(m, V)`` (principal values on the cage) and ``psi`` ``(m, T)``, whether
    each point lies on a triangle, and its hat values ``(m, V)`` there, with the torch kernel."""
    m = x.shape[0]
    a = tri_p[None] - x[:, None, None, :]  # (m, T, 3, 3)
    phi_face, psi_t, _, on_face, alpha = triangle_integrals(a, tuple(g[None] for g in tri_geometry), tol)
    phi = torch.zeros(m, V, dtype=x.dtype, device=x.device)
    for i in range(3):
        phi = phi.index_add(1, triangles[:, i], phi_face[..., i])
    f = on_face.to(torch.int8).argmax(dim=1)
    bary = alpha[torch.arange(m, device=x.device), f].clamp_min(0.0)
    bary = bary / bary.sum(dim=1, keepdim=True).clamp_min(1e-300)
    hat = torch.zeros(m, V, dtype=x.dtype, device=x.device).scatter_add(1, triangles[f], bary)
    return phi, psi_t, on_face.any(dim=1), hat


def _chunk(x: torch.Tensor, tri_part, quad_part, V: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(phi (m, V), psi (m, T + 4Q))`` of a chunk ``x`` ``(m, 3)``; ``tri_part(x)`` and
    ``quad_part(x)`` compute the triangles' and the quads' shares (None where there are none)."""
    m = x.shape[0]
    psis = []
    if tri_part is not None:
        phi, psi_t, on, hat = tri_part(x)
        psis.append(psi_t)
    else:
        phi = torch.zeros(m, V, dtype=x.dtype, device=x.device)
        on = torch.zeros(m, dtype=torch.bool, device=x.device)
        hat = torch.zeros(m, V, dtype=x.dtype, device=x.device)
    if quad_part is not None:
        phi_q, psi_q, onq, hat_q = quad_part(x)
        phi = phi + phi_q
        psis.append(psi_q)
        hat = torch.where(on[:, None], hat, hat_q)
        on = on | (onq >= 0)
    if bool(on.any()):
        # On the cage: the principal values plus the jump of the double layer, 1 - sum(phi), on the
        # interpolating basis functions of the point (the limit from inside).
        phi = phi + torch.where(on[:, None], (1 - phi.sum(dim=1, keepdim=True)) * hat, 0.0)
    return phi, torch.cat(psis, dim=1)


def _native_batch(
    points: torch.Tensor,
    cage: Cage,
    n: int,
    chunk_size: int | None,
    dtype: torch.dtype | None,
    progress: bool | Callable[[int, int], None],
    backend: str,
    allow_invalid: bool,
    tol: float | None,
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Quad Green coordinates ``(phi (*B', N, V), psi (*B', N, T + 4Q))`` of a batch of cages with
    one topology by the native kernels: one call of each per chunk of points for every cage, the
    cages' tables built by one set of tensor operations; element by element the numbers of the
    single-cage call (the same tolerances, centring, vertex snap, kernels and unit sum). ``None``
    where it does not serve (another backend or device, a compute dtype other than float64, an
    autograd graph or a ``torch.func`` transform, no native build): the caller then loops.

    Raises:
        ValueError: a wrong ``n``, ``tol`` or ``backend``.
        CageError: invalid quads (unless ``allow_invalid``).
        PointsError: points that do not broadcast with the cages, NaN or inf, naming the element.
    """
    call = quad_batch_call(QGC, points, cage, n, dtype, backend, allow_invalid, tol, "quad Green coordinates")
    if call is None:
        return None
    pts, verts, batch, out_dtype, lib, quad_tol = call
    compute = torch.float64
    # as the single-cage call, element by element: the on-cage tolerance of the uncentred cage, at
    # least the rounding of the points' dtype (INPUT_ROUNDING); the box's middle as the centre
    eps = torch.finfo(pts.dtype).eps
    coarse = eps > torch.finfo(torch.float64).eps
    v0 = verts.to(compute)  # (B', V, 3): the broadcast batch's cages
    scales = (v0.amax(dim=-2) - v0.amin(dim=-2)).norm(dim=-1)  # (B',), as Cage.scale of each
    rounding = INPUT_ROUNDING * eps * (scales + v0.abs().amax(dim=(-2, -1))) if coarse else torch.zeros_like(scales)
    tols = torch.maximum(on_cage_tolerances(verts), rounding)
    x0 = pts.to(compute)
    centre = (v0.amax(dim=-2) + v0.amin(dim=-2)) / 2  # (B, 3)
    v = v0 - centre[:, None]
    x = snap_to_vertices_batch(
        x0 - centre[:, None], v, torch.maximum(VERTEX_SNAP * ON_CAGE_TOLERANCE * scales, rounding)
    )
    phi, psi = native_coordinates(lib, x, v, cage.triangles, cage.quads, tols, n, quad_tol, chunk_size, progress)
    phi = unit_sum(phi, x0, v0)
    N, K = x.shape[1], psi.shape[-1]
    return phi.to(out_dtype).reshape(*batch, N, v.shape[1]), psi.to(out_dtype).reshape(*batch, N, K)


#: The function as one opaque custom op under ``torch.compile`` (:mod:`torchcage._core.compiled`).
COMPILED = CompiledOp(
    "qgc",
    lambda points, cage, options: tuple(quad_green_coordinates(points, cage, **options)),
    lambda vertices, triangles, quads, edges: [vertices.shape[-2], triangles.shape[0] + 4 * quads.shape[0]],
    QGC,
)


def quad_green_coordinates(
    points: torch.Tensor,
    cage: Cage,
    n: int = 2,
    *,
    chunk_size: int | None = None,
    dtype: torch.dtype | None = None,
    progress: bool | Callable[[int, int], None] = False,
    backend: str = "auto",
    allow_invalid: bool = False,
    tol: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Green coordinates for triquad cages (Thiery and Boubekeur 2022).

    Triangles keep Lipman's Green coordinates; each quad, a bilinear patch, adds to its corners'
    ``phi`` and has four normal coordinates, one per corner. At rest, for points inside the cage,

    ``phi @ V + psi[:, :T] @ n + sum_{q,k} psi[:, T + 4q + k] N_{q,k} = x``

    with ``n`` the unit outward triangle normals and ``N_{q,k} = (q_{k+1} - q_k) x (q_{k+3} - q_k)``
    the unnormalised corner normals of quad ``q`` (:meth:`Cage.quad_corner_normals`). This
    identity (linear precision) is exact by construction; the rest of each quad's coordinates is
    estimated by an adaptive Riemann sum on ``4 (n+1)^2`` sub-triangles of the quad, or, with
    ``tol``, computed from the defining integrals to that relative tolerance.

    Args:
        points: ``(*, 3)`` points inside the cage.
        cage: a closed 3D cage of triangles and/or valid quads.
            Or a batch of cages ``(*B, V, D)`` with one topology: then ``points`` are
            ``(*B, N, D)`` (or ``(N, D)``, shared) and every result gains the batch shape in front
            (``(*B, N, V)``); each element equals the call on ``cage[b]`` (docs/learning.md).
        n: tessellation parameter, ``n >= 1`` (cost grows like ``(n+1)^2``).
        chunk_size: points per chunk (memory grows with ``chunk_size x quads x (n+1)^2``).
        dtype: dtype of the result (default: that of the inputs). The kernels compute in float64
            whatever it is (float32 would lose accuracy near the cage: see docs/accuracy.md).
        progress: ``True`` for a progress bar, or a callable ``progress(done, total)``.
        backend: ``"auto"`` (default): the native C kernel for the quads with float64 CPU points
            when no autograd graph is needed, else the torch kernel; ``"torch"`` or ``"native"``.
        allow_invalid: compute even if some quads fail the validity predicate (with a warning).
        tol: if given, the quads' integrals (``int phi_k dOmega`` and ``int phi_k / r``, per
            corner) to this relative tolerance by an error-controlled Gauss quadrature instead of
            the Riemann sum (``n`` is then unused; docs/green.md).

    Gradients: the torch kernel is differentiable with respect to the points and the cage
    vertices; ``"auto"`` picks it when either requires grad.

    Points outside the cage (whose coordinates sum to 0, not 1) warn with their count
    (``OutsideCageWarning``). Points within the rounding of their own dtype of the cage
    (``INPUT_ROUNDING`` units: a float32 point placed on a face) get the values on the cage, the
    limit from inside.

    Returns:
        ``(phi, psi)``: ``(*, V)`` and ``(*, T + 4Q)``; column ``T + 4q + k`` of ``psi`` belongs to
        corner ``k`` of quad ``q``.

    Raises:
        CageError: a 2D cage, or invalid quads (unless ``allow_invalid``).
        PointsError: points of the wrong shape or device, NaN or inf.

    Examples:
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
    if through_op(points, cage) and not allow_invalid:  # one opaque op (compile, vmap: :mod:`_core.compiled`)
        phi, psi = COMPILED(points, cage, chunk_size, backend, n, check_tol(tol), dtype=dtype)
        return phi, psi
    backend = resolve(backend)
    points, cage = as_inputs(points, cage)
    if cage.is_batched:
        out = _native_batch(points, cage, n, chunk_size, dtype, progress, backend, allow_invalid, tol)
        if out is not None:
            phi, psi = out
            warn_outside(phi.detach().sum(dim=-1).reshape(-1), "quad Green coordinates")
            return phi, psi
        # (the torch kernel, graphs, torch.func transforms: one call per element, invalid quads
        # refused first for the batch, naming the element)
        if not allow_invalid:
            check_quads(cage, False, "quad Green coordinates")
        return over_cage_batch(
            quad_green_coordinates,
            points,
            cage,
            n=n,
            chunk_size=chunk_size,
            dtype=dtype,
            progress=progress,
            backend=backend,
            allow_invalid=allow_invalid,
            tol=tol,
        )
    quad_tol = check_tol(tol)
    x, out_dtype, verts, tol = prepare_quad_call(points, cage, n, dtype, allow_invalid, "quad Green coordinates")
    # Points of a coarser dtype within its rounding of the cage are on it (module INPUT_ROUNDING).
    rounding = input_rounding_tolerance(points.dtype, cage)
    tol = max(tol, rounding)
    # The kernels work about the cage's centre (the coordinates do not change under translation;
    # about the origin, a cage moved by 1e6 lost 1e6 eps to every difference of corners and point).
    # The sum is made 1 about the origin, where the caller multiplies by the vertices (unit_sum).
    x0, verts0 = x, verts
    centre = (verts.detach().amax(dim=0) + verts.detach().amin(dim=0)) / 2
    x, verts = x - centre, verts - centre
    x = snap_to_vertices(x, verts, max(VERTEX_SNAP * ON_CAGE_TOLERANCE * cage.scale, rounding))  # (the limit there)
    T, Q, V = cage.triangles.shape[0], cage.quads.shape[0], cage.num_vertices
    lib = select(QGC, backend, x, cage.vertices).lib
    lead = points.shape[:-1]
    if lib is not None:  # (a batch of one)
        tols = torch.tensor([tol], dtype=torch.float64)
        phi, psi = native_coordinates(
            lib, x[None], verts[None], cage.triangles, cage.quads, tols, n, quad_tol, chunk_size, progress
        )
        phi = unit_sum(phi[0], x0, verts0)
        warn_outside(phi.sum(dim=-1), "quad Green coordinates")  # (as QuadGreenCoordinates and deform)
        return phi.to(out_dtype).reshape(*lead, V), psi[0].to(out_dtype).reshape(*lead, T + 4 * Q)
    tri_part = quad_part = None
    if T:
        tri_p = verts[cage.triangles]
        tri_part = functools.partial(
            _tri_part_torch,
            tri_p=tri_p,
            tri_geometry=triangle_green_geometry(tri_p),
            triangles=cage.triangles,
            V=V,
            tol=tol,
        )
    if Q:
        qdata = quad_green_data(verts, cage.quads, tol, n)
        quad_part = functools.partial(_quad_part_torch, qdata=qdata, V=V, quad_tol=quad_tol)
    size = chunk_size or max(8, (1 << 17) // (max(Q, 1) * 4 * (n + 1) ** 2 + T))
    phis, psis = [], []
    for sl in chunks(x.shape[0], size, progress, desc="quad Green coordinates"):
        ph, ps = _chunk(x[sl], tri_part, quad_part, V)
        phis.append(ph)
        psis.append(ps)
    phi = unit_sum(cat_output(phis), x0, verts0) if phis else x.new_zeros((0, V))
    if phis:  # (as QuadGreenCoordinates and deform: quad Green coordinates are defined inside the cage)
        warn_outside(phi.detach().sum(dim=-1), "quad Green coordinates")
    psi = cat_output(psis) if psis else x.new_zeros((0, T + 4 * Q))
    return phi.to(out_dtype).reshape(*lead, V), psi.to(out_dtype).reshape(*lead, T + 4 * Q)
