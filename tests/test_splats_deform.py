"""Deforming Gaussian splats with a cage and mapping deformed-space samples back to rest space."""

from __future__ import annotations

import math
import warnings

import pytest
import torch
from support import data_path

import torchcage
from torchcage.geometry import inside_cage
from torchcage.splats import DeformGaussians, GaussianScene, eval_sh, quaternion_to_matrix, rest_points
from torchcage.splats.inverse import _map
from torchcage.splats.linalg import closest_rotation, matrix_to_quaternion, svd3

D64 = torch.float64
METHODS = ("mvc", "gc")


def _cube() -> torchcage.Cage:
    return torchcage.load_cage(torchcage.data.path("cube.obj")).to(D64)


def _scene(n: int = 80, degree: int = 3, seed: int = 0) -> GaussianScene:
    return GaussianScene.random(n, degree=degree, seed=seed, box=(-0.6, 0.6), dtype=D64)


def _similarity(seed: int) -> tuple[float, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    R = quaternion_to_matrix(torch.randn(4, generator=g, dtype=D64))
    return 0.3 + 2 * float(torch.rand(1, generator=g)), R, 5 * torch.randn(3, generator=g, dtype=D64)


@pytest.mark.parametrize("method", METHODS)
def test_rest_pose_changes_nothing(method: str) -> None:
    scene = _scene()
    out = DeformGaussians(_cube(), scene, method=method, chunk_size=17)(_cube().vertices)
    assert float((out.means - scene.means).abs().max()) < 1e-12
    assert float((out.covariances - scene.covariances()).abs().max()) < 1e-12
    assert float((out.sh - scene.sh).abs().max()) < 1e-12
    R = quaternion_to_matrix(out.rotations)
    rebuilt = R * torch.exp(2 * out.log_scales)[..., None, :] @ R.transpose(-1, -2)
    assert float((rebuilt - scene.covariances()).abs().max()) < 1e-12


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("seed", [0, 1])
def test_similarity_moves_every_gaussian_exactly(method: str, seed: int) -> None:
    """Centre a R mu + t, covariance a^2 R Sigma R^T, colour c(R^T d): 1e-10 in float64."""
    cage, scene = _cube(), _scene(seed=seed)
    a, R, t = _similarity(seed)
    out = DeformGaussians(cage, scene, method=method)(a * cage.vertices @ R.T + t)
    assert float((out.means - (a * scene.means @ R.T + t)).abs().max()) < 1e-10 * a
    cov = a * a * R @ scene.covariances() @ R.T
    assert float((out.covariances - cov).abs().max()) < 1e-10 * a * a
    g = torch.Generator().manual_seed(seed + 7)
    d = torch.nn.functional.normalize(torch.randn(scene.num_gaussians, 3, generator=g, dtype=D64), dim=-1)
    assert float((eval_sh(out.sh, d) - eval_sh(scene.sh, d @ R)).abs().max()) < 1e-10
    # the scales of the decomposition are a times the rest ones (in some order)
    rest_sorted = scene.log_scales.sort(dim=-1).values + math.log(a)
    assert float((out.log_scales.sort(dim=-1).values - rest_sorted).abs().max()) < 1e-10


def test_batched_poses_and_chunks_agree_with_single_calls() -> None:
    cage, scene = _cube(), _scene(50)
    g = torch.Generator().manual_seed(3)
    poses = cage.vertices + 0.1 * torch.randn(2, 3, *cage.vertices.shape, generator=g, dtype=D64)
    batched = DeformGaussians(cage, scene, chunk_size=7)(poses)
    one = DeformGaussians(cage, scene)(poses[1, 2])
    assert batched.covariances.shape == (2, 3, 50, 3, 3) and batched.sh.shape == (2, 3, 50, 16, 3)
    for name in ("means", "covariances", "log_scales", "sh"):
        assert torch.allclose(getattr(batched, name)[1, 2], getattr(one, name), atol=1e-13), name


@pytest.mark.parametrize("method", METHODS)
def test_gradients_with_respect_to_the_pose(method: str) -> None:
    cage, scene = _cube(), _scene(4, degree=2, seed=5)
    deform = DeformGaussians(cage, scene, method=method)
    g = torch.Generator().manual_seed(2)
    pose = (cage.vertices + 0.1 * torch.randn(cage.vertices.shape, generator=g, dtype=D64)).requires_grad_()

    def f(p):
        o = deform(p)
        return o.means, o.covariances, o.log_scales, o.sh, o.rotations

    assert torch.autograd.gradcheck(f, (pose,))


def test_degenerate_poses_stay_finite() -> None:
    """Isotropic Gaussians at rest (repeated singular values), a cage collapsed to a point and one
    flattened onto a plane: finite values, finite log-scales (the documented floor), finite gradients."""
    cage = _cube()
    scene = _scene(20).replace(log_scales=torch.full((20, 3), -3.0, dtype=D64))
    deform = DeformGaussians(cage, scene)
    flat = cage.vertices * torch.tensor([1.0, 1.0, 0.0], dtype=D64)
    for pose in (cage.vertices, torch.zeros_like(cage.vertices), flat):
        p = pose.clone().requires_grad_()
        out = deform(p)
        for t in (out.means, out.covariances, out.log_scales, out.rotations, out.sh):
            assert bool(torch.isfinite(t).all())
        assert float(out.log_scales.detach().min()) >= -3.0 + math.log(1e-6) - 1e-9
        (out.log_scales.sum() + out.rotations.sum() + out.sh.sum() + out.covariances.sum()).backward()
        assert bool(torch.isfinite(p.grad).all())


def test_decompositions() -> None:
    """svd3 reproduces M and agrees with torch's gradient where singular values differ; the closest
    rotation is proper and nearest (it beats random rotations); quaternions round-trip."""
    g = torch.Generator().manual_seed(0)
    M = torch.randn(30, 3, 3, generator=g, dtype=D64)
    U, S, V = svd3(M)
    assert torch.allclose(U * S[..., None, :] @ V.transpose(-1, -2), M, atol=1e-13)
    Q = closest_rotation(M)
    assert torch.allclose(torch.linalg.det(Q), torch.ones(30, dtype=D64), atol=1e-12)
    assert torch.allclose(Q @ Q.transpose(-1, -2), torch.eye(3, dtype=D64).expand(30, 3, 3), atol=1e-12)
    others = quaternion_to_matrix(torch.randn(30, 200, 4, generator=g, dtype=D64))
    best = (Q - M).flatten(-2).norm(dim=-1)
    assert bool(((others - M[:, None]).flatten(-2).norm(dim=-1) >= best[:, None] - 1e-12).all())
    q = torch.randn(500, 4, generator=g, dtype=D64)
    q = q / q.norm(dim=-1, keepdim=True) * torch.sign(q[:, :1])
    assert torch.allclose(matrix_to_quaternion(quaternion_to_matrix(q)), q, atol=1e-14)
    Mg = M[:4].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda m: closest_rotation(m), (Mg,))


