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

from ..cage import Cage
from ..errors import CageError, PointsError
from ..geometry import inside_cage, near_cage
from ..solvers.mec import solve_mec
from ._common import as_inputs, check_points, chunks, on_cage_tolerance, result_dtype
from .mean_value import mean_value_coordinates
from .quad_mean_value import quad_mean_value_coordinates

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
        tolerance) get the cage's interpolant (barycentric on triangles, bilinear on quads), the
        limit of the coordinates there. The result carries no gradient (a constant of the rest
        cage, as in the coordinate modules).

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
    if points.requires_grad or cage.vertices.requires_grad:
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

    tol_on = on_cage_tolerance(cage_c)
    on = near_cage(x, cage_c, tol_on)
    inside = inside_cage(x, cage_c) | on
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
            w = w.index_copy(0, rows, _interpolant(xc[rows], cage_c, n).to(compute))
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
