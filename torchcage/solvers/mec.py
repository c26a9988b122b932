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
    z = log_m + torch.bmm(d, mu[:, :, None])[..., 0]
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
    g = torch.bmm(w[:, None, :], d)[:, 0]
    res = g.norm(dim=1)
    stuck = torch.zeros(n, dtype=torch.bool, device=d.device)  # no descent left: rounding-level steps
    for _ in range(max_iter):
        active = (res > tol) & ~stuck
        count = int(active.sum())
        if count == 0:
            break
        if 4 * count >= n:  # most rows still move: full tensors (gathers cost more than the spare rows)
            rows = None
            parts = (log_m, d, mu, F, w, g)
        else:
            rows = torch.nonzero(active).flatten()
            parts = tuple(t.index_select(0, rows) for t in (log_m, d, mu, F, w, g))
        mu_n, F_n, w_n, g_n, moved = _newton_step(*parts)
        if rows is None:
            moved = moved & active
            mu = torch.where(moved[:, None], mu_n, mu)
            F = torch.where(moved, F_n, F)
            w = torch.where(moved[:, None], w_n, w)
            g = torch.where(moved[:, None], g_n, g)
            iters += moved.long()
            stuck |= active & ~moved
        else:
            keep = rows[moved]
            mu[keep], F[keep], w[keep], g[keep] = mu_n[moved], F_n[moved], w_n[moved], g_n[moved]
            iters[keep] += 1
            stuck[rows[~moved]] = True
        res = g.norm(dim=1)
    return MecSolution(w, iters, res, res <= tol)


def _newton_step(log_m, d, mu, F, w, g) -> tuple[torch.Tensor, ...]:
    """One damped Newton step of every row: ``(mu, F, w, g, moved)`` after it (``moved`` False where
    the line search found no acceptable step; those rows' other outputs are their inputs)."""
    D = d.shape[-1]
    H = torch.bmm((d * w[..., None]).transpose(1, 2), d) - g[:, :, None] * g[:, None, :]
    # (a tiny ridge keeps the solve finite where the covariance is singular to rounding)
    scale = H.diagonal(dim1=1, dim2=2).sum(-1).clamp_min(torch.finfo(d.dtype).tiny)
    H = H + (1e-15 * scale)[:, None, None] * torch.eye(D, dtype=d.dtype, device=d.device)
    step = -torch.linalg.solve(H, g[..., None])[..., 0]
    slope = (g * step).sum(-1)  # < 0: a descent direction
    gnorm = g.norm(dim=1)

    def accept(Ft, gt, alpha, Fa, slope_, gn):
        # Armijo's decrease, or (near the solution, where the decrease is below the rounding of F)
        # the gradient halved
        return (Ft <= Fa + _ARMIJO * alpha * slope_) | (gt.norm(dim=1) <= 0.5 * gn)

    Ft, wt = _dual(log_m, d, mu + step)
    gt = torch.bmm(wt[:, None, :], d)[:, 0]
    ok = accept(Ft, gt, 1.0, F, slope, gnorm)
    mu_n, F_n, w_n, g_n = mu + step, Ft, wt, gt
    todo = torch.nonzero(~ok).flatten()
    alpha = torch.full((todo.numel(),), 0.5, dtype=d.dtype, device=d.device)
    for _ in range(_HALVINGS):  # (few rows: gathered)
        if todo.numel() == 0:
            break
        lm, dd, m0, st = log_m[todo], d[todo], mu[todo], step[todo]
        Fs, ws = _dual(lm, dd, m0 + alpha[:, None] * st)
        gs = torch.bmm(ws[:, None, :], dd)[:, 0]
        good = accept(Fs, gs, alpha, F[todo], slope[todo], gnorm[todo])
        hit = todo[good]
        mu_n[hit], F_n[hit], w_n[hit], g_n[hit] = (m0 + alpha[:, None] * st)[good], Fs[good], ws[good], gs[good]
        ok[hit] = True
        todo, alpha = todo[~good], alpha[~good] * 0.5
    mu_n = torch.where(ok[:, None], mu_n, mu)
    F_n = torch.where(ok, F_n, F)
    w_n = torch.where(ok[:, None], w_n, w)
    g_n = torch.where(ok[:, None], g_n, g)
    return mu_n, F_n, w_n, g_n, ok