def test_inverse_recovers_points_and_reports_the_rest() -> None:
    """On a stretched cube the inverse is known in closed form; queries outside the deformed cage are
    flagged and warned about."""
    cage = _cube()
    pose = cage.vertices * torch.tensor([2.0, 0.5, 1.0], dtype=D64) + 3.0
    g = torch.Generator().manual_seed(0)
    x = torch.rand(200, 3, generator=g, dtype=D64) - 0.5
    y = x * torch.tensor([2.0, 0.5, 1.0], dtype=D64) + 3.0
    out = rest_points(y, cage, pose)
    assert bool(out.converged.all()) and bool(out.inside.all())
    assert float((out.points - x).abs().max()) < 1e-9
    assert int(out.iterations.max()) <= 8
    far = torch.cat([y[:3], torch.tensor([[50.0, 3, 3]], dtype=D64)])
    with pytest.warns(UserWarning, match="1 of 4 points lie outside the deformed cage"):
        res = rest_points(far, cage, pose)
    assert res.inside.tolist() == [True, True, True, False]


@pytest.mark.parametrize("method", METHODS)
def test_inverse_is_differentiable(method: str) -> None:
    """gradcheck of x(y, V') in float64: the implicit function theorem's derivatives."""
    cage = _cube()
    g = torch.Generator().manual_seed(0)
    pose = (cage.vertices + 0.15 * torch.randn(cage.vertices.shape, generator=g, dtype=D64)).requires_grad_()
    y = (0.3 * torch.rand(3, 3, generator=g, dtype=D64) - 0.15).requires_grad_()
    f = lambda y, p: rest_points(y, cage, p, method=method, tol=1e-13, warn=False).points  # noqa: E731
    assert torch.autograd.gradcheck(f, (y, pose), atol=1e-7, rtol=1e-5)


def test_inverse_batched_poses() -> None:
    cage = _cube()
    g = torch.Generator().manual_seed(4)
    poses = cage.vertices + 0.1 * torch.randn(2, *cage.vertices.shape, generator=g, dtype=D64)
    x = 0.8 * (torch.rand(30, 3, generator=g, dtype=D64) - 0.5)
    y = torch.stack([_map(x, cage.triangulated(), p, "mvc", jacobian=False)[0] for p in poses])
    out = rest_points(y, cage, poses)
    assert out.points.shape == (2, 30, 3) and out.iterations.shape == (2, 30)
    assert float((out.points - x).abs().max()) < 1e-9


