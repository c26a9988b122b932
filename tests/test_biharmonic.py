"""Bounded biharmonic weights: bounds, partition of unity, boundary and Lagrange values, the
certified objective gap, and agreement with an independent solve (numpy assembly, scipy's
L-BFGS-B with bounds)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from support import box_cage, data_path, l_shape, p1_stiffness, triquad
from support import sample_inside as _split_inside

import torchcage as tc
from torchcage import functional as F
from torchcage.solvers.biharmonic import solve_bbw
from torchcage.solvers.domain import mesh_domain

pytest.importorskip("scipy")

D64 = torch.float64


def sample_inside(cage, n: int, seed: int = 0) -> torch.Tensor:
    """Points inside the cage whose quads are bilinear patches (the surface the weights take their
    boundary values on), not split along a diagonal as :func:`support.sample_inside` has it."""
    from torchcage.solvers.domain import inside_bilinear_cage

    x = _split_inside(cage, 2 * n, seed)
    return x[inside_bilinear_cage(x, cage)][:n]


def _polygon() -> tc.Cage:
    return tc.Cage(torch.tensor([[0.0, 0], [2, 0], [2, 1], [1, 1.5], [0.3, 0.6], [0, 1]], dtype=D64))


CAGES = {"polygon": _polygon, "cube": box_cage, "l_shape": l_shape, "triquad": triquad}


def _energy_parts(dom) -> tuple:
    """The biharmonic energy assembled independently: ``Q = K M^-1 K`` with ``K`` from
    :func:`support.p1_stiffness` and the lumped mass from the cells' ``[1, x]`` determinants."""
    from scipy.sparse import diags

    v, cells = dom.vertices.numpy(), dom.cells.numpy()
    k = cells.shape[1]
    M = np.concatenate([np.ones((cells.shape[0], k, 1)), v[cells]], axis=2)
    vol = np.abs(np.linalg.det(M)) / np.prod(np.arange(1, k))
    mass = np.bincount(cells.ravel(), np.repeat(vol / k, k), minlength=v.shape[0])
    K = p1_stiffness(v, cells)
    return (K @ diags(1.0 / mass) @ K).tocsr()


def _reference(Q, dom, j: int) -> tuple[np.ndarray, float]:
    """Cage vertex ``j``'s box QP by L-BFGS-B (scipy), run to its limits: ``(w at all vertices,
    energy)``."""
    from scipy.optimize import minimize

    I, B = dom.interior.numpy(), dom.boundary.numpy()
    b = dom.boundary_values.numpy()[:, j]
    QII, c = Q[I][:, I], Q[I][:, B] @ b
    const = 0.5 * b @ (Q[B][:, B] @ b)
    fun = lambda w: (0.5 * w @ (QII @ w) + c @ w + const, QII @ w + c)  # noqa: E731
    r = minimize(fun, np.full(I.size, 0.1), jac=True, method="L-BFGS-B", bounds=[(0.0, 1.0)] * I.size,
                 options={"ftol": 1e-16, "gtol": 1e-13, "maxiter": 50000, "maxcor": 30})  # fmt: skip
    w = np.zeros(dom.vertices.shape[0])
    w[B], w[I] = b, r.x
    return w, float(r.fun)


