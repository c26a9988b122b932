r"""Maximum entropy coordinates (Hormann & Sukumar 2008): positive coordinates from a prior.

Among all coordinates of a point (partition of unity and linear precision), the ones closest to
prior masses ``m_i`` in relative entropy, ``max -sum w_i log(w_i / m_i)``: nonnegative, smooth
where the prior is, and equal to the prior wherever the prior is itself a set of positive
coordinates. With mean value (or quad mean value) coordinates as the prior, whose negative entries
are set to a small positive floor, they keep the coordinates' behaviour and lose their negative
weights, the post-process of Thiery et al. (2018, Fig. 17). The solver is Newton's method on the
three-unknown dual (:mod:`torchcage.solvers.mec`).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import NamedTuple

import torch

from torchcage._core.common import as_inputs, check_points, chunks, has_tangent, on_cage_tolerance, result_dtype
from torchcage.cage import Cage
from torchcage.errors import CageError, PointsError
from torchcage.families.mean_value.api import mean_value_coordinates
from torchcage.families.quad_mean_value.api import quad_mean_value_coordinates
from torchcage.geometry import inside_cage, near_cage
from torchcage.solvers.mec import solve_mec

__all__ = ["MaximumEntropyResult", "maximum_entropy_coordinates"]

#: Negative and zero prior coordinates become this fraction of the point's largest one: every vertex
#: keeps a positive mass, so the dual has a solution at every point inside the cage.
PRIOR_FLOOR = 1e-6


class MaximumEntropyResult(NamedTuple):
    """What :func:`maximum_entropy_coordinates` returns with ``return_info=True``."""

    weights: torch.Tensor  # (*, V)
    iterations: torch.Tensor  # (*,) Newton steps (0 on the cage and where the prior was already exact)
    residual: torch.Tensor  # (*,) linear precision |sum w_i v_i - x| over the cage size
    converged: torch.Tensor  # (*,) bool


def _prior(x: torch.Tensor, cage: Cage, prior: str, n: int) -> torch.Tensor:
    if prior == "uniform":
        return torch.ones(x.shape[0], cage.num_vertices, dtype=x.dtype, device=x.device)
    if prior == "qmvc":
        if cage.dim != 3:
            raise CageError("the 'qmvc' prior needs a 3D cage; use prior='mvc' or 'uniform' for polygons")
        return quad_mean_value_coordinates(x, cage, n, dtype=x.dtype)
    if prior == "mvc":
        return mean_value_coordinates(x, cage.triangulated() if cage.has_quads else cage, dtype=x.dtype)
    raise ValueError(f"prior must be 'mvc', 'qmvc', 'uniform' or a tensor of masses (N, V), got {prior!r}")


def _interpolant(x: torch.Tensor, cage: Cage, n: int) -> torch.Tensor:
    """The cage's interpolant at points on it: barycentric on triangles, bilinear on quads."""
    if cage.dim == 3 and cage.has_quads:
        return quad_mean_value_coordinates(x, cage, n, dtype=x.dtype)
    return mean_value_coordinates(x, cage, dtype=x.dtype)


