"""Quad mean value coordinates to a tolerance (``tol=``): the quadrature's error bound, agreement
with an independent reference of the defining integrals, the coordinates' properties, and the
native and torch kernels against each other."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from reference import quad_weights_reference
from support import QMVC_MODELS, box_points, data_path, model_points, quad_adversarial_points, triquad

import torchcage
from torchcage import functional as F
from torchcage._core import quad_quadrature as QQ
from torchcage.backends.native import available as native_available

needs_native = pytest.mark.skipif(not native_available(), reason="the native kernels are not built")


def qmvc_reference(x: torch.Tensor, cage: torchcage.Cage) -> torch.Tensor:
    """Normalised QMVC ``(N, V)`` of points off the cage from the independent reference of each
    quad's integrals (a triangle is the bilinear quad ``(a, b, c, c)``: its weights are the
    triangle's mean value weights)."""
    P = cage.vertices.to(torch.float64).numpy()
    faces = [q for q in cage.quads.tolist()] + [[a, b, c, c] for a, b, c in cage.triangles.tolist()]
    W = np.zeros((x.shape[0], P.shape[0]))
    for i, xi in enumerate(x.to(torch.float64).numpy()):
        for f in faces:
            np.add.at(W[i], f, quad_weights_reference(xi, P[f]))
    return torch.from_numpy(W / W.sum(axis=1, keepdims=True))


def cube() -> torchcage.Cage:
    """The bundled cube of six quads."""
    return torchcage.load_cage(torchcage.data.path("cube.obj"))


def random_panel(g: torch.Generator) -> torch.Tensor:
    """Corners ``(4, 3)`` of a random curved panel of aspect 1 to 8."""
    aspect = [1.0, 2.0, 8.0][int(torch.randint(3, (1,), generator=g))]
    base = torch.tensor([[0, 0, 0], [aspect, 0, 0], [aspect, 1, 0], [0, 1, 0]], dtype=torch.float64)
    return base + 0.3 * torch.randn(4, 3, generator=g, dtype=torch.float64)


def sheet_args(corners: torch.Tensor, x: torch.Tensor) -> tuple:
    q0, q1, q2, q3 = corners

    def vec(t: torch.Tensor) -> tuple:
        return tuple(t[i].reshape(1) for i in range(3))

    return vec(q0 - x), vec(q1 - q0), vec(q3 - q0), vec(q0 - q1 + q2 - q3)


def test_the_gauss_error_stays_under_the_bound_on_random_panels() -> None:
    # the a-priori model C m rho^(-2m) (relative to the integral of |N| / r^3) that picks the
    # orders, against a converged composite rule
    g = torch.Generator().manual_seed(3)
    worst = 0.0
    for trial in range(40):
        corners = random_panel(g)
        ctr = corners.mean(0)
        R = float((corners - ctr).norm(dim=1).max())
        d = torch.randn(3, generator=g, dtype=torch.float64)
        if trial % 3 == 0:
            d[2] = 0.0  # in the panel's plane: the singularity on the real axis
        q = [1.3, 1.6, 2.5, 4.0][trial % 4]
        x = ctr + q * R * d / d.norm()
        args = sheet_args(corners, x)
        edges = torch.linspace(0, 1, 9, dtype=torch.float64)
        u0, v0 = torch.meshgrid(edges[:-1], edges[:-1], indexing="ij")
        K = u0.numel()
        exp = [tuple(t.expand(K) for t in vec) for vec in args]
        zk = torch.zeros(K, dtype=torch.float64)
        a0, b0 = u0.reshape(-1), v0.reshape(-1)
        ref = QQ.gauss_panels(exp, zk, zk, a0, a0 + 0.125, b0, b0 + 0.125, 16).sum(dim=1)
        magnitude = _magnitude(corners, x)
        one, zero = torch.ones(1, dtype=torch.float64), torch.zeros(1, dtype=torch.float64)
        rho = q + math.sqrt(q * q - 1)
        for m in range(2, QQ.MAX_ORDER + 1):
            err = float((QQ.gauss_panels(args, zero, zero, zero, one, zero, one, m)[:, 0] - ref).abs().max())
            bound = QQ.ERROR_C * m * rho ** (-2 * m) * magnitude
            worst = max(worst, err / bound)
            assert err <= bound + 1e-15 * magnitude, (trial, q, m, err, bound)
    assert worst > 1e-2  # the bound is not vacuous


