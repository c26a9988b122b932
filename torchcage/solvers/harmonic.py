r"""Harmonic coordinates (Joshi et al. 2007) on a simplicial mesh of the cage's interior.

Each coordinate function is the discrete harmonic extension of its boundary values: piecewise
linear (P1) on the mesh of :mod:`torchcage.solvers.domain`, equal to the cage's basis functions on
the boundary (barycentric on triangles, linear on 2D edges, bilinear on quads, Lagrange at the cage
vertices), and minimising the Dirichlet energy :math:`\int |\nabla w|^2` inside. With ``K`` the P1
stiffness matrix (the cotangent Laplacian), ``I`` the interior and ``B`` the boundary vertices:

.. math::
    K_{II}\, W_I = -K_{IB}\, W_B .

All cage vertices are right-hand sides of one factorisation. P1 elements reproduce linear functions
exactly, so linear precision and partition of unity hold at every mesh vertex and every point
interpolated in a cell, to the solver's precision. The weights are nonnegative when the mesh is
good enough for the discrete maximum principle (in 2D: no angle sum opposite an edge above pi);
:class:`HarmonicResult` reports the smallest weight.

**Solver.** ``"lu"``: scipy's sparse LU (SuperLU, COLAMD ordering; ``K_II`` is symmetric positive
definite, but scipy has no sparse Cholesky, and the factorisation is a small part of the cost
here: see docs/harmonic.md for the measurements); ``"cg"``: Jacobi-preconditioned conjugate
gradients in torch on any device, all right-hand sides at once.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from .domain import Domain
from .lbc import _single_threaded_blas, gradient_operator

__all__ = ["HarmonicResult", "solve_harmonic", "stiffness_matrix"]


@dataclass
class HarmonicResult:
    """Harmonic coordinates at the mesh vertices.

    Attributes:
        domain: the mesh.
        weights: ``(Nv, V)`` float64 coordinates at its vertices (boundary rows: the boundary values).
        residual: ``max |K_II W_I + K_IB W_B|`` over the largest entry of ``K``: the solve's accuracy.
        min_weight: the smallest weight (negative where the mesh breaks the maximum principle).
        negative_vertices: mesh vertices with a weight below ``-1e-12``.
        solver: ``"lu"`` or ``"cg"``.
        seconds: time of the assembly and solve.
    """

    domain: Domain
    weights: torch.Tensor
    residual: float
    min_weight: float
    negative_vertices: int
    solver: str
    seconds: float


def stiffness_matrix(vertices: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """The P1 stiffness matrix ``K (Nv, Nv)`` (sparse COO, float64): ``K_ab = sum over cells of
    vol * grad phi_a . grad phi_b``, the cotangent Laplacian.

    Examples:
        >>> v = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
        >>> stiffness_matrix(v, torch.tensor([[0, 1, 2]])).to_dense().tolist()
        [[1.0, -0.5, -0.5], [-0.5, 0.5, 0.0], [-0.5, 0.0, 0.5]]
    """
    G, vol = gradient_operator(vertices, cells)  # (D C, Nv), rows component-major
    D = cells.shape[1] - 1
    G = G.to_sparse_coo().coalesce()
    w = vol.repeat(D)[G.indices()[0]]  # each row's cell volume
    Gw = torch.sparse_coo_tensor(G.indices(), G.values() * w, G.shape, check_invariants=False).coalesce()
    return (G.t().coalesce() @ Gw).coalesce()


def _scipy(K: torch.Tensor):
    from scipy.sparse import coo_matrix

    i = K.indices().numpy()
    return coo_matrix((K.values().numpy(), (i[0], i[1])), shape=K.shape).tocsr()


def _cg(A, rhs: torch.Tensor, tol: float, max_iter: int) -> torch.Tensor:
    """Jacobi-preconditioned CG on the CSR matrix ``A`` for the columns of ``rhs`` at once."""
    diag = torch.zeros(A.shape[0], dtype=rhs.dtype)
    coo = A.to_sparse_coo().coalesce()
    i = coo.indices()
    on = i[0] == i[1]
    diag.index_add_(0, i[0][on], coo.values()[on])
    inv = 1.0 / diag
    x = torch.zeros_like(rhs)
    r = rhs.clone()
    z = inv[:, None] * r
    p = z.clone()
    rz = (r * z).sum(0)
    stop = tol * rhs.norm(dim=0).clamp_min(1e-300)
    for _ in range(max_iter):
        if bool((r.norm(dim=0) <= stop).all()):
            break
        Ap = A @ p
        alpha = rz / (p * Ap).sum(0).clamp_min(1e-300)
        x += alpha * p
        r -= alpha * Ap
        z = inv[:, None] * r
        rz_new = (r * z).sum(0)
        p = z + (rz_new / rz.clamp_min(1e-300)) * p
        rz = rz_new
    return x


def solve_harmonic(domain: Domain, solver: str = "lu", *, tol: float = 1e-13, max_iter: int = 20000) -> HarmonicResult:
    """Harmonic coordinates at the vertices of ``domain``.

    Args:
        domain: the mesh with its boundary values (:func:`torchcage.solvers.domain.mesh_domain`).
        solver: ``"lu"`` (scipy sparse LU, factored once) or ``"cg"`` (torch conjugate gradients).
        tol: relative residual of ``"cg"``.
        max_iter: iterations of ``"cg"``.

    Returns:
        A :class:`HarmonicResult`.
    """
    if solver not in ("lu", "cg"):
        raise ValueError(f"solver must be 'lu' or 'cg', got {solver!r}")
    t0 = time.perf_counter()
    v = domain.vertices.to(torch.float64)
    lo, hi = v.min(0).values, v.max(0).values
    scale = float((hi - lo).norm()) or 1.0
    K = stiffness_matrix((v - lo) / scale, domain.cells)  # (scaled: the same matrix up to scale^(D-2))
    I, B = domain.interior, domain.boundary
    WB = domain.boundary_values.to(torch.float64)
    Nv, V = v.shape[0], WB.shape[1]
    W = torch.zeros(Nv, V, dtype=torch.float64)
    W[B] = WB
    Ks = _scipy(K)
    Ii, Bi = I.numpy(), B.numpy()
    KII, KIB = Ks[Ii][:, Ii], Ks[Ii][:, Bi]
    rhs = -(KIB @ WB.numpy())
    if I.numel():
        if solver == "lu":
            from scipy.sparse.linalg import splu

            with _single_threaded_blas():
                WI = torch.from_numpy(splu(KII.tocsc(), permc_spec="COLAMD").solve(rhs))
        else:
            A = KII.tocsr()
            At = torch.sparse_csr_tensor(
                torch.from_numpy(A.indptr).long(), torch.from_numpy(A.indices).long(), torch.from_numpy(A.data),
                A.shape, check_invariants=False,
            )  # fmt: skip
            WI = _cg(At, torch.from_numpy(rhs), tol, max_iter)
        W[I] = WI
        res = float(abs(KII @ W[I].numpy() - rhs).max() / max(abs(Ks).max(), 1e-300))
    else:
        res = 0.0
    mn = float(W.min()) if W.numel() else 0.0
    neg = int((W.min(dim=1).values < -1e-12).sum())
    return HarmonicResult(domain, W, res, mn, neg, solver, time.perf_counter() - t0)