@pytest.mark.parametrize("name", list(CAGES))
def test_properties_and_an_independent_solve(name: str) -> None:
    cage = CAGES[name]()
    dom = mesh_domain(cage, 500 if cage.dim == 2 else 1500)
    res = solve_bbw(dom, tol=1e-8)
    W, V = res.weights, cage.num_vertices
    assert res.converged and float(res.gap.max()) <= 1e-8 and res.iterations > 0  # (the bounds are active)
    assert float(W.min()) >= 0.0 and float(W.max()) <= 1.0  # bounds: exact (the iterate is a clamp)
    assert float(res.raw_weights.min()) >= 0.0 and float(res.raw_weights.max()) <= 1.0
    assert float((W.sum(1) - 1).abs().max()) <= 1e-12  # partition of unity
    assert torch.equal(W[dom.boundary], dom.boundary_values) and torch.equal(
        res.raw_weights[dom.boundary], dom.boundary_values
    )  # boundary values exact, before and after the division
    assert torch.equal(W[:V], torch.eye(V, dtype=D64))  # Lagrange at the cage vertices
    Q = _energy_parts(dom)
    for j in (0, V // 2, V - 1):
        w_ref, e_ref = _reference(Q, dom, j)
        w = res.raw_weights[:, j].numpy()
        e = 0.5 * w @ (Q @ w)
        # the certificate: no feasible point, the reference included, is below (1 - gap) E(w)
        assert e_ref >= e * (1 - float(res.gap[j])) - 1e-12 * e
        assert abs(e - e_ref) <= 3e-8 * e  # the same minimum (measured: 5e-9 at most)
        assert float(np.abs(w - w_ref).max()) <= 5e-4  # and the same minimiser (measured: 6e-5 at most)
    x = sample_inside(cage, 200)
    wx = F.bounded_biharmonic_weights(x, cage, solution=res)
    assert float(wx.min()) >= 0.0 and float((wx.sum(1) - 1).abs().max()) <= 1e-12


def test_the_gap_bounds_the_objective_error() -> None:
    """Loose and tight solves: the loose one's energy is within its certified gap of the tight
    one's, and the gaps shrink with the tolerance."""
    dom = mesh_domain(l_shape(), 3000)
    loose, tight = solve_bbw(dom, tol=1e-3), solve_bbw(dom, tol=1e-9)
    assert loose.iterations < tight.iterations
    assert bool((tight.energy <= loose.energy * (1 + 1e-12)).all())
    assert bool(((loose.energy - tight.energy) / loose.energy <= loose.gap + 1e-12).all())
    assert float(loose.gap.max()) <= 1e-3 and float(tight.gap.max()) <= 1e-9


def test_non_convergence_warns_and_bad_options_raise() -> None:
    dom = mesh_domain(_polygon(), 400)
    with pytest.warns(UserWarning, match="raise max_iter"):
        r = solve_bbw(dom, max_iter=3, check_every=1)
    assert not r.converged and r.iterations == 3 and float(r.weights.min()) >= 0.0
    for bad in ({"tol": 0.0}, {"tol": float("nan")}, {"rho": -1.0}, {"solver": "qr"}, {"max_iter": 0}):
        with pytest.raises(ValueError):
            solve_bbw(dom, **bad)
    seen = []
    solve_bbw(dom, progress=lambda it, gap: seen.append((it, gap)))
    assert seen and seen[-1][1] <= 1e-5


def test_lu_and_cholesky_agree() -> None:
    pytest.importorskip("cholespy")
    dom = mesh_domain(box_cage(), 1500)
    a, b = solve_bbw(dom, solver="lu", tol=1e-9), solve_bbw(dom, solver="cholesky", tol=1e-9)
    assert float((a.weights - b.weights).abs().max()) <= 1e-4
    assert float(((a.energy - b.energy) / a.energy).abs().max()) <= 2e-9


def test_module_translation_and_outside_points() -> None:
    cage = triquad()
    x = sample_inside(cage, 40)
    m = tc.BoundedBiharmonicWeights(cage, x, target_cells=1500)
    assert m.weights.shape == (40, cage.num_vertices)
    shift = torch.tensor([0.3, -2.0, 1.0], dtype=D64)
    out = m(torch.stack([cage.vertices, cage.vertices + shift]))
    assert out.shape == (2, 40, 3)
    assert torch.allclose(out[0], x, atol=1e-12) and torch.allclose(out[1], x + shift, atol=1e-12)  # displacements
    pose = cage.vertices * torch.tensor([1.5, 1.0, 0.8], dtype=D64)
    plain = tc.BoundedBiharmonicWeights(cage, x, solution=m.solution, displacements=False)
    assert torch.allclose(plain(pose), m.weights @ pose, atol=1e-14)
    assert torch.allclose(m(pose), x + m.weights @ (pose - cage.vertices), atol=1e-12)
    assert float((plain(cage.vertices) - x).abs().max()) > 1e-3  # (no linear precision: why displacements)
    assert "gap" in repr(m) and "displacements=False" in repr(plain)
    f32 = tc.BoundedBiharmonicWeights(cage, x.float(), solution=m.solution, dtype=torch.float32)
    assert f32(cage.vertices.float()).dtype == torch.float32
    assert torch.allclose(f32(cage.vertices.float()).double(), x, atol=1e-5)
    with pytest.warns(UserWarning, match="outside the meshed interior"):
        F.bounded_biharmonic_weights(torch.tensor([[9.0, 9.0, 9.0]], dtype=D64), cage, solution=m.solution)


def test_build_module() -> None:
    from torchcage.methods import build_module

    cage = box_cage()
    x = sample_inside(cage, 10)
    seen = []
    m = build_module("bbw", cage, x, progress=lambda done, total, msg: seen.append(msg))
    assert isinstance(m, tc.BoundedBiharmonicWeights) and seen
    assert torch.allclose(m(cage.vertices), x, atol=1e-12) and torch.allclose(m(cage.vertices + 1.0), x + 1.0)


@pytest.mark.slow
def test_firehydrant() -> None:
    cage = tc.load_cage(data_path("qmvc", "FireHydrant_Cage.obj")).to(D64)
    dom = mesh_domain(cage, 80000)  # (about 20,000 mesh vertices, the benchmark's mesh)
    res = solve_bbw(dom)
    assert res.converged and float(res.gap.max()) <= 1e-5
    W = res.weights
    assert float(W.min()) >= 0.0 and float(W.max()) <= 1.0 and float((W.sum(1) - 1).abs().max()) <= 1e-12
    assert torch.equal(W[dom.boundary], dom.boundary_values)
    tight = solve_bbw(dom, tol=1e-8)  # the objective within 0.1% of a tight solve (the target)
    assert bool(((res.energy - tight.energy) / tight.energy <= 1e-3).all())


def test_cli(tmp_path) -> None:
    """``torchcage deform --method bbw`` writes what the module gives for the same pose."""
    from support import cube_files

    from torchcage.cli import main

    args = cube_files(tmp_path)
    assert main([*args, "--out", str(tmp_path / "bbw"), "--method", "bbw", "--no-picture"]) == 0
    rest, _ = tc.load_mesh(tmp_path / "bbw" / "rest_mesh.obj")
    moved, _ = tc.load_mesh(tmp_path / "bbw" / "deformed_mesh.obj")
    cage, pose = tc.load_cage(tmp_path / "cage.obj"), tc.load_cage(tmp_path / "pose.obj")
    expect = tc.BoundedBiharmonicWeights(cage, rest.to(D64))(pose.vertices.to(D64))
    assert torch.allclose(moved.to(D64), expect, atol=1e-5)  # (the OBJ's printed digits)
