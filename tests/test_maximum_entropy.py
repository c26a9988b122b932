"""Maximum entropy coordinates: positivity, partition of unity, linear precision, the box's closed
form, optimality against feasible perturbations, the prior reproduced where it is positive."""

from __future__ import annotations

import pytest
import torch
from support import bent_box, box_cage, l_shape, notched, sample_inside, triquad

import torchcage as tc
from torchcage import functional as F
from torchcage.functional import maximum_entropy_coordinates
from torchcage.geometry import inside_cage
from torchcage.testing import adversarial_points, assert_partition_of_unity

D64 = torch.float64


_inside = sample_inside


def _star() -> tc.Cage:
    ang = torch.arange(12, dtype=D64) * torch.pi / 6
    r = torch.where(torch.arange(12) % 2 == 0, 1.0, 0.4).to(D64)
    return tc.Cage(torch.stack([r * torch.cos(ang), r * torch.sin(ang)], dim=1))


def _check(w: torch.Tensor, x: torch.Tensor, cage: tc.Cage) -> None:
    assert bool(torch.isfinite(w).all())
    assert float(w.min()) >= 0.0
    assert float((w.sum(-1) - 1).abs().max()) <= 1e-12
    lp = (w @ cage.vertices.to(D64) - x).norm(dim=-1).max() / cage.scale
    assert float(lp) <= 1e-10


def test_a_box_with_a_uniform_prior_gives_trilinear_weights() -> None:
    """On a box, entropy is maximal for the product of the 1D two-point laws (fixed by linear
    precision): the trilinear weights, an independent closed form."""
    cage = box_cage()  # [-1, 1]^3, 8 vertices
    x = _inside(cage, 200)
    w = F.maximum_entropy_coordinates(x, cage, prior="uniform")
    t = (x + 1) / 2
    v = (cage.vertices + 1) / 2  # corners in {0, 1}^3
    tri = torch.prod(torch.where(v[None] > 0.5, t[:, None], 1 - t[:, None]), dim=-1)
    assert float((w - tri).abs().max()) <= 1e-12


def test_a_square_with_a_uniform_prior_gives_bilinear_weights() -> None:
    sq = tc.Cage(torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], dtype=D64))
    x = _inside(sq, 100)
    w = F.maximum_entropy_coordinates(x, sq, prior="uniform")
    s, t = x[:, 0], x[:, 1]
    bil = torch.stack([(1 - s) * (1 - t), s * (1 - t), s * t, (1 - s) * t], dim=1)
    assert float((w - bil).abs().max()) <= 1e-12


@pytest.mark.parametrize(
    "name,prior",
    [("l_shape", "mvc"), ("notched", "mvc"), ("l_shape", "uniform"), ("triquad", "qmvc"), ("bent_box", "qmvc")],
)
def test_positive_coordinates_that_reproduce_points(name: str, prior: str) -> None:
    cage = {"l_shape": l_shape, "notched": notched, "triquad": triquad, "bent_box": bent_box}[name]()
    x = _inside(cage, 150)
    r = F.maximum_entropy_coordinates(x, cage, prior=prior, return_info=True)
    _check(r.weights, x, cage)
    assert bool(r.converged.all()) and int(r.iterations.max()) <= 20


def test_2d_polygon() -> None:
    cage = _star()
    x = _inside(cage, 150)
    lam = F.mean_value_coordinates(x, cage)
    assert float(lam.min()) < -1e-4  # the star's MVC have negative weights
    _check(F.maximum_entropy_coordinates(x, cage), x, cage)


def test_the_prior_is_kept_where_it_is_positive() -> None:
    """A convex cage: MVC (and QMVC) are positive coordinates, so they maximise the entropy
    relative to themselves."""
    cage = box_cage()
    x = _inside(cage, 100) * 0.9
    mvc = F.mean_value_coordinates(x, cage.triangulated())
    assert float(mvc.min()) > 0
    r = F.maximum_entropy_coordinates(x, cage.triangulated(), prior="mvc", return_info=True)
    assert float((r.weights - mvc).abs().max()) <= 1e-12 and int(r.iterations.max()) == 0
    qmvc = F.quad_mean_value_coordinates(x, cage)
    assert float((F.maximum_entropy_coordinates(x, cage, prior="qmvc") - qmvc).abs().max()) <= 1e-12


def test_negative_prior_weights_are_removed() -> None:
    cage = l_shape()
    x = _inside(cage, 400, seed=1)
    mvc = F.mean_value_coordinates(x, cage)
    neg = mvc.min(dim=1).values < -1e-4
    assert int(neg.sum()) > 0
    w = F.maximum_entropy_coordinates(x[neg], cage, prior="mvc")
    _check(w, x[neg], cage)