@pytest.mark.parametrize("model", ["FireHydrant", "Beast", "SpikyBox"])
@pytest.mark.parametrize("method", METHODS)
def test_inverse_on_the_data_sets_deformed_poses(model: str, method: str) -> None:
    """Points inside the deformed cage of the data set's poses: residual <= 1e-10 of the size within
    8 Newton iterations (Beast's pose folds: some queries need a second start)."""
    root = data_path("qmvc")
    if not (root / f"{model}_Cage.obj").exists():
        pytest.skip("the QMVC data set is not present")
    rest = torchcage.load_cage(root / f"{model}_Cage.obj").to(D64)
    pose = torchcage.load_cage(root / f"{model}_Cage_Deformed.obj", check_intersections=False).vertices.to(D64)
    tri = rest.triangulated()
    g = torch.Generator().manual_seed(11)
    lo, hi = tri.vertices.amin(0), tri.vertices.amax(0)
    x = lo + (hi - lo) * torch.rand(3000, 3, generator=g, dtype=D64)
    x = x[inside_cage(x, tri)][:250]
    y = _map(x, tri, pose, method, jacobian=False)[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = rest_points(y, rest, pose, method=method)
    inside = out.inside
    assert int(inside.sum()) > 50
    assert float(out.residual[inside].max()) <= 1e-10
    assert int(out.iterations[inside].max()) <= 8


def test_renderer_places_a_gaussian_where_the_camera_sees_it() -> None:
    """One small opaque Gaussian in front of the camera: the brightest change at its projection,
    its colour there (c(d) + 1/2), background elsewhere."""
    from torchcage.splats.render import Camera, render
    from torchcage.splats.sh import C0

    cam = Camera(eye=(0.0, 0.0, 5.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), width=41, height=31)
    mean = torch.tensor([[0.0, 0.0, 0.0]], dtype=D64)  # on the optical axis: the centre of pixel (15, 20)
    cov = (0.02**2) * torch.eye(3, dtype=D64)[None]
    rgb = torch.tensor([0.9, 0.2, 0.1], dtype=D64)
    sh = ((rgb - 0.5) / C0)[None, None, :]
    img = render(mean, cov, sh, torch.tensor([8.0], dtype=D64), cam, background=(0.0, 0.0, 0.0))
    _, px = cam.project(mean)
    peak = torch.nonzero(img.sum(-1) == img.sum(-1).max())[0]
    assert peak.tolist() == [15, 20] and px[0].tolist() == [20.5, 15.5]
    assert torch.allclose(img[15, 20], 0.99 * rgb, atol=1e-12)  # opacity capped at 0.99 there
    assert float(img[0, 0].abs().max()) == 0.0


@pytest.mark.slow
def test_the_splats_example_runs(tmp_path) -> None:
    import runpy
    import sys

    script = str(__import__("pathlib").Path(__file__).resolve().parents[1] / "examples" / "splats.py")
    argv = sys.argv
    sys.argv = [script, "--out", str(tmp_path), "--gaussians", "400", "--samples", "8", "--image-scale", "0.2"]
    try:
        with pytest.raises(SystemExit) as stop:
            runpy.run_path(script, run_name="__main__")
    finally:
        sys.argv = argv
    assert stop.value.code == 0 and (tmp_path / "splats.png").exists()


def test_inverse_points_are_the_same_with_and_without_a_graph() -> None:
    """The implicit-function step adds derivatives only: unconverged points (max_iter=1) are returned
    unchanged when the queries require grad."""
    cage = _cube()
    pose = cage.vertices * torch.tensor([1.6, 1.0, 1.0], dtype=D64)
    pose[0] += 0.3
    y = 0.5 * (torch.rand(40, 3, generator=torch.Generator().manual_seed(1), dtype=D64) - 0.5)
    plain = rest_points(y, cage, pose, max_iter=1, warn=False)
    graph = rest_points(y.clone().requires_grad_(), cage, pose, max_iter=1, warn=False)
    assert not bool(plain.converged.all())
    assert torch.equal(graph.points.detach(), plain.points)


def test_bad_inputs_are_refused() -> None:
    cage, scene = _cube(), _scene(10)
    from torchcage import MeanValueCoordinates

    other = MeanValueCoordinates(cage.triangulated(), scene.means[:7], store_derivatives=1)
    with pytest.raises(ValueError, match="embeds 7 points"):
        DeformGaussians(cage, scene, module=other)
    with pytest.raises(ValueError, match="1, 4, 9 or 16"):
        eval_sh(torch.zeros(5, 3, 3, dtype=D64), torch.zeros(5, 3, dtype=D64))
    with pytest.raises(ValueError, match="method must be"):
        DeformGaussians(cage, scene, method="lbc")


def test_float32_poses_are_computed_in_float64() -> None:
    cage, scene = _cube(), _scene(30)
    deform = DeformGaussians(cage, scene)
    pose = (cage.vertices * 1.3).float()
    out32, out64 = deform(pose), deform(pose.double())
    assert out32.covariances.dtype == torch.float32
    assert torch.equal(out32.covariances, out64.covariances.float())
