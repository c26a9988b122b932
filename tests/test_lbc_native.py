"""LBC's ADMM iterations in the native library (``torchcage/backends/native/lbc.c``) against the torch
loop of :func:`~torchcage.solvers.lbc.solve_lbc`: the same iterates to rounding (2D and 3D meshes, fixed
and adaptive penalty, after few and many iterations), the same residual history and penalties, and
iterates that do not depend on the thread count."""

from __future__ import annotations

import warnings

import pytest
import torch
from support import box_cage, data_path, l_shape

import torchcage
from torchcage.backends import native
from torchcage.solvers import lbc
from torchcage.solvers.domain import mesh_domain
from torchcage.solvers.lbc import LBCResult, solve_lbc

pytest.importorskip("scipy")
pytestmark = pytest.mark.native  # (skipped where no native library loads)


def _lbc2d(name: str) -> torchcage.Cage:
    v = [[float(t) for t in line.split()[1:3]] for line in open(data_path("lbc2d", f"{name}-control-edgeset.obj"))
         if line.startswith("v ")]  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torchcage.Cage(torch.tensor(v, dtype=torch.float64))


def _star() -> torchcage.Cage:
    """A non-convex 2D polygon (ten vertices), counter-clockwise."""
    k = torch.arange(10, dtype=torch.float64)
    r = torch.where(k % 2 == 0, 1.0, 0.45)
    a = k * torch.pi / 5
    return torchcage.Cage(torch.stack([r * torch.cos(a), r * torch.sin(a)], dim=1))


def _both(monkeypatch: pytest.MonkeyPatch, domain, cage: torchcage.Cage, **options) -> tuple[LBCResult, LBCResult]:
    """The solve with the native iterations, then with the torch loop (the library hidden)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (a run to max_iter that did not converge)
        fast = solve_lbc(domain, cage.vertices, **options)
        with monkeypatch.context() as mp:
            mp.setattr(native, "library", lambda: None)
            slow = solve_lbc(domain, cage.vertices, **options)
    return fast, slow


def _assert_same(fast: LBCResult, slow: LBCResult, tol: float) -> None:
    assert fast.iterations == slow.iterations and fast.converged == slow.converged
    assert fast.mu == slow.mu
    assert len(fast.history) == len(slow.history)
    for a, b in zip(fast.history, slow.history, strict=True):
        assert a[0] == b[0] and a[3] == b[3]  # iteration, penalty
        # (the residuals are norms of differences: near convergence, rounding is a larger part of them)
        assert a[1] == pytest.approx(b[1], rel=1e-9, abs=1e-10) and a[2] == pytest.approx(b[2], rel=1e-9, abs=1e-10)
    assert float((fast.weights - slow.weights).abs().max()) <= tol
    assert fast.objective == pytest.approx(slow.objective, rel=1e-10)


CASES = {
    "star": lambda: (_star(), 250),
    "cactus": lambda: (_lbc2d("cactus"), 1500),
    "cube": lambda: (box_cage(), 300),
    "l_shape": lambda: (l_shape(), 300),
}


@pytest.mark.parametrize("name", list(CASES))
def test_native_iterations_equal_the_torch_loop(name, monkeypatch) -> None:
    cage, cells = CASES[name]()
    d = mesh_domain(cage, cells)
    for iterations in (1, 50):
        fast, slow = _both(monkeypatch, d, cage, mu=10.0, adaptive=False, eps_primal=0, eps_dual=0,
                           max_iter=iterations, report_every=10)  # fmt: skip
        _assert_same(fast, slow, 1e-12)


@pytest.mark.parametrize("name", ["star", "cube"])
def test_native_iterations_with_the_adaptive_penalty(name, monkeypatch) -> None:
    # the default solve: residual checks every 50 iterations, the penalty balanced, stopped at the
    # tolerances (the same iteration, the same penalties)
    cage, cells = CASES[name]()
    d = mesh_domain(cage, cells)
    fast, slow = _both(monkeypatch, d, cage)
    assert fast.converged and len({h[3] for h in fast.history}) > 1  # (the penalty moved)
    _assert_same(fast, slow, 1e-10)


@pytest.mark.parametrize("name", ["cactus", "l_shape"])
def test_native_iterations_equal_the_torch_loop_after_1000(name, monkeypatch) -> None:
    cage, cells = CASES[name]()
    d = mesh_domain(cage, cells)
    fast, slow = _both(monkeypatch, d, cage, mu=10.0, adaptive=False, eps_primal=0, eps_dual=0, max_iter=1000,
                       report_every=10)  # fmt: skip
    _assert_same(fast, slow, 1e-10)


def test_native_iterates_do_not_depend_on_the_thread_count(monkeypatch) -> None:
    monkeypatch.setattr(lbc, "_NATIVE_PARALLEL_MIN", 0)  # (threads for any size)
    cage = box_cage()
    d = mesh_domain(cage, 300)
    before = torch.get_num_threads()
    out = []
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                out.append(solve_lbc(d, cage.vertices, eps_primal=0, eps_dual=0, max_iter=120).weights)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(out[0], out[1])
