"""Local barycentric coordinates: the constraints (non-negativity, partition of unity,
reproduction, Lagrange property, bilinear boundary values on quads), optimality against a long
tight solve, convergence reporting, locality against mean value coordinates, the sparse module."""

from __future__ import annotations

import io
import math
import warnings

import pytest
import torch
from support import box_cage, data_path, l_shape

import torchcage
from torchcage import functional as F
from torchcage.solvers.domain import inside_bilinear_cage, mesh_domain
from torchcage.solvers.lbc import solve_lbc

pytest.importorskip("scipy")

LBC2D = ["Gil_Gecko", "LBClogo", "cactus", "woody"]


def load_lbc2d(name: str) -> torchcage.Cage:
    """The polygon of one of the paper's 2D cages: its ``v`` lines, in order (they run clockwise;
    the Cage orients the edges and keeps the vertex order)."""
    v = [[float(t) for t in line.split()[1:3]] for line in open(data_path("lbc2d", f"{name}-control-edgeset.obj"))
         if line.startswith("v ")]  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torchcage.Cage(torch.tensor(v, dtype=torch.float64))


def check_constraints(W: torch.Tensor, cage: torchcage.Cage, X: torch.Tensor, tol: float = 1e-6) -> None:
    W = W.to_dense() if W.layout != torch.strided else W
    assert float(W.min()) >= -1e-6
    assert float((W.sum(dim=1) - 1).abs().max()) <= tol
    assert float((W @ cage.vertices.to(W.dtype) - X).norm(dim=1).max()) <= tol * cage.scale