def test_optimal_against_feasible_perturbations() -> None:
    """The relative entropy decreases along every direction that keeps partition of unity and
    linear precision (the null space of ``[1; V^T]``): an optimality check independent of the
    dual."""
    cage = l_shape()
    x = _inside(cage, 5, seed=2)
    m = F.mean_value_coordinates(x, cage).clamp_min(0)
    m = torch.where(m > 0, m, 1e-6 * m.amax(dim=1, keepdim=True))
    w = F.maximum_entropy_coordinates(x, cage, prior=m)
    A = torch.cat([torch.ones(1, cage.num_vertices, dtype=D64), cage.vertices.to(D64).T])  # (4, V)
    null = torch.linalg.svd(A, full_matrices=True).Vh[A.shape[0] :]  # (V - 4, V)

    def entropy(p: torch.Tensor, mi: torch.Tensor) -> torch.Tensor:
        return -(p * (p / mi).log()).sum()

    g = torch.Generator().manual_seed(0)
    for i in range(x.shape[0]):
        e0 = entropy(w[i], m[i])
        for _ in range(20):
            z = null.T @ torch.randn(null.shape[0], generator=g, dtype=D64)
            step = 1e-3 * float(w[i].min()) / float(z.abs().max())
            for s in (step, -step):
                assert float(entropy(w[i] + s * z, m[i])) < float(e0)


def test_points_on_the_cage_get_the_interpolant() -> None:
    cage = box_cage()
    x = torch.tensor([[0.3, -0.2, 1.0], [1.0, 1.0, 0.5], [-1.0, -1.0, -1.0]], dtype=D64)
    w = F.maximum_entropy_coordinates(x, cage, prior="uniform")
    assert torch.allclose(w, F.quad_mean_value_coordinates(x, cage), atol=1e-14)
    _check(w, x, cage)


def test_points_near_the_cage_converge() -> None:
    """Points 1e-3..1e-12 of the size inside the L's re-entrant faces (x = 0, y = 0) and its top:
    the dual's solution grows only like log(1 / distance)."""
    cage = l_shape()
    pts = []
    for d in (1e-3, 1e-6, 1e-9, 1e-12):
        pts += [[0.5, -d, 0.0], [-d, 0.5, 0.0], [0.5, -0.5, 0.5 - d], [-d, -d, 0.0]]
    x = torch.tensor(pts, dtype=D64)
    assert bool(inside_cage(x, cage).all())
    for prior in ("mvc", "uniform"):
        r = F.maximum_entropy_coordinates(x, cage, prior=prior, return_info=True)
        _check(r.weights, x, cage)
        assert bool(r.converged.all()) and int(r.iterations.max()) <= 30, (r.residual, r.iterations)


def test_errors_and_warnings() -> None:
    cage = l_shape()
    with pytest.raises(tc.PointsError, match="outside the cage"):
        F.maximum_entropy_coordinates(torch.tensor([[0.5, 0.5, 0.5]], dtype=D64), cage)  # the L's notch
    with pytest.raises(tc.PointsError, match="not differentiable"):
        F.maximum_entropy_coordinates(torch.zeros(1, 3, dtype=D64).requires_grad_(), cage)
    with pytest.raises(tc.CageError, match="3D cage"):
        F.maximum_entropy_coordinates(torch.zeros(1, 2, dtype=D64), _star(), prior="qmvc")
    with pytest.raises(ValueError, match="prior"):
        F.maximum_entropy_coordinates(torch.zeros(1, 3, dtype=D64) - 0.5, cage, prior="harmonic")
    with pytest.raises(tc.PointsError, match="masses"):
        F.maximum_entropy_coordinates(torch.zeros(1, 3, dtype=D64) - 0.5, cage, prior=torch.ones(2, 12))
    with pytest.warns(RuntimeWarning, match="did not reach"):
        F.maximum_entropy_coordinates(_inside(cage, 10), cage, prior="uniform", max_iter=1)


def test_module() -> None:
    cage = triquad()
    x = _inside(cage, 60)
    m = tc.MaximumEntropyCoordinates(cage, x)
    assert m.weights.shape == (60, cage.num_vertices) and float(m.weights.min()) >= 0
    assert torch.allclose(m(cage.vertices), x, atol=1e-10)
    R = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(0), dtype=D64)).Q
    poses = torch.stack([cage.vertices, cage.vertices @ R.T + 1.0])
    out = m(poses)
    assert out.shape == (2, 60, 3)
    assert torch.allclose(out[1], x @ R.T + 1.0, atol=1e-10)  # rigid motions are reproduced
    assert "prior=None" in repr(m)


def _sheet_samples(cage, k: int, seed: int):
    """Random points on the bilinear quads of ``cage``, their quads, parameters and unit outward
    sheet normals."""
    g = torch.Generator().manual_seed(seed)
    q = cage.vertices[cage.quads]
    qi = torch.randint(0, q.shape[0], (k,), generator=g)
    u, v = (torch.rand(k, 1, dtype=torch.float64, generator=g) for _ in range(2))
    Q = q[qi]
    x = (1 - u) * (1 - v) * Q[:, 0] + u * (1 - v) * Q[:, 1] + u * v * Q[:, 2] + (1 - u) * v * Q[:, 3]
    xu = (1 - v) * (Q[:, 1] - Q[:, 0]) + v * (Q[:, 2] - Q[:, 3])
    xv = (1 - u) * (Q[:, 3] - Q[:, 0]) + u * (Q[:, 2] - Q[:, 1])
    n = torch.nn.functional.normalize(torch.linalg.cross(xu, xv, dim=-1), dim=1)
    return x, qi, u, v, n, g


