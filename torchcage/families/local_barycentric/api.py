r"""Local barycentric coordinates (LBC, Zhang et al. 2014): the public front end.

The cage's interior is meshed (:mod:`torchcage.solvers.domain`), the weighted total variation of
the coordinate functions is minimised on that mesh by ADMM (:mod:`torchcage.solvers.lbc`), and the
values at the mesh vertices are interpolated linearly at the query points. Small entries are
dropped (the paper's ``10^-3 / V``) and each row is corrected on its support so that partition of
unity and reproduction still hold: the result is a sparse ``(N, V)`` tensor.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import torch

from torchcage._core.common import as_inputs, check_points, records_graph
from torchcage.cage import Cage
from torchcage.errors import PointsError
from torchcage.families.harmonic.api import check_mesh_solution, refuse_options_with_solution
from torchcage.solvers.domain import Domain, domain_for
from torchcage.solvers.lbc import LBCResult, make_feasible, solve_lbc
from torchcage.solvers.locate import locate_points, outside_points

__all__ = ["local_barycentric_coordinates", "locality_statistics", "locate", "solve_local_barycentric"]


def solve_local_barycentric(
    cage: Cage,
    *,
    target_cells: int = 4000,
    domain: tuple[torch.Tensor, torch.Tensor] | Domain | None = None,
    weighting: str = "quadratic",
    progress: bool | Callable[[int, float, float], None] = False,
    **solver: Any,
) -> LBCResult:
    """Mesh the cage's interior and solve for local barycentric coordinates at the mesh vertices.

    Args:
        cage: a closed 2D polygon or 3D triquad cage (quads get bilinear boundary values).
        target_cells: about how many triangles / tetrahedra to mesh the interior with.
        domain: your own mesh instead, ``(vertices (Nv, D), cells (C, D + 1))`` whose boundary
            vertices lie on the cage (triangle cages and polygons), or a :class:`Domain`.
        weighting: ``"quadratic"`` (default, the paper's), ``"linear"``, ``"sqrt"`` or
            ``"constant"`` (plain total variation): ``tau`` in ``phi_i = tau(D_i)``.
        progress: ``True`` for a progress bar with the residuals.
        **solver: options of :func:`torchcage.solvers.lbc.solve_lbc` (``max_iter``,
            ``eps_primal``, ``eps_dual``, ``mu``, ``alpha``, ``linear_solver``, ...).

    Returns:
        The :class:`~torchcage.solvers.lbc.LBCResult` (weights at the mesh vertices, iterations,
        residuals, convergence, objective).
    """
    dom = domain_for(cage, target_cells, domain, "local barycentric coordinates")
    return solve_lbc(dom, cage.vertices, weighting=weighting, progress=progress, **solver)


def locate(points: torch.Tensor, domain: Domain) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Cells holding points and the points' barycentric coordinates in them.

    Exact (:class:`torchcage.solvers.locate.MeshLocator`: a grid of the cells' bounding boxes,
    built once per domain): a point inside a cell is found, however long and thin the cell;
    points in no cell get the cell and clamped coordinates of the nearest point of the mesh.

    Args:
        points: ``(N, D)`` float64.
        domain: the mesh.

    Returns:
        ``cell (N,)``, ``bary (N, D + 1)`` and ``inside (N,)`` (False where clamped).
    """
    cell, bary, inside, _ = locate_points(points, domain)
    return cell, bary, inside


def local_barycentric_coordinates(
    points: torch.Tensor,
    cage: Cage,
    *,
    threshold: float | None = None,
    solution: LBCResult | None = None,
    chunk_size: int = 1 << 16,
    **options: Any,
) -> torch.Tensor:
    """Local barycentric coordinates of points inside a cage, as a sparse ``(N, V)`` tensor.

    Non-negative, local (each point depends on a few cage vertices), reproduce linear functions
    and sum to one; linear on the cage's triangles and edges, bilinear on its quads. Computing
    them means meshing the cage's interior and an iterative solve (seconds): pass ``solution=``
    (from :func:`solve_local_barycentric`) to reuse one for more points.

    Args:
        points: ``(N, D)`` points inside the cage (points outside get the coordinates of a nearby
            point of the meshed interior, with a warning).
        cage: a closed 2D polygon or 3D triquad cage.
        threshold: entries below it are dropped and rows corrected to keep reproduction and
            partition of unity. Default ``1e-3 / V`` (the paper's); ``0`` keeps every entry.
        solution: a previous solve for the same cage (checked: a solution of another cage, by
            dimension, vertex count, faces or rest vertices, raises a ``CageError``).
        chunk_size: points per chunk.
        **options: passed to :func:`solve_local_barycentric` (``target_cells``, ``domain``,
            ``weighting``, ``progress``, solver options).

    Returns:
        A sparse COO tensor ``(N, V)`` in the points' dtype.

    Examples:
        >>> import torch, torchcage
        >>> from torchcage import functional as F
        >>> square = torchcage.Cage(torch.tensor([[0.0, 0], [2, 0], [2, 1], [1, 1.5], [0, 1]], dtype=torch.float64))
        >>> x = torch.tensor([[0.5, 0.5], [1.5, 0.7]], dtype=torch.float64)
        >>> w = F.local_barycentric_coordinates(x, square, target_cells=300).to_dense()
        >>> bool((w >= 0).all()), torch.allclose(w @ square.vertices, x), torch.allclose(w.sum(1), 1 + 0 * w[:, 0])
        (True, True, True)
    """
    points, cage = as_inputs(points, cage)
    if records_graph(points, cage.vertices):
        raise PointsError(
            "local_barycentric_coordinates is not differentiable with respect to the points or the cage's vertices "
            "(sparse, thresholded weights of an iterative solve), and takes no torch.func transform; pass detached "
            "points and cage, or use harmonic_coordinates, which differentiate with respect to the points"
        )
    if points.ndim > 2 and not cage.is_batched:  # (a batch of cages: check_points names that first)
        raise PointsError(
            f"local_barycentric_coordinates returns a sparse (N, V) matrix: give points (N, {cage.dim}), e.g. "
            f"points.reshape(-1, {cage.dim}), got shape {tuple(points.shape)}"
        )
    flat = check_points(points, cage)
    V = cage.num_vertices
    if solution is not None:
        refuse_options_with_solution(options, "local_barycentric_coordinates")
        check_mesh_solution(solution, cage, "local barycentric coordinates")
    result = solution if solution is not None else solve_local_barycentric(cage, **options)
    thr = 1e-3 / V if threshold is None else float(threshold)
    if thr < 0:
        raise ValueError(f"threshold must be >= 0, got {threshold}")
    x = flat.detach().to(torch.float64).cpu()
    # (the constraints in coordinates centred on the cage and scaled by its size: the same rows,
    # better conditioned; in raw coordinates of size 100 the correction left the sums off by 1e-10)
    P = cage.vertices.to(torch.float64).cpu()
    centre, scale = P.mean(dim=0), max(cage.scale, 1e-300)
    K = torch.cat([(P - centre) / scale, torch.ones(V, 1, dtype=torch.float64)], 1)
    rows, cols, vals = [], [], []
    outside, farthest = 0, 0.0
    for s in range(0, x.shape[0], chunk_size):
        xc = x[s : s + chunk_size]
        cell, bary, inside, distance = locate_points(xc, result.domain)
        warn = outside_points(xc, inside, distance, result.domain, cage, flat.dtype)
        if bool(warn.any()):
            outside += int(warn.sum())
            farthest = max(farthest, float(distance[warn].max()))
        corners = result.domain.cells[cell]  # (n, D+1)
        w = torch.einsum("nk,nkv->nv", bary, result.weights[corners])
        if thr > 0:
            # the interpolated position of clamped points is their nearest mesh point
            target = torch.einsum("nk,nkd->nd", bary, result.domain.vertices[corners])
            B = torch.cat([(target - centre) / scale, torch.ones(xc.shape[0], 1, dtype=torch.float64)], 1)
            cut = make_feasible(w * (w >= thr), K, B)
            # rows whose remaining support cannot reproduce the point keep every entry
            bad = ((cut @ K - B).abs().amax(dim=1) > 1e-12 * (1 + B.abs().amax(dim=1))) | (cut.amin(dim=1) < 0)
            w = torch.where(bad[:, None], w, cut)
            # the correction leaves the sums off by up to 2e-12: restore the partition of unity
            # exactly (it moves the reproduced point by the same relative amount)
            total = w.sum(dim=1, keepdim=True)
            w = torch.where(total > 0, w / torch.where(total > 0, total, 1.0), w)
        r, c = torch.nonzero(w > 0, as_tuple=True)
        rows.append(r + s)
        cols.append(c)
        vals.append(w[r, c])
    if outside:
        warnings.warn(
            f"{outside} points lie outside the meshed interior of the cage (up to {farthest:.3g} away, "
            f"{farthest / max(cage.scale, 1e-300):.2g} of its size); they got the coordinates of the nearest "
            "point of the mesh",
            stacklevel=2,
        )
    idx = torch.stack([torch.cat(rows), torch.cat(cols)]) if rows else torch.zeros((2, 0), dtype=torch.int64)
    val = torch.cat(vals) if vals else torch.zeros(0, dtype=torch.float64)
    out = torch.sparse_coo_tensor(idx, val, (x.shape[0], V), check_invariants=False).coalesce()
    if not bool(torch.isfinite(out.values()).all()):
        raise PointsError("local barycentric coordinates are not finite at some points")  # pragma: no cover
    return out.to(dtype=flat.dtype, device=flat.device)


def locality_statistics(
    weights: torch.Tensor, measure: torch.Tensor | None = None, ts: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The paper's locality statistics (Eqs. 19-21) of coordinates sampled at points.

    ``P(t)``: the mean over cage vertices of the fraction of the domain where ``|w_i| <= t``;
    ``Q(k)``: the fraction of the domain where at least ``k`` coordinates exceed ``10^-3 / V``.

    Args:
        weights: ``(N, V)`` coordinates (dense or sparse) at sample points.
        measure: ``(N,)`` the volume each point stands for (default: equal).
        ts: thresholds for ``P`` (default: 50 values from 1e-6 to 1, log-spaced).

    Returns:
        ``ts``, ``P (len(ts),)`` and ``Q (V + 1,)`` (``Q[k]`` for ``k = 0..V``).

    Examples:
        >>> import torch
        >>> w = torch.tensor([[1.0, 0.0, 0.0], [0.5, 0.5, 0.0]], dtype=torch.float64)
        >>> _, P, Q = locality_statistics(w, ts=torch.tensor([0.0, 0.6]))
        >>> P.round(decimals=6).tolist(), Q.tolist()
        ([0.5, 0.833333], [1.0, 1.0, 0.5, 0.0])
    """
    w = (weights.to_dense() if weights.layout != torch.strided else weights).abs()
    N, V = w.shape
    mu = torch.ones(N, dtype=w.dtype) if measure is None else measure.to(w.dtype)
    mu = mu / mu.sum()
    ts = torch.logspace(-6, 0, 50, dtype=w.dtype) if ts is None else ts.to(w.dtype)
    P = torch.stack([((w <= t).to(w.dtype) * mu[:, None]).sum(0).mean() for t in ts])
    count = (w > 1e-3 / V).sum(dim=1)
    Q = torch.stack([(mu * (count >= k).to(w.dtype)).sum() for k in range(V + 1)])
    return ts, P, Q
