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

**Solver.** ``K_II`` is symmetric positive definite. ``"cholesky"``: cholespy's sparse Cholesky
(BSD; CPU and CUDA tensors), the fastest measured (docs/harmonic.md); ``"lu"``: scipy's sparse LU
(SuperLU, COLAMD ordering; scipy has no sparse Cholesky); ``"cg"``: Jacobi-preconditioned
conjugate gradients in torch, all right-hand sides at once; ``"auto"``: cholesky where cholespy is
installed, else lu.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from torchcage.solvers.domain import Domain
from torchcage.solvers.lbc import _single_threaded_blas

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
        solver: ``"cholesky"``, ``"lu"`` or ``"cg"``.
        seconds: time of the assembly and solve.
    """

    domain: Domain
    weights: torch.Tensor
    residual: float
    min_weight: float
    negative_vertices: int
    solver: str
    seconds: float


def _cell_gradients(vertices: torch.Tensor, cells: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The hat functions' gradients on every cell ``(C, D, D + 1)`` and the cell volumes ``(C,)``."""
    D = cells.shape[1] - 1
    p = vertices[cells]  # (C, D+1, D)
    E = p[:, 1:] - p[:, :1]  # (C, D, D) rows: edge vectors
    inv = torch.linalg.inv(E)  # column k: the gradient of barycentric k + 1
    grads = torch.cat([-inv.sum(dim=2, keepdim=True), inv], dim=2)
    return grads, torch.linalg.det(E).abs() / math.factorial(D)


def _stiffness_scipy(vertices: torch.Tensor, cells: torch.Tensor):
    """:func:`stiffness_matrix` as a scipy CSR matrix (duplicates summed)."""
    from scipy.sparse import coo_matrix

    grads, vol = _cell_gradients(vertices, cells)
    local = vol[:, None, None] * torch.einsum("cda,cdb->cab", grads, grads)  # (C, k, k)
    k = cells.shape[1]
    c = cells.numpy()
    rows, cols = np.repeat(c, k, axis=1).ravel(), np.tile(c, (1, k)).ravel()
    n = vertices.shape[0]
    return coo_matrix((local.numpy().ravel(), (rows, cols)), shape=(n, n)).tocsr()


def stiffness_matrix(vertices: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """The P1 stiffness matrix ``K (Nv, Nv)`` (sparse COO, float64): ``K_ab = sum over cells of
    vol * grad phi_a . grad phi_b``, the cotangent Laplacian.

    Examples:
        >>> v = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
        >>> stiffness_matrix(v, torch.tensor([[0, 1, 2]])).to_dense().tolist()
        [[1.0, -0.5, -0.5], [-0.5, 0.5, 0.0], [-0.5, 0.0, 0.5]]
    """
    K = _stiffness_scipy(vertices.to(torch.float64), cells).tocoo()
    idx = torch.from_numpy(np.stack([K.row, K.col]).astype(np.int64))
    return torch.sparse_coo_tensor(idx, torch.from_numpy(K.data), K.shape, check_invariants=False).coalesce()


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


def _cholesky(A, rhs: np.ndarray) -> torch.Tensor:
    from cholespy import CholeskySolverD, MatrixType

    A = A.tocoo()
    rows, cols = torch.from_numpy(A.row.astype(np.int32)), torch.from_numpy(A.col.astype(np.int32))
    solver = CholeskySolverD(A.shape[0], rows, cols, torch.from_numpy(A.data), MatrixType.COO)
    b = torch.from_numpy(np.ascontiguousarray(rhs))
    x = torch.zeros_like(b)
    for s in range(0, b.shape[1], 128):  # (cholespy solves at most 128 right-hand sides at once)
        xs = torch.zeros_like(b[:, s : s + 128]).contiguous()
        solver.solve(b[:, s : s + 128].contiguous(), xs)
        x[:, s : s + 128] = xs
    return x


def _has_cholespy() -> bool:
    try:
        import cholespy  # noqa: F401
    except ImportError:
        return False
    return True


def solve_harmonic(
    domain: Domain, solver: str = "auto", *, tol: float = 1e-13, max_iter: int = 20000
) -> HarmonicResult:
    """Harmonic coordinates at the vertices of ``domain``.

    Args:
        domain: the mesh with its boundary values (:func:`torchcage.solvers.domain.mesh_domain`).
        solver: ``"auto"``, ``"cholesky"`` (cholespy), ``"lu"`` (scipy sparse LU) or ``"cg"``
            (torch conjugate gradients); see the module docstring.
        tol: relative residual of ``"cg"``.
        max_iter: iterations of ``"cg"``.

    Returns:
        A :class:`HarmonicResult`.
    """
    if solver not in ("auto", "cholesky", "lu", "cg"):
        raise ValueError(f"solver must be 'auto', 'cholesky', 'lu' or 'cg', got {solver!r}")
    if solver == "auto":
        solver = "cholesky" if _has_cholespy() else "lu"
    elif solver == "cholesky" and not _has_cholespy():
        raise ImportError("solver='cholesky' needs cholespy: pip install 'torchcage[lbc]' (or pip install cholespy)")
    t0 = time.perf_counter()
    v = domain.vertices.to(torch.float64)
    lo, hi = v.min(0).values, v.max(0).values
    scale = float((hi - lo).norm()) or 1.0
    Ks = _stiffness_scipy((v - lo) / scale, domain.cells)  # (scaled: the same matrix up to scale^(D-2))
    I, B = domain.interior, domain.boundary
    WB = domain.boundary_values.to(torch.float64)
    Nv, V = v.shape[0], WB.shape[1]
    W = torch.zeros(Nv, V, dtype=torch.float64)
    W[B] = WB
    Ii, Bi = I.numpy(), B.numpy()
    KII, KIB = Ks[Ii][:, Ii], Ks[Ii][:, Bi]
    rhs = -(KIB @ WB.numpy())
    if I.numel():
        if solver == "cholesky":
            WI = _cholesky(KII, rhs)
        elif solver == "lu":
            from scipy.sparse.linalg import splu

            with _single_threaded_blas():
                WI = torch.from_numpy(splu(KII.tocsc(), permc_spec="COLAMD").solve(rhs))
        else:
            A = KII.tocsr()
            with warnings.catch_warnings():  # (torch's "CSR is beta" notice: the product used here works)
                warnings.simplefilter("ignore", UserWarning)
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