def random_inside(cage: torchcage.Cage, n: int, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    lo, hi = cage.vertices.min(0).values, cage.vertices.max(0).values
    x = lo + (hi - lo) * torch.rand((4 * n, cage.dim), dtype=torch.float64, generator=gen)
    return x[inside_bilinear_cage(x, cage)][:n]  # (quads: inside their bilinear patches)


@pytest.mark.parametrize(
    "name", [*LBC2D[:2], *(pytest.param(n, marks=pytest.mark.slow) for n in LBC2D[2:])]
)  # the two larger cages in the slow tier
def test_2d_cages_of_the_paper(name):
    cage = load_lbc2d(name)
    result = F.solve_local_barycentric(cage, target_cells=1200)
    assert result.converged and result.iterations < 5000
    W, d = result.weights, result.domain
    check_constraints(W, cage, d.vertices)
    V = cage.num_vertices
    assert torch.equal(W[:V], torch.eye(V, dtype=torch.float64))  # Lagrange property, exactly
    x = random_inside(cage, 300)
    check_constraints(F.local_barycentric_coordinates(x, cage, solution=result), cage, x)
    check_constraints(F.local_barycentric_coordinates(x, cage, solution=result, threshold=0), cage, x)


@pytest.mark.parametrize(
    "make",
    [lambda: box_cage(), lambda: l_shape(), lambda: torchcage.load_cage(data_path("qmvc", "ManHead_Cage.obj")),
     pytest.param(lambda: torchcage.load_cage(data_path("qmvc", "FireHydrant_Cage.obj")), marks=pytest.mark.slow)],
    ids=["cube", "l_shape", "ManHead", "FireHydrant"],
)  # fmt: skip
def test_3d_cages(make):
    cage = make()
    result = F.solve_local_barycentric(cage, target_cells=1500)
    assert result.converged
    W, d = result.weights, result.domain
    check_constraints(W, cage, d.vertices)
    V = cage.num_vertices
    assert torch.equal(W[:V], torch.eye(V, dtype=torch.float64))
    x = random_inside(cage, 200)
    check_constraints(F.local_barycentric_coordinates(x, cage, solution=result), cage, x)


def test_quads_get_bilinear_boundary_values():
    """Boundary samples on a non-planar quad carry the bilinear weights of their parameters."""
    cage = box_cage()
    v = cage.vertices.clone()
    v[0] += torch.tensor([0.0, -0.3, 0.2], dtype=torch.float64)  # bend the faces at vertex 0
    cage = torchcage.Cage(v, cage.quads)
    d = mesh_domain(cage, 600)
    B = d.boundary_values
    assert torch.allclose(B @ cage.vertices, d.vertices[d.boundary], atol=1e-14)  # points on the patches
    # on quads, the values are bilinear: at most 4 non-zeros, the products of two linear factors
    quad_pts = (B > 0).sum(dim=1) == 4
    assert bool(quad_pts.any())
    for q in cage.quads.tolist():
        rows = quad_pts & (B[:, q].sum(dim=1) > 1 - 1e-12)
        w = B[rows][:, q]  # (n, 4) = (1-u)(1-v), u(1-v), uv, (1-u)v
        assert torch.allclose(w[:, 0] * w[:, 2], w[:, 1] * w[:, 3], atol=1e-14)


@pytest.mark.slow
def test_objective_matches_a_long_tight_solve():
    cage = load_lbc2d("LBClogo")
    d = mesh_domain(cage, 500)
    default = solve_lbc(d, cage.vertices)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the tight run stops at max_iter
        tight = solve_lbc(d, cage.vertices, eps_primal=1e-13, eps_dual=1e-13, max_iter=8000)
    assert default.converged
    assert default.objective <= tight.objective * 1.001
    # and the solve does optimise: the plain harmonic-like start is much worse
    assert tight.objective < 0.9 * solve_lbc(d, cage.vertices, max_iter=1, eps_primal=1.0).objective


def test_convergence_is_reported():
    cage = load_lbc2d("cactus")
    d = mesh_domain(cage, 400)
    with pytest.warns(UserWarning, match="without converging"):
        r = solve_lbc(d, cage.vertices, max_iter=20, report_every=10)
    assert not r.converged and r.iterations == 20 and r.primal_residual > 0 and len(r.history) == 2
    seen = []
    solve_lbc(d, cage.vertices, progress=lambda it, p, q: seen.append(it), report_every=25)
    assert seen and seen[0] == 25


def test_weighting_controls_locality():
    """Quadratic weighting is more local than plain total variation, and both far more than MVC."""
    cage = load_lbc2d("cactus")
    d = mesh_domain(cage, 1200)
    measure = torch.zeros(d.vertices.shape[0], dtype=torch.float64)
    measure.index_add_(0, d.cells.reshape(-1), d.cell_volumes().repeat_interleave(3) / 3)
    quad = solve_lbc(d, cage.vertices, weighting="quadratic").weights
    const = solve_lbc(d, cage.vertices, weighting="constant").weights
    mvc = F.mean_value_coordinates(d.vertices, cage)
    V = cage.num_vertices
    count = [(w.abs() > 1e-3 / V).sum(dim=1).double().median() for w in (quad, const, mvc)]
    assert count[0] <= count[1] < count[2]
    ts = torch.logspace(-6, -2, 20, dtype=torch.float64)  # "where is a coordinate negligible?"
    _, P_quad, Q_quad = F.locality_statistics(quad, measure, ts)
    _, P_mvc, Q_mvc = F.locality_statistics(mvc, measure, ts)
    assert float(Q_quad[8]) < 0.5 * float(Q_mvc[8])
    assert bool((P_quad >= P_mvc).all())


def test_user_domain_and_errors():
    cage = l_shape()
    d = mesh_domain(cage, 800)
    r = F.solve_local_barycentric(cage, domain=(d.vertices, d.cells))
    check_constraints(r.weights, cage, r.domain.vertices)
    with pytest.raises(torchcage.CageError, match="not vertices of the domain mesh"):
        F.solve_local_barycentric(cage, domain=(d.vertices[cage.num_vertices :], d.cells - cage.num_vertices))
    with pytest.raises(ValueError, match="weighting must be one of"):
        F.solve_local_barycentric(cage, weighting="cubic", target_cells=100)
    with pytest.raises(ValueError, match="threshold must be >= 0"):
        F.local_barycentric_coordinates(torch.zeros(1, 3, dtype=torch.float64), cage, threshold=-1.0, solution=r)
    with pytest.raises(torchcage.PointsError, match="NaN or inf"):
        F.local_barycentric_coordinates(torch.full((1, 3), math.nan), cage, solution=r)


def test_module_round_trip_and_gradients():
    cage = load_lbc2d("LBClogo")
    x = random_inside(cage, 100)
    lbc = torchcage.LocalBarycentricCoordinates(cage, x, target_cells=600)
    assert lbc.weights.layout == torch.sparse_csr and lbc.weight_values.numel() < x.shape[0] * cage.num_vertices
    # similarity and affine motions are reproduced (linear precision), batched
    A = torch.tensor([[1.2, 0.3], [-0.2, 0.9]], dtype=torch.float64)
    t = torch.tensor([3.0, -1.0], dtype=torch.float64)
    moved = torch.stack([cage.vertices @ A.T + t, cage.vertices])
    out = lbc(moved)
    assert out.shape == (2, 100, 2)
    assert torch.allclose(out[0], x @ A.T + t, atol=1e-6 * cage.scale)
    # state_dict round trip through torch.save
    buf = io.BytesIO()
    torch.save(lbc.state_dict(), buf)
    buf.seek(0)
    other = torchcage.LocalBarycentricCoordinates(cage, x, solution=lbc.solution)
    other.load_state_dict(torch.load(buf))
    assert torch.equal(other(moved), out)
    # gradients with respect to the deformed vertices
    v = moved[0].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda v: lbc(v), (v,))
    with pytest.raises(ValueError, match="vertices must have shape"):
        lbc(moved[..., :1])


