"""Variational MVC (Sec. 8.2-8.3 of Thiery et al. 2014): rigid motions reproduced from their
constraints, batching, convergence of the fitted rotations, scalar fields from value and gradient
constraints."""

from __future__ import annotations

import math

import pytest
import torch
from support import HANDMADE

import torchcage
from torchcage.geometry import inside_cage
from torchcage.variational import VariationalMVC, cotangent_laplacian, design_scalar_field

f64 = torch.float64


def _inside(cage: torchcage.Cage, n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    v = cage.vertices.to(f64)
    lo, hi = v.min(0).values, v.max(0).values
    x = lo + (hi - lo) * torch.rand(40 * n, cage.dim, generator=g, dtype=f64)
    if cage.dim == 3:
        x = x[inside_cage(x, cage)]
    else:
        from torchcage.geometry import inside_polygon

        x = x[inside_polygon(x, v, cage.edges)]
    return x[:n]


def _rotation(D: int, seed: int) -> torch.Tensor:
    Q = torch.linalg.qr(torch.randn(D, D, dtype=f64, generator=torch.Generator().manual_seed(seed)))[0]
    if torch.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return Q


def _star() -> torchcage.Cage:
    ang = torch.arange(14, dtype=f64) * math.pi / 7
    r = torch.where(torch.arange(14) % 2 == 0, 1.0, 0.5).double()
    return torchcage.Cage(torch.stack([r * torch.cos(ang), r * torch.sin(ang)], dim=1))


@pytest.mark.parametrize("name", ["l_shape", "star"])
def test_rigid_motion_is_reproduced_with_fitted_rotations(name):
    cage = _star() if name == "star" else HANDMADE[name]()
    D = cage.dim
    solver = VariationalMVC(cage, _inside(cage, 6, 0), _inside(cage, 10, 1), _inside(cage, 10, 2))
    R, t = 1.0 * _rotation(D, 4), torch.arange(1, D + 1, dtype=f64)
    res = solver.solve(solver.handles @ R.T + t, rotations="fit")
    expected = cage.vertices.to(f64) @ R.T + t
    assert res.converged and res.iterations <= 5
    assert (res.vertices - expected).abs().max() <= 1e-8
    assert res.positional_residual <= 1e-8 and res.energy <= 1e-16
    assert (res.rotations - R).abs().max() <= 1e-8


def test_batched_constraint_sets_and_given_rotations():
    cage = HANDMADE["l_shape"]()
    solver = VariationalMVC(cage, _inside(cage, 5, 0), _inside(cage, 8, 1), _inside(cage, 8, 2))
    R = torch.stack([_rotation(3, 5), _rotation(3, 6)])
    t = torch.tensor([[0.0, 0, 1], [2, 0, 0]], dtype=f64)
    targets = torch.einsum("bij,pj->bpi", R, solver.handles) + t[:, None]
    batch = solver.solve(targets, rotations=R[:, None].expand(2, 8, 3, 3))
    for b in range(2):
        one = solver.solve(targets[b], rotations=R[b])
        assert torch.allclose(batch.vertices[b], one.vertices, atol=1e-12)
        assert (one.vertices - (cage.vertices.to(f64) @ R[b].T + t[b])).abs().max() < 1e-8


def test_fitting_decreases_the_energy_and_reports_convergence():
    """A non-rigid edit (one end moved): the local/global iteration never increases the energy."""
    cage = HANDMADE["l_shape"]()
    handles = _inside(cage, 6, 3)
    solver = VariationalMVC(cage, handles, _inside(cage, 20, 4), _inside(cage, 20, 5))
    targets = handles.clone()
    targets[handles[:, 0] > 0, 2] += 0.3
    res = solver.solve(targets, rotations="fit", max_iter=500, tol=1e-6)
    e = torch.stack(res.history)[:, 0]
    assert (e[1:] <= e[:-1] * (1 + 1e-12)).all()
    assert res.converged and res.iterations < 500
    short = solver.solve(targets, rotations="fit", max_iter=2)
    assert not short.converged and short.iterations == 2


def test_variational_errors():
    cage = HANDMADE["cube"]()
    solver = VariationalMVC(cage, _inside(cage, 5, 0), _inside(cage, 4, 1))
    with pytest.raises(ValueError, match="targets must have shape"):
        solver.solve(torch.zeros(4, 3, dtype=f64))
    with pytest.raises(ValueError, match="rotations must be"):
        solver.solve(solver.handles, rotations="guess")
    with pytest.raises(ValueError, match="NaN"):
        solver.solve(torch.full((5, 3), float("nan"), dtype=f64))


def test_scalar_field_reproduces_linear_functions():
    """With consistent value and gradient constraints of a linear function (and no smoothness),
    the minimiser is the linear function itself: MVC and their gradients reproduce it."""
    cage = HANDMADE["l_shape"]()
    a, b = torch.tensor([0.3, -1.2, 2.0], dtype=f64), 0.7
    xv, xg = _inside(cage, 12, 0), _inside(cage, 6, 1)
    res = design_scalar_field(cage, xv, xv @ a + b, xg, a.expand(6, 3), smoothness_weight=0.0)
    assert (res.values - (cage.vertices.to(f64) @ a + b)).abs().max() < 1e-8
    assert res.value_residual < 1e-9 and res.gradient_residual < 1e-9


def test_scalar_field_gradient_constraints_take_effect():
    cage = HANDMADE["cube"]()
    xv = torch.tensor([[0.0, 0, -0.6], [0.0, 0, 0.6]], dtype=f64)
    xg = torch.tensor([[0.0, 0.0, 0.0]], dtype=f64)
    target = torch.tensor([[0.0, 0, 4.0]], dtype=f64)
    plain = design_scalar_field(cage, xv, torch.tensor([0.0, 1.0]), xg, target, gradient_weight=0.0)
    steered = design_scalar_field(cage, xv, torch.tensor([0.0, 1.0]), xg, target, gradient_weight=10.0)
    assert steered.gradient_residual < 0.5 * plain.gradient_residual
    const = design_scalar_field(cage, xv, torch.tensor([2.0, 2.0]))
    assert (const.values - 2.0).abs().max() < 1e-9


def test_cotangent_laplacian_kernel_and_symmetry():
    for cage in (HANDMADE["cube"](), _star()):
        L = cotangent_laplacian(cage)
        assert L.sum(1).abs().max() < 1e-12
        v = cage.vertices.to(f64)
        area_weighted = L * (1 / L.diagonal().abs())[:, None]
        assert torch.isfinite(area_weighted).all()
        if cage.dim == 2:  # a polygon: second differences of a linear function vanish at straight vertices only
            continue
        # on the cube the cotangent weights of each face's diagonal vanish (right angles)
        assert (L[0] != 0).sum() <= 7
        assert torch.isfinite(L @ v).all()
