r"""Local barycentric coordinates (Zhang, Deng, Hormann, Zheng 2014): weighted total variation of
the coordinate functions on a simplicial mesh of the cage's interior, minimised by ADMM with torch
(sparse) tensor operations.

The discrete problem (the paper's Eq. 15) is

.. math::
    \min_W \sum_s \sum_i \phi_i^s A_s \|G_s W_i + e_i^s\| \quad \text{s.t.}\quad WK = B,\; W \ge 0,

over the values ``W (m, V)`` at the ``m`` interior mesh vertices. Writing ``W = Y M + H`` (rows of
``M`` an orthonormal basis of the null space of ``K^T``, ``H`` the least-norm solution of
``H K = B``, both from the SVD of ``K``) makes reproduction and partition of unity exact by
construction. ADMM (Appendix B) alternates group soft-thresholding of the gradient variables,
projection onto ``W >= 0``, over-relaxation, and the ``Y`` step, an SPD solve with the fixed matrix
``G^T G + I`` for all right-hand sides at once (a sparse LU factorisation computed once, or a
warm-started Jacobi-preconditioned conjugate gradient). With the native library (CPU), the whole
iteration runs in C (``torchcage/backends/native/lbc.c``): the same steps fused into three passes
over memory, and the ``Y`` step as forward and back substitution over all right-hand sides at once;
its iterates equal the torch loop's to rounding (``TORCHCAGE_NATIVE=0`` selects the torch loop).

**Adaptive penalty.** The ``Y`` step's matrix does not depend on the penalty ``mu``, so residual
balancing (Boyd et al. 2011, 3.4.1) is free: every ``balance_every`` iterations, ``mu`` is doubled
when the primal residual is more than ten times further from its tolerance than the dual one, and
halved in the opposite case (the scaled multipliers are rescaled to match). With the paper's fixed
``mu = 10`` 3D problems need tens of thousands of iterations; balancing cuts that by an order of
magnitude (see the benchmarks).

**Weighting.** ``phi_i = tau(D_i)`` with ``D_i`` the geodesic distance to cage vertex ``i`` inside the
domain, normalised to ``[0, 1]``. torchcage uses shortest paths along the mesh's edges (exact on the
mesh graph, a few percent above the true geodesic distance); the weighting only needs a monotone,
domain-aware distance, and this one needs no extra solve.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from torchcage.errors import CageError
from torchcage.solvers.domain import Domain

__all__ = ["TAU", "LBCResult", "geodesic_distances", "gradient_operator", "make_feasible", "project_rows", "solve_lbc"]

#: The weighting functions tau of the paper's Eq. 11.
TAU: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "quadratic": lambda x: x * x,
    "linear": lambda x: x,
    "sqrt": torch.sqrt,
    "constant": torch.ones_like,
}


@dataclass
class LBCResult:
    """Outcome of an LBC solve.

    Attributes:
        domain: the mesh the coordinates live on.
        weights: ``(Nv, V)`` coordinates at every mesh vertex (boundary values included),
            reproduction and partition of unity exact to rounding, non-negative.
        iterations: ADMM iterations run.
        primal_residual: ``||r_p||_F`` at the end (Eq. 26), and ``primal_tolerance`` its threshold.
        dual_residual: ``||r_d||_F`` at the end (Eq. 27), and ``dual_tolerance`` its threshold.
        converged: both residuals below their thresholds.
        objective: the weighted total variation of ``weights`` (Eq. 14, in the cage's units).
        mu: the final penalty.
        history: ``(iteration, primal, dual, mu)`` every ``report_every`` iterations.
    """

    domain: Domain
    weights: torch.Tensor
    iterations: int
    primal_residual: float
    dual_residual: float
    primal_tolerance: float
    dual_tolerance: float
    converged: bool
    objective: float
    mu: float
    history: list[tuple[int, float, float, float]] = field(default_factory=list)


def _csr(t: torch.Tensor) -> torch.Tensor:
    """``t`` in CSR layout (torch's "beta" warning about CSR silenced: the operations used here work)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return t.to_sparse_csr()


def gradient_operator(vertices: torch.Tensor, cells: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Cell gradients of piecewise-linear functions: ``G (D C, Nv)`` sparse CSR with
    ``(G f)[C d + s] = d f / d x_d`` on cell ``s`` (component-major, so that ``(G f).reshape(D, C)``
    holds the gradients' components), and the cell volumes ``(C,)``.

    Examples:
        >>> import torch
        >>> v = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
        >>> G, vol = gradient_operator(v, torch.tensor([[0, 1, 2]]))
        >>> (G @ (2 * v[:, :1] + 3 * v[:, 1:])).flatten().tolist(), vol.tolist()    # d/dx, d/dy
        ([2.0, 3.0], [0.5])
    """
    C, k = cells.shape
    D = k - 1
    p = vertices[cells]  # (C, D+1, D)
    E = p[:, 1:] - p[:, :1]  # (C, D, D) rows: edge vectors
    inv = torch.linalg.inv(E)  # (C, D, D): grad of barycentric k+1 is column k of inv
    grads = torch.cat([-inv.sum(dim=2, keepdim=True), inv], dim=2)  # (C, D, D+1)
    rows = (torch.arange(C)[:, None, None] + C * torch.arange(D)[None, :, None]).expand(C, D, k)
    cols = cells[:, None, :].expand(C, D, k)
    G = torch.sparse_coo_tensor(
        torch.stack([rows.reshape(-1), cols.reshape(-1)]),
        grads.reshape(-1),
        (D * C, vertices.shape[0]),
        check_invariants=False,
    ).coalesce()
    return _csr(G), torch.linalg.det(E).abs() / math.factorial(D)


def geodesic_distances(domain: Domain, sources: torch.Tensor) -> torch.Tensor:
    """Shortest-path distances along the mesh's edges from each source vertex: ``(S, Nv)``."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    c = domain.cells
    k = c.shape[1]
    # each edge once (it belongs to several cells; a COO matrix would sum its copies into a longer
    # edge, by how the cells happen to list it: the distances then depended on the cells' order)
    pairs = torch.unique(torch.cat([c[:, [a, b]] for a in range(k) for b in range(a + 1, k)]).sort(dim=1).values, dim=0)
    pairs = pairs.numpy()
    v = domain.vertices.numpy()
    w = np.linalg.norm(v[pairs[:, 0]] - v[pairs[:, 1]], axis=1)
    n = v.shape[0]
    graph = coo_matrix((w, (pairs[:, 0], pairs[:, 1])), shape=(n, n)).tocsr()
    return torch.from_numpy(dijkstra(graph, directed=False, indices=sources.numpy()))


def project_rows(W: torch.Tensor, K: torch.Tensor, B: torch.Tensor, support: torch.Tensor) -> torch.Tensor:
    """Least-norm correction of each row of ``W (m, V)`` on its ``support (m, V)`` so that
    ``W K = B`` holds again (reproduction and partition of unity), entries off the support zero."""
    W = W * support
    r = B - W @ K  # (m, D+1)
    S = support.to(W.dtype)
    gram = torch.einsum("jv,vd,ve->jde", S, K, K)
    sol = torch.linalg.lstsq(gram, r.unsqueeze(-1)).solution.squeeze(-1)  # (m, D+1)
    return W + S * (sol @ K.T)


def make_feasible(W: torch.Tensor, K: torch.Tensor, B: torch.Tensor, max_rounds: int = 30) -> torch.Tensor:
    """Nearby rows that are non-negative and reproduce ``B`` exactly: negative entries are set to
    zero and leave the support, and the rest of each row is corrected (least norm) until no entry
    is negative (an active-set loop; the support only shrinks)."""
    support = W > 0
    for _ in range(max_rounds):
        W = project_rows(W.clamp_min(0.0), K, B, support)
        negative = W < 0
        if not bool(negative.any()):
            break
        support &= ~negative
    return W


class _FactoredSolve:
    """``(G^T G + s^2 I)^{-1}`` applied to all right-hand sides: sparse LU on the CPU (scipy),
    factored once. The solve runs with the BLAS behind scipy limited to one thread: its idle
    threads otherwise spin between calls and take the cores from torch's (measured: 7x slower
    iterations on 2 cores)."""

    def __init__(self, G: torch.Tensor, shift: float) -> None:
        from scipy.sparse import csr_matrix, identity
        from scipy.sparse.linalg import splu

        Gs = csr_matrix((G.values().numpy(), G.col_indices().numpy(), G.crow_indices().numpy()), shape=G.shape)
        self.lu = splu((Gs.T @ Gs + shift * identity(G.shape[1])).tocsc(), permc_spec="COLAMD")

    def __call__(self, rhs: torch.Tensor, guess: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(self.lu.solve(rhs.numpy()))


#: The smallest ``(D C, V)`` block for which the native iterations run on more than one thread.
_NATIVE_PARALLEL_MIN = 1 << 21


class _NativeADMM:
    """The iterations of :func:`solve_lbc`'s ADMM loop in the native library (``tc_lbc_admm`` in
    ``torchcage/backends/native/lbc.c``; CPU, float64): the same steps in three passes over memory
    per iteration, with the ``Y`` step as forward and back substitution over all right-hand sides at
    once (the sparse LU of ``G^T G + s^2 I``, factored once with a symmetric minimum-degree
    ordering). It updates ``Y M`` (the ``(m, V)`` change of the interior values) in place of ``Y``:
    ``Y M = A^{-1} Z M^T M`` with ``M^T M = I - Q^T Q``, the rows of ``Q`` an orthonormal basis of
    the columns of ``K`` (the same iterates; ``D + 1`` rows of ``Q`` instead of ``V - D - 1`` of
    ``M``), and the gradients ``G P2 + E`` as one product with the gradient operator of all the
    mesh's vertices.

    The state ``P1 (D C, V)`` (its cells in the kernel's order), ``P2 (m, V)``, ``u1``, ``u2`` lives
    in padded tensors (:attr:`u1` and :attr:`u2` may be rescaled in place between calls: the
    adaptive penalty); :meth:`run` advances it by a number of iterations and returns the squared
    residuals of the last one; :attr:`interior_values` is ``P2``."""

    def __init__(
        self,
        lib: object,
        G: torch.Tensor,
        Gfull: torch.Tensor,
        cells: torch.Tensor,
        interior: torch.Tensor,
        boundary: torch.Tensor,
        boundary_values: torch.Tensor,
        GtJ: torch.Tensor,
        J: torch.Tensor,
        H: torch.Tensor,
        phiA: torch.Tensor,
        Q: torch.Tensor,
        ws: float,
        alpha: float,
    ) -> None:
        from scipy.sparse import csr_matrix, identity, tril, triu
        from scipy.sparse.linalg import splu

        from torchcage.backends.native import abi

        DC, m = G.shape
        C, V = phiA.shape
        D, nb = DC // C, boundary.shape[0]
        Gs = csr_matrix((G.values().numpy(), G.col_indices().numpy(), G.crow_indices().numpy()), shape=G.shape)
        lu = splu(
            (Gs.T @ Gs + ws * ws * identity(m)).tocsc(),
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
        low, up = tril(lu.L, k=-1).tocsr(), triu(lu.U, k=1).tocsr()  # (L's diagonal is 1)
        if max(low.nnz, up.nnz, Gfull.values().shape[0]) >= 2**31:
            raise OverflowError("the native LBC iterations index sparse matrices with int32")
        # all the mesh's vertices, interior first, then boundary: the rows of the padded P2
        order = torch.empty(Gfull.shape[1], dtype=torch.int64)
        order[interior] = torch.arange(m)
        order[boundary] = torch.arange(m, m + nb)
        # The cells (the rows of P1, u1, phiA), internal to the kernel, sorted by their first
        # vertex in that order: the rows that one vertex's step reads lie close together (a
        # mesher's cells come in any order; 12% per iteration on the LBC paper's cactus)
        ranked = order[cells]
        cell_order = torch.argsort(ranked.amin(dim=1) * (m + nb) + ranked.amax(dim=1), stable=True)
        rows = (torch.arange(D)[:, None] * C + cell_order[None, :]).reshape(-1).numpy()
        Gt = Gs[rows].T.tocsr()
        Gf = csr_matrix(
            (Gfull.values().numpy(), order[Gfull.col_indices()].numpy(), Gfull.crow_indices().numpy()),
            shape=Gfull.shape,
        )[rows]
        phiA, J = phiA[cell_order], J[torch.from_numpy(rows)]

        # (V padded with zero columns to a multiple of 4, which stay 0: the kernel's vector width)
        Vp = -(-V // 4) * 4

        def pad(t: torch.Tensor) -> torch.Tensor:
            return torch.nn.functional.pad(t.to(torch.float64), (0, Vp - V)).contiguous()

        def i32(a: np.ndarray | torch.Tensor) -> torch.Tensor:
            return torch.as_tensor(np.ascontiguousarray(a, dtype=np.int32))

        def f64(a: np.ndarray | torch.Tensor) -> torch.Tensor:
            return torch.as_tensor(np.ascontiguousarray(a, dtype=np.float64))

        self.P1, self.P2 = pad(J), pad(torch.cat([H, boundary_values]))
        self.u1, self.u2 = torch.zeros_like(self.P1), torch.zeros((m, Vp), dtype=torch.float64)
        self.V, self.m = V, m
        self.res = torch.zeros(2, dtype=torch.float64)
        # threads (torch's count) only for large blocks: each iteration opens four parallel regions,
        # whose cost (and, on a busy machine, the waits of spinning threads) outweighs small passes
        threads = torch.get_num_threads() if D * C * Vp >= _NATIVE_PARALLEL_MIN else 1
        kwargs = {
            "D": D, "C": C, "m": m, "V": Vp,
            "g_ptr": i32(Gf.indptr), "g_idx": i32(Gf.indices), "g_val": f64(Gf.data), "g_nnz": Gf.nnz,
            "gt_ptr": i32(Gt.indptr), "gt_idx": i32(Gt.indices), "gt_val": f64(Gt.data), "gt_nnz": Gt.nnz,
            "l_ptr": i32(low.indptr), "l_idx": i32(low.indices), "l_val": f64(low.data), "l_nnz": low.nnz,
            "u_ptr": i32(up.indptr), "u_idx": i32(up.indices), "u_val": f64(up.data), "u_nnz": up.nnz,
            "u_diag": f64(lu.U.diagonal()), "pr": i32(lu.perm_r), "pc": i32(lu.perm_c),
            "nb": nb, "GtJ": pad(GtJ), "H": pad(H), "phiA": pad(phiA), "Q": pad(Q),
            "mu": 1.0, "alpha": alpha, "ws": ws, "iters": 0, "nthreads": threads,
            "P1": self.P1, "P2": self.P2, "u1": self.u1, "u2": self.u2,
            "work": torch.empty((2 * D * C + 2 * m + threads * (2 * D + 2)) * Vp, dtype=torch.float64),
            "res": self.res,
        }  # fmt: skip
        self._keep = kwargs  # (the arrays behind the pointers stay alive)
        self._args = abi.check_arguments("tc_lbc_admm", kwargs)
        names = [a.name for a in abi.SIGNATURES["tc_lbc_admm"]]
        self._mu, self._iters = names.index("mu"), names.index("iters")
        self._fn = lib.tc_lbc_admm  # type: ignore[attr-defined]

    @property
    def interior_values(self) -> torch.Tensor:
        """``(m, V)`` the current ``P2`` (a view)."""
        return self.P2[: self.m, : self.V]

    def run(self, iterations: int, mu: float) -> tuple[float, float]:
        """Advance by ``iterations`` (>= 1) with penalty ``mu``; the last one's ``||X - P1'||^2 +
        ||W - P2'||^2`` and ``||P1' - P1||^2 + ||P2' - P2||^2``."""
        self._args[self._mu], self._args[self._iters] = float(mu), int(iterations)
        self._fn(*self._args)
        sp, sd = self.res.tolist()
        return sp, sd


def _single_threaded_blas() -> contextlib.AbstractContextManager:
    """Limit the BLAS libraries loaded by numpy/scipy to one thread (no-op without threadpoolctl)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


class _ConjugateGradient:
    """Jacobi-preconditioned conjugate gradient on ``G^T G + I`` for all right-hand sides at once,
    warm-started from the previous iterate (any device)."""

    def __init__(self, G: torch.Tensor, shift: float, tol: float = 1e-10, max_iter: int = 500) -> None:
        self.G, self.Gt = G, _csr(G.to_sparse_coo().t().coalesce())
        diag = torch.zeros(G.shape[1], dtype=G.dtype, device=G.device)
        coo = G.to_sparse_coo().coalesce()
        diag.index_add_(0, coo.indices()[1], coo.values() ** 2)
        self.inv_diag = 1.0 / (diag + shift)
        self.shift = shift
        self.tol, self.max_iter = tol, max_iter

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return self.Gt @ (self.G @ x) + self.shift * x

    def __call__(self, rhs: torch.Tensor, guess: torch.Tensor) -> torch.Tensor:
        x = guess.clone()
        r = rhs - self.apply(x)
        z = self.inv_diag[:, None] * r
        p = z.clone()
        rz = (r * z).sum(0)
        stop = self.tol * rhs.norm(dim=0).clamp_min(1e-300)
        for _ in range(self.max_iter):
            if bool((r.norm(dim=0) <= stop).all()):
                break
            Ap = self.apply(p)
            alpha = rz / (p * Ap).sum(0).clamp_min(1e-300)
            x += alpha * p
            r -= alpha * Ap
            z = self.inv_diag[:, None] * r
            rz_new = (r * z).sum(0)
            p = z + (rz_new / rz.clamp_min(1e-300)) * p
            rz = rz_new
        return x


def solve_lbc(
    domain: Domain,
    cage_vertices: torch.Tensor,
    *,
    weighting: str = "quadratic",
    mu: float | None = None,
    mu_factor: float = 0.3,
    alpha: float = 1.65,
    eps_primal: float = 3e-7,
    eps_dual: float = 1e-5,
    max_iter: int = 20000,
    adaptive: bool = True,
    w_scale: float = 1.0,
    balance_every: int = 50,
    balance_after: int = 500,
    balance_ratio: float = 1e-2,
    balance_step: float = 1.5,
    linear_solver: str = "auto",
    report_every: int = 50,
    progress: bool | Callable[[int, float, float], None] = False,
) -> LBCResult:
    """Minimise the weighted total variation of the coordinate functions on ``domain`` by ADMM.

    The scene is rescaled to a bounding-box diagonal of 1 inside (the paper's setting, so that
    ``mu`` and the tolerances mean the same for any cage size).

    Args:
        domain: the mesh, with boundary values.
        cage_vertices: ``(V, D)`` the cage's vertices.
        weighting: ``"quadratic"`` (tau(x) = x², the paper's choice), ``"linear"``, ``"sqrt"`` or
            ``"constant"`` (plain total variation).
        mu: initial penalty. Default: ``mu_factor`` times the ratio of the mean weight ``phi A``
            to the RMS gradient of the initial iterate (the paper's fixed ``mu = 10`` is orders of
            magnitude above this scale and stops far from the optimum, see the module docstring).
        mu_factor: scales the default penalty.
        alpha: over-relaxation in [1.5, 1.8] (the paper: 1.65).
        eps_primal: the primal tolerance per entry: stop when ``||r_p||_F <= eps_primal * N_p``
            and ``||r_d||_F <= eps_dual * N_d`` (the paper's rule and values, ``N`` the number of
            entries of each residual). ``0`` (either tolerance) runs to ``max_iter`` (to compare
            solvers per iteration): no warning then, and ``converged`` is ``False`` unless the
            residuals reach exactly 0.
        eps_dual: the dual tolerance per entry.
        max_iter: iteration limit; stopping there warns and reports ``converged=False``.
        adaptive: residual balancing of ``mu`` (see the module docstring); ``False`` keeps ``mu``.
        balance_every: iterations between balancing steps.
        linear_solver: ``"lu"`` (scipy sparse LU, factored once; CPU; with the native library,
            the whole iteration runs in C), ``"cg"`` (warm-started preconditioned conjugate
            gradient in torch; any device) or ``"auto"`` (lu on the CPU).
        report_every: iterations between residual checks (and history entries).
        progress: ``True`` for a progress bar (:class:`~torchcage.solvers.progress.ToleranceProgress`:
            how far, on a log scale, the residuals have come towards their tolerances, with their
            ratios to them; iterations towards ``max_iter`` when a tolerance is 0), or a callable
            ``progress(iteration, primal, dual)``.

    Returns:
        An :class:`LBCResult`.

    Raises:
        ValueError: an unknown ``weighting`` or ``linear_solver``, a negative or non-finite
            tolerance, or a non-positive ``max_iter``, ``balance_every``, ``report_every`` or
            ``balance_step``.
    """
    if weighting not in TAU:
        raise ValueError(f"weighting must be one of {tuple(TAU)}, got {weighting!r}")
    if linear_solver not in ("auto", "lu", "cg"):
        raise ValueError(f"linear_solver must be 'auto', 'lu' or 'cg', got {linear_solver!r}")
    for name, value in (("eps_primal", eps_primal), ("eps_dual", eps_dual)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be a finite number >= 0 (0: run to max_iter), got {value!r}")
    for name, count in (("max_iter", max_iter), ("balance_every", balance_every), ("report_every", report_every)):
        if isinstance(count, bool) or not isinstance(count, int) or count < 1:
            raise ValueError(f"{name} must be a positive integer, got {count!r}")
    if not (isinstance(balance_step, (int, float)) and math.isfinite(balance_step) and balance_step > 1):
        raise ValueError(f"balance_step must be a finite number above 1, got {balance_step!r}")
    dt = torch.float64
    cv = torch.as_tensor(cage_vertices).detach().to(dt).cpu()
    want = (domain.boundary_values.shape[1], domain.vertices.shape[1])
    if cv.ndim != 2 or tuple(cv.shape) != want:
        raise CageError(
            f"cage_vertices must have shape {want} for this domain (its boundary values are for {want[0]} cage "
            f"vertices in {want[1]}D), got {tuple(cv.shape)}; pass the vertices of the cage the domain was made for"
        )
    if domain.cage_vertices is not None:
        ref = domain.cage_vertices.to(dt)
        if bool(((cv - ref).abs() > 1e-9 * max(float(ref.abs().amax()), 1e-300)).any()):
            raise CageError(
                "cage_vertices differ from the rest cage this domain was meshed for; pass that cage's vertices, "
                "or mesh this cage (mesh_domain)"
            )
    V, D = cv.shape
    lo, hi = domain.vertices.min(0).values, domain.vertices.max(0).values
    scale = float((hi - lo).norm())
    verts = (domain.vertices - lo) / scale
    c = (cv - lo) / scale
    boundary, interior = domain.boundary, domain.interior
    m = interior.shape[0]
    Gfull, vol = gradient_operator(verts, domain.cells)
    if m == 0:
        # every mesh vertex is on the cage (a flat cage's mesh spans its thickness): the boundary
        # values are the whole answer, nothing to optimise
        weights = torch.zeros((verts.shape[0], V), dtype=dt)
        weights[boundary] = domain.boundary_values.to(dt)
        dist = geodesic_distances(domain, torch.arange(V))
        used = torch.zeros(dist.shape[1], dtype=torch.bool)
        used[domain.cells.reshape(-1)] = True
        dist = dist / dist[:, used].amax(dim=1, keepdim=True).clamp_min(1e-300)
        at_cells = dist.T[domain.cells].mean(dim=1)
        grads = torch.sqrt((Gfull @ weights).reshape(D, -1, V).square().sum(dim=0))
        objective = float((TAU[weighting](at_cells) * vol[:, None] * grads).sum()) * scale ** (D - 1)
        return LBCResult(domain, weights, 0, 0.0, 0.0, 0.0, 0.0, True, objective, math.nan if mu is None else mu)
    Gfull_coo = Gfull.to_sparse_coo().coalesce()
    idx, val = Gfull_coo.indices(), Gfull_coo.values()
    col_map = torch.full((verts.shape[0],), -1, dtype=torch.int64)
    col_map[interior] = torch.arange(m)
    keep = col_map[idx[1]] >= 0
    G = torch.sparse_coo_tensor(
        torch.stack([idx[0, keep], col_map[idx[1, keep]]]), val[keep], (Gfull.shape[0], m), check_invariants=False
    )
    G = G.coalesce()
    Gt = _csr(G.t().coalesce())
    G = _csr(G)
    Wfull_b = torch.zeros((verts.shape[0], V), dtype=dt)
    Wfull_b[boundary] = domain.boundary_values.to(dt)
    E = Gfull @ Wfull_b  # (DC, V) boundary contributions
    K = torch.cat([c, torch.ones(V, 1, dtype=dt)], 1)  # (V, D+1)
    Bm = torch.cat([verts[interior], torch.ones(m, 1, dtype=dt)], 1)  # (m, D+1)
    U, S, Vh = torch.linalg.svd(K, full_matrices=True)
    H = Bm @ (Vh.T @ torch.diag(1 / S) @ U[:, : D + 1].T)  # least-norm solution of H K = B
    M = U[:, D + 1 :].T.contiguous()  # (V - D - 1, V), M K = 0, M M^T = I
    J = G @ H + E
    # weights phi_i^s A_s: tau of the normalised geodesic distance at the cell centroid
    dist = geodesic_distances(domain, torch.arange(V))  # (V, Nv), in the cage's units
    # (normalised over the vertices of cells only: a mesher may leave vertices in no cell, at
    # infinite distance, which made every distance 0 and the penalty 0; the sliver cube did)
    used = torch.zeros(dist.shape[1], dtype=torch.bool)
    used[domain.cells.reshape(-1)] = True
    far = ~torch.isfinite(dist[:, used]).all(dim=1)
    if bool(far.any()):
        raise ValueError(
            f"cage vertices {torch.nonzero(far).flatten()[:10].tolist()} are not connected to the meshed "
            "interior of the cage; pass a domain= that contains them, or remove the slivers around them"
        )
    dist = dist / dist[:, used].amax(dim=1, keepdim=True).clamp_min(1e-300)
    at_cells = dist.T[domain.cells].mean(dim=1)  # (C, V)
    phiA = TAU[weighting](at_cells) * vol[:, None]  # (C, V)
    C = domain.cells.shape[0]

    # Scaling of the W = Y M + H constraint: the paper's weight 1 makes it thousands of times weaker
    # than the gradient constraint (G's entries are ~1 / cell size), and the non-negativity of W
    # then converges slowly; s^2 = the mean diagonal of G^T G balances the two (same solution).
    ws = math.sqrt(float(G.values().square().sum()) / m) * w_scale if w_scale > 0 else 1.0
    if not (math.isfinite(ws) and ws > 0):  # (interior vertices in no cell only: no gradient rows)
        ws = 1.0
    native: _NativeADMM | None = None
    if linear_solver != "cg":
        from torchcage.backends import native as _native

        lib = _native.library()
        if lib is not None:  # the whole iteration in C ("lu" and "auto" with the native library)
            Q = U[:, : D + 1].T  # (D+1, V): orthonormal basis of K's columns, M^T M = I - Q^T Q
            with contextlib.suppress(OverflowError):  # (int32 indices overflow: the torch loop)
                native = _NativeADMM(
                    lib, G, Gfull, domain.cells, interior, boundary, domain.boundary_values.to(dt), Gt @ J, J, H,
                    phiA, Q, ws, alpha,
                )  # fmt: skip
    if linear_solver == "cg":
        solve: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] = _ConjugateGradient(G, ws * ws)
    elif native is None:
        solve = _FactoredSolve(G, ws * ws)

    if mu is None:
        # The penalty's natural scale: the shrinkage threshold phi A / mu against the gradients'
        # size (the initial iterate's, J = G H + E): a penalty far above it makes the weighted total
        # variation a negligible pull per iteration and ADMM crawls towards the optimum.
        grad0 = torch.sqrt(J.view(D, C, V).square().sum(dim=0))
        mu = float(phiA.mean() / grad0.square().mean().sqrt().clamp_min(1e-300)) * mu_factor
    if not (math.isfinite(mu) and mu > 0):
        raise ValueError(f"the ADMM penalty mu must be finite and positive, got {mu}")
    r = V - D - 1
    Y = torch.zeros((m, r), dtype=dt)
    P1, P2 = J.clone(), H.clone()  # G Y M + J and Y M + H, kept up to date
    P1_new = torch.empty_like(J)
    u1, u2 = torch.zeros_like(J), torch.zeros_like(H)  # multipliers scaled by 1 / mu
    a, q = torch.empty_like(J), torch.empty_like(J)  # work buffers for the (D C, V) block
    GtJ = Gt @ J
    Np, Nd = (D * C + m) * V, (D * C + m) * V
    tol_p, tol_d = eps_primal * Np, eps_dual * Nd
    history: list[tuple[int, float, float, float]] = []
    bar = None
    if progress is True:
        from torchcage.solvers.progress import ToleranceProgress

        bar = ToleranceProgress("LBC (ADMM)", max_iter, ("primal", "dual"), (tol_p, tol_d))
    # Residual balancing compares each residual with its tolerance; a zero tolerance (run to
    # max_iter) is replaced there by the default's, so that the comparison stays defined
    bal_p = tol_p if tol_p > 0 else 3e-7 * Np
    bal_d = tol_d if tol_d > 0 else 1e-5 * Nd
    mu_lo, mu_hi = mu * 1e-12, mu * 1e12  # (balancing never drives the penalty to 0 or inf)
    rp = rd = math.inf
    it = 0

    def checkpoint(it: int, rp: float, rd: float) -> tuple[bool, int]:
        """History and progress after a residual check; whether to stop, and the balancing step:
        ``1`` (raise ``mu``), ``-1`` (lower it) or ``0``."""
        if it % report_every == 0 or it == max_iter:
            history.append((it, rp, rd, mu))
            if bar is not None:
                bar.update(it, (rp, rd))
            elif callable(progress):
                progress(it, rp, rd)
        if rp <= tol_p and rd <= tol_d:
            return True, 0
        if adaptive and it % balance_every == 0 and it >= balance_after:
            # Gentle balancing against the tolerances: raise the penalty only while the dual
            # residual is far inside its tolerance and the primal one is not (products, not
            # ratios: residuals and tolerances may be exactly 0).
            if rd * bal_p < balance_ratio * rp * bal_d and rp > tol_p and mu * balance_step <= mu_hi:
                return False, 1
            if rp * bal_d < balance_ratio * rd * bal_p and rd > tol_d and mu / balance_step >= mu_lo:
                return False, -1
        return False, 0

    if native is not None:
        # The native iterations (the same steps in C), run from one residual check to the next.
        while it < max_iter:
            nxt = min(max_iter, (it // report_every + 1) * report_every)
            if adaptive:
                nxt = min(nxt, (it // balance_every + 1) * balance_every)
            sp, sd = native.run(nxt - it, mu)
            it = nxt
            rp, rd = math.sqrt(sp), mu * math.sqrt(sd)
            stop, step = checkpoint(it, rp, rd)
            if stop:
                break
            if step > 0:
                mu = mu * balance_step
                native.u1.div_(balance_step)
                native.u2.div_(balance_step)
            elif step < 0:
                mu = mu / balance_step
                native.u1.mul_(balance_step)
                native.u2.mul_(balance_step)
        P2 = native.interior_values
    # Every operation on the large (D C, V) block writes into a preallocated buffer: on a small CPU
    # these passes over memory, not the arithmetic, set the time per iteration.
    with _single_threaded_blas():
        for it in range(1, max_iter + 1 if native is None else 1):  # (the native loop ran)
            # Step 1: group soft-thresholding of the gradients (Eq. 30), over-relaxed: q = X~ + u1.
            torch.sub(P1, u1, out=a)
            a3 = a.view(D, C, V)
            norm = torch.sqrt((a3 * a3).sum(dim=0)).clamp_min_(1e-300)
            shrink = torch.div(phiA, norm).mul_(-1.0 / mu).add_(1.0).clamp_min_(0.0)
            torch.mul(a3, shrink, out=q.view(D, C, V))  # X
            check = it % report_every == 0 or it == max_iter or (adaptive and it % balance_every == 0)
            if check:
                X = q.clone()
            torch.lerp(P1, q, alpha, out=q).add_(u1)
            # ... and projection on W >= 0 (Eq. 31), over-relaxed: w = W~ + u2 / s.
            W = (P2 - u2 / ws).clamp_min_(0.0)
            w = torch.lerp(P2, W, alpha).add_(u2, alpha=1.0 / ws)
            # Step 2: the Y step, one SPD solve for all right-hand sides.
            rhs = torch.addmm(w - H, Gt, q, alpha=1.0 / (ws * ws)).sub_(GtJ, alpha=1.0 / (ws * ws)).mul_(ws * ws) @ M.T
            Y_new = solve(rhs, Y)
            P2_new = torch.addmm(H, Y_new, M)
            torch.addmm(J, G, P2_new - H, out=P1_new)
            # Step 3: multipliers.
            torch.sub(q, P1_new, out=u1)
            u2 = (w - P2_new) * ws
            if check:
                rp = math.sqrt(float((X - P1_new).square().sum() + (W - P2_new).square().sum()))
                rd = mu * math.sqrt(float((P1_new - P1).square().sum() + (P2_new - P2).square().sum()))
            P1, P1_new = P1_new, P1
            Y, P2 = Y_new, P2_new
            if check:
                stop, step = checkpoint(it, rp, rd)
                if stop:
                    break
                if step > 0:
                    mu, u1, u2 = mu * balance_step, u1 / balance_step, u2 / balance_step
                elif step < 0:
                    mu, u1, u2 = mu / balance_step, u1 * balance_step, u2 * balance_step
    if bar is not None:
        bar.close()
    converged = rp <= tol_p and rd <= tol_d
    if not converged and tol_p > 0 and tol_d > 0:  # (a zero tolerance asked to run to max_iter)
        warnings.warn(
            f"LBC's ADMM stopped after {it} iterations without converging (primal residual {rp:.3g}, tolerance "
            f"{tol_p:.3g}; dual {rd:.3g}, tolerance {tol_d:.3g}); raise max_iter, keep adaptive=True, or use "
            "fewer cells (target_cells)",
            stacklevel=2,
        )
    # Exact constraints (W = Y M + H), then non-negativity: clamp and re-project on the support.
    Wi = make_feasible(P2, K, Bm)
    weights = Wfull_b.clone()
    weights[interior] = Wi
    grads = torch.sqrt((Gfull @ weights).reshape(D, C, V).square().sum(dim=0))
    objective = float((TAU[weighting](at_cells) * vol[:, None] * grads).sum()) * scale ** (D - 1)
    return LBCResult(domain, weights, it, rp, rd, tol_p, tol_d, converged, objective, mu, history)