def _magnitude(corners: torch.Tensor, x: torch.Tensor) -> float:
    """``int |N| / |xi - x|^3 du dv`` over the panel (composite Gauss, 16 x 16 panels of 12^2)."""
    t, w = np.polynomial.legendre.leggauss(12)
    t = ((np.arange(16)[:, None] + (t + 1) / 2) / 16).ravel()
    w = np.tile(w / 32, 16)
    U, V = (torch.from_numpy(a) for a in np.meshgrid(t, t, indexing="ij"))
    q0, q1, q2, q3 = corners
    b, c, dd = q1 - q0, q3 - q0, q0 - q1 + q2 - q3
    X = (q0 - x) + U[..., None] * b + V[..., None] * c + (U * V)[..., None] * dd
    N = torch.linalg.cross(b + V[..., None] * dd, c + U[..., None] * dd, dim=-1)
    f = N.norm(dim=-1) / X.norm(dim=-1) ** 3
    return float((f * torch.from_numpy(w[:, None] * w[None, :])).sum())


@pytest.mark.parametrize(
    "tol, green, trials",
    [(1e-4, False, 2), (1e-10, False, 2), (1e-6, True, 2), (1e-10, True, 2)]  # (12 trials each: slow tier)
    + [pytest.param(t, g, 12, marks=pytest.mark.slow) for t in (1e-4, 1e-8, 1e-10) for g in (False, True)],
)
def test_the_quadrature_meets_the_tolerance_against_a_reference(tol: float, green: bool, trials: int) -> None:
    g = torch.Generator().manual_seed(7)
    for trial in range(trials):
        corners = random_panel(g)
        u, v = torch.rand(2, generator=g, dtype=torch.float64).tolist()
        U, V = torch.tensor(u, dtype=torch.float64), torch.tensor(v, dtype=torch.float64)
        q0, q1, q2, q3 = corners
        xi = (1 - U) * (1 - V) * q0 + U * (1 - V) * q1 + U * V * q2 + (1 - U) * V * q3
        normal = torch.linalg.cross((1 - V) * (q1 - q0) + V * (q2 - q3), (1 - U) * (q3 - q0) + U * (q2 - q1))
        for h in (1.0, 1e-2, 1e-5, 1e-9):
            x = xi + h * normal / normal.norm() * (1 if trial % 2 else -1)
            ref = quad_weights_reference(x.numpy(), corners.numpy(), green=green)
            om = QQ.quad_integrals(*sheet_args(corners, x), U.reshape(1), V.reshape(1), tol, green)[:, 0].numpy()
            if green:  # each family to the tolerance of its own sum
                ref, om = np.stack([ref[:4], ref[4:]]), np.stack([om[:4], om[4:]])
            else:
                ref, om = ref[None], om[None]
            # (at h from the sheet, the inputs' rounding moves the integrals by about eps / h)
            # (and the reference is converged to about 1e-11 of the sum: test_the_reference_is_converged)
            rounding = 1e-16 * float(corners.abs().max()) / h + 1e-11
            assert (np.abs(om - ref).max(1) <= (tol + rounding) * np.abs(ref).sum(1)).all(), (trial, h, om, ref)