@pytest.mark.parametrize("seed", [0, 1])
def test_points_on_and_just_inside_bilinear_quads_are_accepted(seed: int) -> None:
    """Points on the bilinear (non-planar) quads of a random triquad cage, and
    1e-10..1e-6 of the size inside them, were refused as outside (the inside test and the on-cage
    test used the quads' split triangles, up to 0.1 of the size away from the sheets here). On the
    sheet: the bilinear weights; inside: nonnegative coordinates reproducing the point."""
    from random_cages import triquad_cage

    cage = triquad_cage(torch.Generator().manual_seed(seed))
    x, qi, u, v, n, g = _sheet_samples(cage, 30, seed)
    w = maximum_entropy_coordinates(x, cage)
    b = torch.cat([(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v], dim=1)
    ref = torch.zeros(x.shape[0], cage.num_vertices, dtype=torch.float64).scatter_add(1, cage.quads[qi], b)
    assert float((w - ref).abs().max()) < 1e-12
    inside = x - n * cage.scale * 10 ** (-10 + 4 * torch.rand(x.shape[0], 1, dtype=torch.float64, generator=g))
    res = maximum_entropy_coordinates(inside, cage, return_info=True)
    assert bool(res.converged.all()) and float(res.weights.min()) >= 0
    assert float((res.weights @ cage.vertices - inside).norm(dim=1).max()) < 1e-12 * cage.scale
    assert_partition_of_unity(res.weights)


def test_float32_points_on_the_cage_are_on_it() -> None:
    """Float32 points on a cage's faces and quads round to just outside it (by
    about eps32 |x|) and were refused; within the rounding of their dtype they are on the cage and
    get its interpolant."""
    from random_cages import triquad_cage

    cage = triquad_cage(torch.Generator().manual_seed(5))
    x, *_ = _sheet_samples(cage, 30, 5)
    tri = adversarial_points(cage, 30, seed=5)["face"]
    for pts in (x.float(), tri.float()):
        w = maximum_entropy_coordinates(pts, cage)
        assert w.dtype == torch.float64 and float(w.min()) >= 0
        assert float((w @ cage.vertices - pts.double()).norm(dim=1).max()) < 1e-6 * cage.scale
    cube = adversarial_points(cage.to(torch.float32), 30, seed=6)["face"]
    w = maximum_entropy_coordinates(cube, cage.to(torch.float32))
    assert w.dtype == torch.float32 and bool(torch.isfinite(w).all())


@pytest.mark.slow
def test_bilinear_quads_and_rounding_sweep() -> None:
    """Random triquad cages, scaled by 1e-3..1e3 and moved by up to 1e6: points on their sheets
    (float64 and float32) and 1e-10..1e-6 of the size inside them, all accepted, nonnegative,
    reproducing the points (to the inputs' rounding), bilinear on the sheets."""
    from random_cages import moved, triquad_cage

    for seed in range(8):
        g = torch.Generator().manual_seed(50 + seed)
        scale = 10 ** (6 * float(torch.rand(1, generator=g)) - 3)
        cage = moved(
            triquad_cage(g, n=2 + seed % 2), g, scale=scale, shift=10 ** (6 * float(torch.rand(1, generator=g)))
        )
        x, qi, u, v, n, g2 = _sheet_samples(cage, 40, seed)
        w = maximum_entropy_coordinates(x, cage)
        b = torch.cat([(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v], dim=1)
        ref = torch.zeros(x.shape[0], cage.num_vertices, dtype=torch.float64).scatter_add(1, cage.quads[qi], b)
        rounding = torch.finfo(torch.float64).eps * float(cage.vertices.abs().max()) / cage.scale
        assert float((w - ref).abs().max()) < 1e-9 + 1e3 * rounding, seed
        inside = x - n * cage.scale * 10 ** (-10 + 4 * torch.rand(x.shape[0], 1, dtype=torch.float64, generator=g2))
        res = maximum_entropy_coordinates(inside, cage, return_info=True)
        assert float(res.weights.min()) >= 0 and bool(res.converged.all()), seed
        assert float((res.weights @ cage.vertices - inside).norm(dim=1).max()) < (1e-12 + 8 * rounding) * cage.scale
        w32 = maximum_entropy_coordinates(x.float(), cage)
        assert float(w32.min()) >= 0
        rounding32 = 8 * torch.finfo(torch.float32).eps * (float(cage.vertices.abs().max()) + cage.scale)
        assert float((w32 @ cage.vertices - x.float().double()).norm(dim=1).max()) < rounding32
