r"""Newton's method on the dual of maximum entropy coordinates (Hormann & Sukumar 2008).

For a point ``x`` and positive prior masses ``m_i`` of the vertices ``v_i``, the maximum entropy
coordinates maximise ``-sum_i w_i log(w_i / m_i)`` subject to ``sum_i w_i = 1`` and
``sum_i w_i (v_i - x) = 0``. Their solution is ``w_i = m_i exp(mu . d_i) / Z(mu)`` with
``d_i = (v_i - x) / s`` (``s`` the cage size, so ``mu`` is of order one) and ``mu`` the minimiser
of the convex dual

.. math::
    F(\mu) = \log \sum_i m_i\, e^{\mu \cdot d_i},\qquad
    \nabla F = \sum_i w_i d_i,\qquad
    \nabla^2 F = \sum_i w_i d_i d_i^T - \nabla F\, \nabla F^T.

``grad F`` is the linear precision residual over the size, so Newton's method stops when it is
below ``tol``; a backtracking line search (Armijo) keeps every step a descent step, which makes it
converge from ``mu = 0`` for every point strictly inside the convex hull of the vertices (the
Hessian, the weights' covariance, is then positive definite). Near the solution the decrease of
``F`` falls below its rounding: a step that halves the gradient is accepted there.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

__all__ = ["MecSolution", "solve_mec"]

#: Armijo constant and the most halvings of a step.
_ARMIJO = 1e-4
_HALVINGS = 40


class MecSolution(NamedTuple):
    """Result of :func:`solve_mec` for ``n`` points."""

    weights: torch.Tensor  # (n, V) coordinates, >= 0, summing to 1
    iterations: torch.Tensor  # (n,) int64 Newton steps taken
    residual: torch.Tensor  # (n,) |sum_i w_i d_i|: linear precision over the size
    converged: torch.Tensor  # (n,) bool residual <= tol


def _dual(log_m: torch.Tensor, d: torch.Tensor, mu: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(F (n,), w (n, V))`` at ``mu`` ``(n, D)``."""
    z = log_m + torch.einsum("nvd,nd->nv", d, mu)
    F = torch.logsumexp(z, dim=1)
    return F, torch.exp(z - F[:, None])


def solve_mec(log_m: torch.Tensor, d: torch.Tensor, tol: float = 1e-13, max_iter: int = 50) -> MecSolution:
    """Maximum entropy coordinates of ``n`` points by Newton's method on the dual, batched.

    Args:
        log_m: ``(n, V)`` logs of the prior masses (``-inf`` for a vertex with no mass).
        d: ``(n, V, D)`` vertices minus the point, over the cage size.
        tol: stop when ``|sum_i w_i d_i|`` (linear precision over the size) is at most this.
        max_iter: most Newton steps.

    Returns:
        :class:`MecSolution`. Points still above ``tol`` after ``max_iter`` steps (a point on the
        hull of the vertices, masses that leave it outside the hull of the massive vertices) are
        flagged ``converged = False``; their weights are the last iterate's.

    Examples:
        >>> v = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], dtype=torch.float64)
        >>> x = torch.tensor([[0.25, 0.5]], dtype=torch.float64)
        >>> sol = solve_mec(torch.zeros(1, 4, dtype=torch.float64), v[None] - x[:, None])
        >>> [round(w, 6) for w in sol.weights[0].tolist()]  # uniform prior on a square: bilinear
        [0.375, 0.125, 0.375, 0.125]
    """
    n, _, D = d.shape
    mu = torch.zeros(n, D, dtype=d.dtype, device=d.device)
    iters = torch.zeros(n, dtype=torch.long, device=d.device)
    F, w = _dual(log_m, d, mu)
    g = torch.einsum("nv,nvd->nd", w, d)
    res = g.norm(dim=1)
    eye = torch.eye(D, dtype=d.dtype, device=d.device)
    stuck = torch.zeros(n, dtype=torch.bool, device=d.device)  # no descent left: rounding-level steps
    for _ in range(max_iter):
        active = torch.nonzero((res > tol) & ~stuck).flatten()
        if active.numel() == 0:
            break
        wa, da, ga, ma, Fa, lm = w[active], d[active], g[active], mu[active], F[active], log_m[active]
        H = torch.einsum("nv,nvi,nvj->nij", wa, da, da) - ga[:, :, None] * ga[:, None, :]
        # (a tiny ridge keeps the solve finite where the covariance is singular to rounding)
        scale = H.diagonal(dim1=1, dim2=2).sum(-1).clamp_min(torch.finfo(d.dtype).tiny)
        H = H + (1e-15 * scale)[:, None, None] * eye
        step = -torch.linalg.solve(H, ga[..., None])[..., 0]
        slope = (ga * step).sum(-1)  # < 0: a descent direction
        alpha = torch.ones_like(slope)
        todo = torch.ones_like(slope, dtype=torch.bool)
        Fn, wn = Fa.clone(), wa.clone()
        for _ in range(_HALVINGS):
            idx = torch.nonzero(todo).flatten()
            if idx.numel() == 0:
                break
            Ft, wt = _dual(lm[idx], da[idx], ma[idx] + alpha[idx, None] * step[idx])
            # Armijo's decrease, or (near the solution, where the decrease is below the rounding of
            # F) the gradient halved
            gt = torch.einsum("nv,nvd->nd", wt, da[idx]).norm(dim=1)
            ok = (Ft <= Fa[idx] + _ARMIJO * alpha[idx] * slope[idx]) | (gt <= 0.5 * ga[idx].norm(dim=1))
            good = idx[ok]
            Fn[good], wn[good] = Ft[ok], wt[ok]
            todo[good] = False
            alpha[idx[~ok]] *= 0.5
        moved = ~todo  # (rows whose line search failed keep their iterate and stop)
        ma = torch.where(moved[:, None], ma + alpha[:, None] * step, ma)
        mu[active], F[active], w[active] = ma, torch.where(moved, Fn, Fa), torch.where(moved[:, None], wn, wa)
        g[active] = torch.einsum("nv,nvd->nd", w[active], da)
        res[active] = g[active].norm(dim=1)
        iters[active[moved]] += 1
        stuck[active[~moved]] = True
    return MecSolution(w, iters, res, res <= tol)