@pytest.mark.slow
def test_the_reference_is_converged() -> None:
    # doubling its nodes changes nothing, on curved, elongated panels, near and far
    g = torch.Generator().manual_seed(1)
    for trial in range(2):
        corners = random_panel(g).numpy()
        for h in (1e-6, 1e-2, 0.5):
            x = corners.mean(0) + np.array([0.01, -0.02, h])
            a = quad_weights_reference(x, corners)
            b = quad_weights_reference(x, corners, radial_nodes=40, angular_nodes=32, angular_panels=32)
            assert np.abs(a - b).max() <= 1e-11 * np.abs(b).sum(), (trial, h)


def _check_model(model: str, npts: int, tol: float, bound: float) -> tuple[float, float]:
    cage = torchcage.load_cage(data_path("qmvc", f"{model}_Cage.obj"))
    pts = model_points(model, cage, 200)
    x = pts[torch.randperm(pts.shape[0], generator=torch.Generator().manual_seed(0))[:npts]]
    ref = qmvc_reference(x, cage)
    w = F.quad_mean_value_coordinates(x, cage, tol=tol)
    w4 = F.quad_mean_value_coordinates(x, cage)
    err, err4 = float((w - ref).abs().max()), float((w4 - ref).abs().max())
    assert err <= bound, (model, err)
    return err, err4


def test_firehydrant_to_1e_8_against_the_reference() -> None:
    err, err4 = _check_model("FireHydrant", 4, 1e-8, 1e-7)
    assert err < 1e-3 * err4  # n = 4 is ~3e-3 off


@pytest.mark.slow
@pytest.mark.parametrize("model", QMVC_MODELS)
def test_every_model_to_1e_8_and_1e_4_against_the_reference(model: str) -> None:
    _check_model(model, 25, 1e-8, 1e-7)
    err, err4 = _check_model(model, 10, 1e-4, 1e-4)
    assert err < err4


@pytest.mark.parametrize("cage_fn", [cube, triquad])
@pytest.mark.parametrize("tol", [1e-4, 1e-10])
def test_properties_hold_to_rounding_at_any_tolerance(cage_fn, tol: float) -> None:
    cage = cage_fn()
    x = quad_adversarial_points(cage)
    w = F.quad_mean_value_coordinates(x, cage, tol=tol)
    assert torch.isfinite(w).all()
    assert (w.sum(-1) - 1).abs().max() <= 1e-12
    assert (w @ cage.vertices.to(torch.float64) - x).abs().max() <= 1e-10 * cage.scale