def _sheet_points(x: torch.Tensor, q: torch.Tensor, steps: int = 8) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The nearest points of bilinear sheets to points: ``x`` ``(k, 3)``, the sheets' corners ``q``
    ``(k, 4, 3)`` (``q0 q1 q2 q3`` around). A 7x7 grid picks a start, Gauss-Newton refines it within
    ``[0, 1]^2``. Returns ``(u, v, offset)``: the parameters ``(k,)`` and ``x - xi(u, v)`` ``(k, 3)``."""
    t = torch.linspace(0.0, 1.0, 7, dtype=x.dtype, device=x.device)
    gu, gv = torch.meshgrid(t, t, indexing="ij")
    gu, gv = gu.reshape(-1), gv.reshape(-1)

    def sheet(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        u, v = u[..., None], v[..., None]
        return (1 - u) * (1 - v) * q[:, 0] + u * (1 - v) * q[:, 1] + u * v * q[:, 2] + (1 - u) * v * q[:, 3]

    grid = sheet(gu[None].expand(x.shape[0], -1).T, gv[None].expand(x.shape[0], -1).T)  # (49, k, 3)
    best = (grid - x[None]).square().sum(-1).argmin(dim=0)
    u, v = gu[best], gv[best]
    for _ in range(steps):
        r = x - sheet(u, v)
        xu = (1 - v)[:, None] * (q[:, 1] - q[:, 0]) + v[:, None] * (q[:, 2] - q[:, 3])
        xv = (1 - u)[:, None] * (q[:, 3] - q[:, 0]) + u[:, None] * (q[:, 2] - q[:, 1])
        a, b, d = (xu * xu).sum(-1), (xu * xv).sum(-1), (xv * xv).sum(-1)
        ru, rv = (xu * r).sum(-1), (xv * r).sum(-1)
        det = a * d - b * b
        ok = det > 0
        det = torch.where(ok, det, 1.0)
        u = (u + torch.where(ok, (d * ru - b * rv) / det, 0.0)).clamp(0.0, 1.0)
        v = (v + torch.where(ok, (a * rv - b * ru) / det, 0.0)).clamp(0.0, 1.0)
    return u, v, x - sheet(u, v)


def _quad_contacts(
    x: torch.Tensor, cage: Cage, tol: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Points ``x`` ``(N, 3)`` against the cage's bilinear quads (not their split triangles).

    Returns:
        ``(on, inner, quad, uv)``: ``on`` ``(N,)`` the points within ``tol`` of a quad's sheet,
        ``inner`` ``(N,)`` those on a sheet's inner side within its bend (the gap between the sheet
        and its split triangles, where the split triangles' winding number says "outside"), and for
        the ``on`` points the quad ``(N,)`` and its parameters ``uv`` ``(N, 2)`` (the bilinear
        weights' arguments).
    """
    N = x.shape[0]
    on = torch.zeros(N, dtype=torch.bool, device=x.device)
    inner = torch.zeros_like(on)
    quad = torch.zeros(N, dtype=torch.long, device=x.device)
    uv = x.new_zeros(N, 2)
    if cage.dim != 3 or not cage.has_quads or N == 0:
        return on, inner, quad, uv
    q = cage.vertices.to(x.dtype)[cage.quads]  # (Q, 4, 3)
    bend = ((q[:, 0] - q[:, 1] + q[:, 2] - q[:, 3]).norm(dim=-1) / 4)[:, None]  # sheet-to-split gap bound
    reach = bend + tol
    lo, hi = q.amin(dim=1) - reach, q.amax(dim=1) + reach
    best = torch.full((N,), float("inf"), dtype=x.dtype, device=x.device)
    rows = max(1, (1 << 20) // max(1, q.shape[0]))
    for s in range(0, N, rows):
        xs = x[s : s + rows]
        pi, qi = torch.nonzero(((xs[:, None] >= lo[None]) & (xs[:, None] <= hi[None])).all(-1), as_tuple=True)
        if pi.numel() == 0:
            continue
        u, v, off = _sheet_points(xs[pi], q[qi])
        dist = off.norm(dim=-1)
        pi = pi + s
        # nearest sheet per point
        order = torch.argsort(dist, descending=True)  # (the last write wins: the nearest)
        pi_o, qi_o, d_o = pi[order], qi[order], dist[order]
        hit = d_o <= tol
        upd = hit & (d_o < best[pi_o])
        best[pi_o[upd]] = d_o[upd]
        on[pi_o[hit]] = True
        quad[pi_o[upd]] = qi_o[upd]
        uv[pi_o[upd]] = torch.stack([u[order][upd], v[order][upd]], dim=1)
        # inner side of the sheet (outward normal xu x xv), parameters interior, within the bend
        uu, vv = u[order], v[order]
        qq = q[qi_o]
        xu = (1 - vv)[:, None] * (qq[:, 1] - qq[:, 0]) + vv[:, None] * (qq[:, 2] - qq[:, 3])
        xv = (1 - uu)[:, None] * (qq[:, 3] - qq[:, 0]) + uu[:, None] * (qq[:, 2] - qq[:, 1])
        side = (off[order] * torch.linalg.cross(xu, xv, dim=-1)).sum(-1)
        interior = (uu > 0) & (uu < 1) & (vv > 0) & (vv < 1)
        inner[pi_o[interior & (side < 0) & (d_o <= bend[qi_o, 0] + tol)]] = True
    return on, inner, quad, uv


def maximum_entropy_coordinates(
    points: torch.Tensor,
    cage: Cage,
    prior: str | torch.Tensor | None = None,
    *,
    n: int = 4,
    tol: float = 1e-13,
    max_iter: int = 50,
    chunk_size: int | None = None,
    dtype: torch.dtype | None = None,
    progress: bool | Callable[[int, int], None] = False,
    return_info: bool = False,
) -> torch.Tensor | MaximumEntropyResult:
    """Maximum entropy coordinates of points inside a cage.

    Args:
        points: ``(*, D)`` points inside the cage (or on it).
        cage: a closed 2D polygon or 3D cage of triangles and/or quads.
        prior: the prior masses: ``"mvc"`` (mean value coordinates; default for triangle cages and
            polygons), ``"qmvc"`` (quad mean value coordinates with grid ``n``; default for cages with
            quads), ``"uniform"`` (equal masses: the classical maximum entropy coordinates), or a
            tensor ``(*, V)`` of masses (coordinates computed before, for instance). Negative and
            zero entries are raised to
            ``PRIOR_FLOOR`` times the point's largest one (positive ones are kept as they are, so
            where the prior is a set of positive coordinates the result equals it).
        n: grid parameter of the ``"qmvc"`` prior.
        tol: Newton stops when the linear precision residual is at most ``tol`` times the cage size.
        max_iter: most Newton steps per point.
        chunk_size: points per chunk (memory: about ``chunk_size * V * 8`` doubles).
        dtype: dtype of the result (computed in float64).
        progress: a progress bar over the chunks, or a callable ``(done, total)``.
        return_info: also return the Newton steps, residuals and convergence flags.

    Returns:
        ``(*, V)`` coordinates: nonnegative, summing to 1, reproducing the points to ``tol`` of the
        cage size; or a :class:`MaximumEntropyResult`. Points on the cage (within the on-cage
        tolerance, or the rounding of the inputs' dtype: ``8 eps (|x|_max + size)``; quads are
        their bilinear sheets, not their split triangles) get the cage's interpolant (barycentric
        on triangles, bilinear on quads), the limit of the coordinates there. Points between a
        quad's sheet and its split triangles on the sheet's inner side are inside. The result
        carries no gradient (a constant of the rest cage, as in the coordinate modules).

    Raises:
        PointsError: points outside the cage (the coordinates exist only inside the convex hull of
            the vertices, and the priors only inside the cage), or points or a cage that require
            grad.
        CageError: a ``"qmvc"`` prior on a polygon.

    Warns:
        RuntimeWarning: points where Newton's method did not reach ``tol`` (with their count and
            worst residual); their coordinates are the last iterate's.

    Examples:
        >>> import torch, torchcage
        >>> from torchcage.functional import maximum_entropy_coordinates
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))  # [-1, 1]^3, 6 quads
        >>> x = torch.tensor([[0.5, -0.5, 0.0]], dtype=torch.float64)
        >>> w = maximum_entropy_coordinates(x, cube, prior="uniform")  # a box: trilinear weights
        >>> sorted(round(v, 6) for v in w[0].tolist())
        [0.03125, 0.03125, 0.09375, 0.09375, 0.09375, 0.09375, 0.28125, 0.28125]
    """
    points, cage = as_inputs(points, cage)
    if points.requires_grad or cage.vertices.requires_grad or has_tangent(points) or has_tangent(cage.vertices):
        raise PointsError(
            "maximum_entropy_coordinates is not differentiable (Newton's method on the dual); pass detached "
            "points and cage, and deform with the coordinates as constants (torchcage.MaximumEntropyCoordinates)"
        )
    lead = points.shape[:-1]
    flat = check_points(points, cage)
    compute, out_dtype = result_dtype(flat, cage, dtype)
    x = flat.to(compute)
    cage_c = cage.to(compute)
    V = cage.num_vertices
    masses = None
    if isinstance(prior, torch.Tensor):
        masses = prior.detach().to(compute).reshape(-1, V) if prior.shape[-1] == V else None
        if masses is None or masses.shape[0] != x.shape[0]:
            raise PointsError(f"prior masses must have shape (*, {V}) matching the points, got {tuple(prior.shape)}")
        if not bool(torch.isfinite(masses).all()):
            raise PointsError("prior masses must be finite")
    elif prior is None:
        prior = "qmvc" if cage.dim == 3 and cage.has_quads else "mvc"
    elif prior not in ("mvc", "qmvc", "uniform"):
        raise ValueError(f"prior must be 'mvc', 'qmvc', 'uniform' or a tensor of masses (N, V), got {prior!r}")

    # on the cage within the rounding of the inputs' dtype (a float32 point on a face rounds off it)
    eps_in = max(torch.finfo(flat.dtype).eps, torch.finfo(cage.dtype).eps)
    extent = max(float(cage_c.vertices.abs().max()), float(x.abs().max()) if x.numel() else 0.0)
    tol_on = max(on_cage_tolerance(cage_c), 8 * eps_in * (extent + cage_c.scale))
    on_quad, inner, quad, uv = _quad_contacts(x, cage_c, tol_on)  # (the bilinear sheets themselves)
    on = near_cage(x, cage_c, tol_on)
    if cage_c.has_quads:  # near a split triangle of a quad is not near its sheet
        on = near_cage(x, Cage._from_faces(cage_c.vertices, cage_c.triangles), tol_on) | on_quad
    inside = inside_cage(x, cage_c) | on | inner
    if not bool(inside.all()):
        bad = torch.nonzero(~inside).flatten()
        raise PointsError(
            f"{bad.numel()} of {x.shape[0]} points lie outside the cage (e.g. rows {bad[:5].tolist()}); maximum "
            "entropy coordinates exist only inside it: drop those points, enlarge the cage, or use "
            "mean_value_coordinates or green_coordinates (exterior='extend') for them"
        )
    size = cage_c.scale
    W = torch.empty(x.shape[0], V, dtype=compute, device=x.device)
    iters = torch.zeros(x.shape[0], dtype=torch.long, device=x.device)
    res = torch.zeros(x.shape[0], dtype=compute, device=x.device)
    step = chunk_size or max(1, (1 << 22) // max(1, V))
    for sl in chunks(x.shape[0], step, progress, desc="Maximum entropy coordinates"):
        xc, onc = x[sl], on[sl]
        m = masses[sl] if masses is not None else _prior(xc, cage_c, prior, n)
        m = m.clamp_min(0.0)
        m = torch.where(m > 0, m, PRIOR_FLOOR * m.amax(dim=1, keepdim=True))
        m = torch.where(m > 0, m, 1.0)  # (a row of zero masses: uniform)
        d = (cage_c.vertices[None] - xc[:, None, :]) / size
        sol = solve_mec(m.log(), d, tol, max_iter)
        w, it, r = sol.weights, sol.iterations, sol.residual
        if bool(onc.any()):
            rows = torch.nonzero(onc).flatten()
            wi = _interpolant(xc[rows], cage_c, n).to(compute)
            # (points within the inputs' rounding of a face, off it: the interpolant's limit, whose
            # entries beyond the face are of the order of that rounding; kept nonnegative)
            wi = wi.clamp_min(0.0)
            w = w.index_copy(0, rows, wi / wi.sum(dim=1, keepdim=True))
            qr = torch.nonzero(on_quad[sl]).flatten()
            if qr.numel():  # on a bilinear quad: its bilinear weights
                u, v = uv[sl][qr, 0:1], uv[sl][qr, 1:2]
                b = torch.cat([(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v], dim=1)
                wq = torch.zeros(qr.numel(), V, dtype=compute, device=x.device)
                wq = wq.scatter_add(1, cage_c.quads[quad[sl][qr]], b)
                w = w.index_copy(0, qr, wq)
            it = it.index_fill(0, rows, 0)
            r = r.index_fill(0, rows, 0.0)
        W[sl], iters[sl], res[sl] = w, it, r
    converged = res <= tol
    if not bool(converged.all()):
        warnings.warn(
            f"maximum entropy coordinates: Newton's method did not reach tol={tol:g} at {int((~converged).sum())} "
            f"of {x.shape[0]} points (worst residual {float(res.max()):.2e} of the size; raise max_iter, or check "
            "for points on the cage's boundary)",
            RuntimeWarning,
            stacklevel=2,
        )
    out = W.to(out_dtype).reshape(*lead, V)
    if return_info:
        return MaximumEntropyResult(out, iters.reshape(lead), res.reshape(lead), converged.reshape(lead))
    return out