def test_sparse_deformation_is_cheaper_than_dense_mvc():
    """Memory: the sparse weights hold far fewer entries than dense MVC for a 27-vertex cage."""
    cage = load_lbc2d("cactus")
    x = random_inside(cage, 2000)
    W = F.local_barycentric_coordinates(x, cage, target_cells=1200)
    assert W.values().numel() < 0.3 * x.shape[0] * cage.num_vertices


def test_conjugate_gradient_y_step_matches_the_factorisation():
    """The torch CG Y step (any device) reaches the same solution as the sparse LU one."""
    cage = l_shape()
    d = mesh_domain(cage, 400)
    lu = solve_lbc(d, cage.vertices, linear_solver="lu")
    cg = solve_lbc(d, cage.vertices, linear_solver="cg")
    assert cg.converged and abs(cg.iterations - lu.iterations) <= 100
    assert float((cg.weights - lu.weights).abs().max()) <= 1e-6
    assert abs(cg.objective - lu.objective) <= 1e-6 * lu.objective
    with pytest.raises(ValueError, match="linear_solver must be"):
        solve_lbc(d, cage.vertices, linear_solver="qr")


def test_lbc_on_a_sliver_cage_with_dangling_mesh_vertices() -> None:
    """The mesher leaves vertices in no cell next to the sliver cube's
    sliver; their infinite geodesic distance made every normalised distance 0, the ADMM penalty 0
    and the solve a ZeroDivisionError. Distances are now normalised over the cells' vertices."""
    from torchcage.testing import sliver_cube

    cage = sliver_cube()
    x = torch.tensor([[0.1, 0.2, -0.3], [0.5, -0.5, 0.9], [-0.9, 0.0, -0.95]], dtype=torch.float64)
    w = F.local_barycentric_coordinates(x, cage, target_cells=1500).to_dense()
    assert bool((w >= 0).all())
    assert float((w.sum(1) - 1).abs().max()) < 1e-12
    assert float((w @ cage.vertices - x).abs().max()) < 1e-10


def test_lbc_points_on_the_cage_faces_are_located() -> None:
    """Points on the cube's faces beside a flat boundary
    cell (far centroid) were not found in 48 candidate cells and got the clamped coordinates of
    another cell, 1e-2 away. The search now widens to 384 candidates, and clamped points take the
    nearest clamped candidate."""
    from torchcage.testing import adversarial_points

    cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
    sol = F.solve_local_barycentric(cube, target_cells=1500)
    x = adversarial_points(cube, 9000, seed=0)["face"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        w = F.local_barycentric_coordinates(x, cube, solution=sol).to_dense()
    assert float((w @ cube.vertices - x).norm(dim=1).max()) < 1e-12


def test_lbc_partition_of_unity_after_dropping_small_entries() -> None:
    """The reproduction correction after small entries are dropped left the sums off by
    2e-10 (raw coordinates), then 2e-12 (centred and scaled); rows are now renormalised exactly."""
    from torchcage.geometry import inside_cage
    from torchcage.testing import adversarial_points

    blob = torchcage.load_cage(torchcage.data.path("blob2d.obj"))
    sol = F.solve_local_barycentric(blob, target_cells=800)
    pts = adversarial_points(blob, 300, seed=1)
    x = torch.cat([pts["near_vertex"], pts["near_edge"], pts["edge"]])
    x = x[inside_cage(x, blob)]
    w = F.local_barycentric_coordinates(x, blob, solution=sol).to_dense()
    assert float((w.sum(1) - 1).abs().max()) < 1e-14
    assert float((w @ blob.vertices - x).norm(dim=1).max()) < 1e-10 * blob.scale
    assert bool((w >= 0).all())