@needs_native
@pytest.mark.parametrize("model", ["FireHydrant", "Beast"])
def test_native_and_torch_agree_and_interpolate(model: str) -> None:
    cage = torchcage.load_cage(data_path("qmvc", f"{model}_Cage.obj"))
    pts = model_points(model, cage, 200)
    # (closer to a quad than 1e-6 of the size, the inputs' rounding sets the agreement, as for n)
    near = quad_adversarial_points(cage, distances=(0.0, 1e-6, 1e-3))
    x = torch.cat([pts[:: max(1, pts.shape[0] // 150)], near[:-9]])
    a = F.quad_mean_value_coordinates(x, cage, tol=1e-8, backend="native")
    b = F.quad_mean_value_coordinates(x, cage, tol=1e-8, backend="torch")
    n = pts[:: max(1, pts.shape[0] // 150)].shape[0]
    assert (a[:n] - b[:n]).abs().max() <= 1e-12  # the mesh's points (measured <= 4e-16)
    assert (a[n:] - b[n:]).abs().max() <= 1e-10  # 1e-6 of the size off a quad: rounding (measured 8e-11)
    assert (a @ cage.vertices.to(torch.float64) - x).abs().max() <= 1e-10 * cage.scale
    # 2-5 cage sizes away the far field's cancelling total sets the agreement, as with n
    far_a = F.quad_mean_value_coordinates(near[-9:], cage, tol=1e-8, backend="native")
    far_b = F.quad_mean_value_coordinates(near[-9:], cage, tol=1e-8, backend="torch")
    assert (far_a - far_b).abs().max() <= 1e-10
    # on a quad: bilinear interpolation of its corners, exactly as the Riemann version
    q = cage.quads[0]
    c = cage.vertices.to(torch.float64)[q]
    uv = torch.tensor([[0.3, 0.6], [0.9, 0.1]], dtype=torch.float64)
    u, v = uv[:, 0], uv[:, 1]
    hats = torch.stack([(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v], 1)
    on = hats @ c
    w = F.quad_mean_value_coordinates(on, cage, tol=1e-8)
    assert (w[:, q] - hats).abs().max() <= 1e-12


def test_gradients_are_finite_and_gradchecked() -> None:
    cage = cube()
    x = torch.tensor([[0.1, 0.2, -0.3], [0.5, -0.7, 0.95], [2.0, 0.5, 0.1]], dtype=torch.float64, requires_grad=True)
    rest = cage.vertices.to(torch.float64)
    corners = torch.tensor([0, 6])  # opposite corners: every quad has one of them (6 of the 24 coordinates)
    moved = rest[corners].clone().requires_grad_(True)

    def f(x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return F.quad_mean_value_coordinates(x, cage.with_vertices(rest.index_put((corners,), v)), tol=1e-11)

    assert torch.autograd.gradcheck(f, (x, moved), atol=1e-6, rtol=1e-5)


def test_tol_is_checked_and_reaches_the_module_and_methods() -> None:
    cage = cube()
    x = torch.zeros(1, 3, dtype=torch.float64)
    for bad in (0.0, -1e-3, 1.0, float("nan"), "1e-8", True):
        with pytest.raises(ValueError, match="tol must be"):
            F.quad_mean_value_coordinates(x, cage, tol=bad)  # type: ignore[arg-type]
    m = torchcage.QuadMeanValueCoordinates(cage, x + 0.1, tol=1e-8)
    assert "tol=1e-08" in repr(m)
    assert torch.allclose(m.weights, F.quad_mean_value_coordinates(x + 0.1, cage, tol=1e-8))
    from torchcage.methods import build_module

    with pytest.raises(ValueError, match="tol is an option of qmvc and qgc"):
        build_module("mvc", cage, x, tol=1e-8)
    assert build_module("qmvc", cage, x, tol=1e-8).tol == 1e-8
    qgc = build_module("qgc", cage, x + 0.1, tol=1e-8)
    assert "tol=1e-08" in repr(qgc)
    assert torch.allclose(qgc.phi, F.quad_green_coordinates(x + 0.1, cage, tol=1e-8)[0])


def test_the_cli_takes_tol(tmp_path, capsys) -> None:
    from torchcage.cli import main

    d = torchcage.data
    args = ["deform", "--cage", str(d.path("bar_cage.obj")), "--deformed", str(d.path("bar_cage_deformed.obj")),
            "--mesh", str(d.path("bar.obj")), "--no-picture"]  # fmt: skip
    assert main([*args, "--out", str(tmp_path / "a"), "--method", "qmvc", "--tol", "1e-6"]) == 0
    assert main([*args, "--out", str(tmp_path / "b"), "--method", "qmvc"]) == 0
    a, _ = torchcage.load_mesh(tmp_path / "a" / "deformed_mesh.obj")
    b, _ = torchcage.load_mesh(tmp_path / "b" / "deformed_mesh.obj")
    assert 0 < float((a - b).abs().max()) < 0.05  # the same deformation, from different integrals
    assert main([*args, "--out", str(tmp_path / "c"), "--method", "mvc", "--tol", "1e-6"]) == 2  # refused
    assert "--tol is an option of --method qmvc and qgc" in capsys.readouterr().err


def test_similarity_and_mirror_symmetry_hold_with_tol() -> None:
    cage = triquad()
    x = quad_adversarial_points(cage, distances=(1e-3,))
    w = F.quad_mean_value_coordinates(x, cage, tol=1e-8)
    g = torch.Generator().manual_seed(2)
    Rm, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    shift = torch.tensor([0.3, -2.0, 5.0], dtype=torch.float64)
    for s in (1e-3, 1e3):
        moved = cage.with_vertices(s * cage.vertices.to(torch.float64) @ Rm.T + shift)
        ws = F.quad_mean_value_coordinates(s * x @ Rm.T + shift, moved, tol=1e-8)
        assert (ws - w).abs().max() <= 1e-10
    # the cube's mirror x -> -x maps vertex i to its mirror image's index and the coordinates with it
    cb = cube()
    v = cb.vertices.to(torch.float64)
    flip = torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    perm = torch.cdist(v * flip, v).argmin(dim=1)
    y = torch.rand(50, 3, generator=g, dtype=torch.float64) * 1.8 - 0.9
    a = F.quad_mean_value_coordinates(y, cb, tol=1e-8)
    b = F.quad_mean_value_coordinates(y * flip, cb, tol=1e-8)
    assert (a[:, perm] - b).abs().max() <= 1e-12


@pytest.mark.parametrize("model", ["FireHydrant", pytest.param("Beast", marks=pytest.mark.slow)])
def test_qgc_to_1e_6_is_within_1e_5_of_1e_9(model: str) -> None:
    cage = torchcage.load_cage(data_path("qmvc", f"{model}_Cage.obj"))
    pts = model_points(model, cage, 200)
    near = quad_adversarial_points(cage, distances=(0.0, 1e-6, 1e-3))[:-9]  # (not the far points)
    x = torch.cat([pts[:: max(1, pts.shape[0] // 300)], near])
    phi6, psi6 = F.quad_green_coordinates(x, cage, tol=1e-6)
    phi9, psi9 = F.quad_green_coordinates(x, cage, tol=1e-9)
    phi2, _ = F.quad_green_coordinates(x, cage)
    assert torch.isfinite(phi6).all() and torch.isfinite(psi6).all()
    assert (phi6 - phi9).abs().max() <= 1e-5 and (psi6 - psi9).abs().max() <= 1e-5 * cage.scale
    assert (phi2 - phi9).abs().max() > 1e-4  # the Riemann sum at n = 2 is farther off
    # linear precision inside the cage (the mesh's points) and the constants: exact by construction
    N = cage.quad_corner_normals().reshape(-1, 3).to(torch.float64)
    T = cage.triangles.shape[0]
    nt = cage.triangle_normals().to(torch.float64)[:T]  # (the cage's own triangles come first)
    rec = phi9 @ cage.vertices.to(torch.float64) + psi9[:, :T] @ nt + psi9[:, T:] @ N
    from test_quad_green import inside_bilinear

    inside = inside_bilinear(x, cage, (6, 12))  # (the mesh's points inside: Beast's cage leaves some out)
    inside[x.shape[0] - near.shape[0] :] = False
    assert int(inside.sum()) > 50
    assert (rec - x)[inside].abs().max() <= 1e-10 * cage.scale
    assert (phi9[inside].sum(-1) - 1).abs().max() <= 1e-10


@needs_native
def test_qgc_native_and_torch_agree() -> None:
    cage = triquad()
    x = torch.cat([box_points(cage, 200, spread=0.9), quad_adversarial_points(cage, distances=(0.0, 1e-6, 1e-3))])
    a = F.quad_green_coordinates(x, cage, tol=1e-8, backend="native")
    b = F.quad_green_coordinates(x, cage, tol=1e-8, backend="torch")
    assert (a[0] - b[0]).abs().max() <= 1e-12 and (a[1] - b[1]).abs().max() <= 1e-12 * cage.scale


def test_qgc_gradients_with_tol_are_gradchecked() -> None:
    cage = cube()
    x = torch.tensor([[0.1, 0.2, -0.3], [0.5, -0.7, 0.9]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p: F.quad_green_coordinates(p, cage, tol=1e-11)[0], (x,), atol=1e-6)
