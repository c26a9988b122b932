"""Harmonic coordinates: partition of unity, linear precision, Lagrange and boundary values, an
independent P1 solve (numpy assembly, scipy's direct solver), convergence under refinement."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from support import box_cage, data_path, l_shape, p1_stiffness, sample_inside, triquad

import torchcage as tc
from torchcage import functional as F
from torchcage.solvers.domain import mesh_domain
from torchcage.solvers.harmonic import solve_harmonic

pytest.importorskip("scipy")

D64 = torch.float64


def _polygon() -> tc.Cage:
    return tc.Cage(torch.tensor([[0.0, 0], [2, 0], [2, 1], [1, 1.5], [0.3, 0.6], [0, 1]], dtype=D64))


def _inside(cage: tc.Cage, n: int, seed: int = 0) -> torch.Tensor:
    """Points inside the cage whose quads are bilinear patches (the surface the coordinates take
    their boundary values on), not split along a diagonal as :func:`support.sample_inside` has it."""
    from torchcage.solvers.domain import inside_bilinear_cage

    x = sample_inside(cage, 2 * n, seed)
    return x[inside_bilinear_cage(x, cage)][:n]


def _independent_p1(vertices: np.ndarray, cells: np.ndarray, boundary: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The P1 harmonic extension: the stiffness matrix assembled independently
    (:func:`support.p1_stiffness`), solved by scipy's spsolve."""
    from scipy.sparse.linalg import spsolve

    n = vertices.shape[0]
    K = p1_stiffness(vertices, cells)
    free = np.setdiff1d(np.arange(n), boundary)
    W = np.zeros((n, values.shape[1]))
    W[boundary] = values
    A = K[free][:, free].tocsc()
    W[free] = spsolve(A, -(K[free][:, boundary] @ values))
    return W


def _check(W: torch.Tensor, x: torch.Tensor, cage: tc.Cage) -> None:
    assert float((W.sum(-1) - 1).abs().max()) <= 1e-10
    assert float((W @ cage.vertices.to(D64) - x).abs().max() / cage.scale) <= 1e-9


@pytest.mark.parametrize("name", ["polygon", "cube", "l_shape", "triquad"])
def test_properties_and_an_independent_solve(name: str) -> None:
    cage = {"polygon": _polygon, "cube": box_cage, "l_shape": l_shape, "triquad": triquad}[name]()
    cells = 600 if cage.dim == 2 else 3000
    dom = mesh_domain(cage, cells)
    res = solve_harmonic(dom)
    W, V = res.weights, cage.num_vertices
    _check(W, dom.vertices, cage)  # at the mesh vertices
    assert torch.allclose(W[:V], torch.eye(V, dtype=D64), atol=1e-14)  # Lagrange at the cage vertices
    assert torch.equal(W[dom.boundary], dom.boundary_values)  # boundary values exact
    ref = _independent_p1(dom.vertices.numpy(), dom.cells.numpy(), dom.boundary.numpy(), dom.boundary_values.numpy())
    assert float(np.abs(W.numpy() - ref).max()) <= 1e-10
    x = _inside(cage, 300)
    _check(F.harmonic_coordinates(x, cage, solution=res), x, cage)  # at query points


def test_solvers_agree() -> None:
    dom = mesh_domain(l_shape(), 3000)
    lu, cg = solve_harmonic(dom, "lu"), solve_harmonic(dom, "cg", tol=1e-13)
    assert float((lu.weights - cg.weights).abs().max()) <= 1e-9
    assert lu.residual <= 1e-12
    pytest.importorskip("cholespy")
    ch = solve_harmonic(dom, "cholesky")
    assert float((lu.weights - ch.weights).abs().max()) <= 1e-12 and ch.residual <= 1e-12


def test_convergence_under_refinement() -> None:
    """At fixed points of a convex pentagon (an H^2 solution: P1 converges like h^2), each
    refinement (4x the cells, h / 2) changes the weights (RMS) at least 2x less than the last."""
    cage = tc.Cage(torch.tensor([[0.0, 0], [2, 0], [2, 1], [1, 1.5], [0, 1]], dtype=D64))
    x = _inside(cage, 200, seed=3)
    Ws = [F.harmonic_coordinates(x, cage, target_cells=n) for n in (250, 1000, 4000, 16000)]
    diffs = [float((a - b).square().mean().sqrt()) for a, b in itertools.pairwise(Ws)]
    assert diffs[1] < diffs[0] / 2 and diffs[2] < diffs[1] / 2, diffs


def test_positive_on_a_good_mesh_and_the_report() -> None:
    res = F.solve_harmonic_coordinates(_polygon(), target_cells=1500)
    assert res.min_weight >= -1e-12 and res.negative_vertices == 0  # (2D meshes here: min angle > 20 deg)
    assert res.domain.min_angle > 20


def test_module_and_outside_points() -> None:
    cage = triquad()
    x = _inside(cage, 40)
    m = tc.HarmonicCoordinates(cage, x, target_cells=3000)
    assert torch.allclose(m(cage.vertices), x, atol=1e-10)
    R = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(1), dtype=D64)).Q
    out = m(torch.stack([cage.vertices, cage.vertices @ R.T - 2.0]))
    assert out.shape == (2, 40, 3) and torch.allclose(out[1], x @ R.T - 2.0, atol=1e-10)
    assert "min_weight" in repr(m)
    with pytest.warns(UserWarning, match="outside the meshed interior"):
        F.harmonic_coordinates(torch.tensor([[9.0, 9.0, 9.0]], dtype=D64), cage, solution=m.solution)


@pytest.mark.slow
def test_firehydrant() -> None:
    cage = tc.load_cage(data_path("qmvc", "FireHydrant_Cage.obj")).to(D64)
    res = F.solve_harmonic_coordinates(cage, target_cells=20000)
    _check(res.weights, res.domain.vertices, cage)
    x = _inside(cage, 500)
    _check(F.harmonic_coordinates(x, cage, solution=res), x, cage)


def test_gradients_with_respect_to_the_points() -> None:
    """P1 interpolation: the gradient in a cell is constant, and the gradient of the reproduced
    point ``w @ V`` is the identity."""
    cage = l_shape()
    sol = F.solve_harmonic_coordinates(cage, target_cells=2000)
    x = _inside(cage, 30).requires_grad_(True)
    w = F.harmonic_coordinates(x, cage, solution=sol)
    y = w @ cage.vertices.to(D64)
    for d in range(3):
        (g,) = torch.autograd.grad(y[:, d].sum(), x, retain_graph=True)
        assert torch.allclose(g, torch.eye(3, dtype=D64)[d].expand_as(g), atol=1e-10)
    (g,) = torch.autograd.grad(w[:, 0].sum(), x)
    step = 1e-7  # against differences (inside a cell: exact up to rounding, unless a step crosses a face)
    fd = torch.stack(
        [(F.harmonic_coordinates(x.detach() + step * e, cage, solution=sol)[:, 0]
          - F.harmonic_coordinates(x.detach() - step * e, cage, solution=sol)[:, 0]) / (2 * step)
         for e in torch.eye(3, dtype=D64)], dim=1,
    )  # fmt: skip
    assert float(((g - fd).abs().max(dim=1).values < 1e-6).double().mean()) > 0.9
