"""Gradients of Green coordinates: the closed form against 60-digit central differences of the
mpmath closed forms, against autograd of the torch kernel, the derivative of linear precision (the
identity at rest), and the rows differentiated through the kernel (outside, on the cage, thin
faces, polygons)."""

from __future__ import annotations

import mpmath as mp
import pytest
import torch
from reference import green3d_reference, mvc_derivatives_reference
from support import data_path, l_shape
from test_gradient_references import _sample

import torchcage as tc
from torchcage import functional as F
from torchcage.families.green.derivatives import _autograd_rows
from torchcage.families.green.derivatives_flat import autograd_rows
from torchcage.families.green.dispatch import green_flat
from torchcage.geometry import inside_cage
from torchcage.testing import sliver_cube

D64 = torch.float64


def _kernel_rows(x: torch.Tensor, cage: tc.Cage, order: int = 1) -> tuple[torch.Tensor, ...]:
    """Plain autograd of the torch kernel of the bare integrals (no custom Function): the
    independent reference for points inside."""
    return autograd_rows(x, order, lambda y: green_flat(y, cage, backend="torch"))


def _cube() -> tc.Cage:
    return tc.load_cage(tc.data.path("cube.obj")).to(D64).triangulated()


@mp.workdps(60)
def _reference_gradients(x: list[float], cage: tc.Cage) -> torch.Tensor:
    """``(V + T, 3)``: central differences of every bare coordinate, step 1e-15 of the size."""
    rows = cage.vertices.tolist()
    h = mp.mpf(cage.scale) * mp.mpf("1e-15")
    cols = []
    for d in range(3):
        up = [mp.mpf(c) for c in x]
        dn = list(up)
        up[d] += h
        dn[d] -= h
        pu, su = green3d_reference(up, rows, cage.triangles)
        pd, sd = green3d_reference(dn, rows, cage.triangles)
        cols.append([float((a - b) / (2 * h)) for a, b in zip([*pu, *su], [*pd, *sd], strict=True)])
    return torch.tensor(cols, dtype=D64).T


@pytest.mark.parametrize("name", ["cube", pytest.param("l_shape", marks=pytest.mark.slow)])
def test_closed_form_matches_high_precision_differences(name: str) -> None:
    cage = _cube() if name == "cube" else l_shape().triangulated()
    X, _ = _sample(cage, 2, seed=0, far=False)
    _, _, gphi, gpsi = F.green_derivatives(X, cage, exterior="none")
    for i in range(X.shape[0]):
        ref = _reference_gradients(X[i].tolist(), cage)
        got = torch.cat([gphi[i], gpsi[i]])
        err = float((got - ref).norm() / ref.norm())
        assert err <= 1e-9, (i, X[i].tolist(), err)


@pytest.mark.parametrize("name", ["l_shape", pytest.param("FireHydrant", marks=pytest.mark.slow)])
def test_matches_autograd_and_reproduces_the_identity(name: str) -> None:
    if name == "l_shape":
        cage = l_shape().triangulated()
    else:
        cage = tc.load_cage(data_path("qmvc", "FireHydrant_Cage.obj")).to(D64).triangulated()
    g = torch.Generator().manual_seed(0)
    v = cage.vertices
    lo, hi = v.min(0).values, v.max(0).values
    x = lo + (hi - lo) * torch.rand(300, 3, generator=g, dtype=D64)
    x = x[inside_cage(x, cage)][:40]
    _, _, gphi, gpsi = F.green_derivatives(x, cage)
    ap, aq, _, _ = _kernel_rows(x, cage)
    assert float((gphi - ap).abs().max()) <= 1e-12 and float((gpsi - aq).abs().max()) <= 1e-12
    J = torch.einsum("nvi,vj->nji", gphi, v) + torch.einsum("nti,tj->nji", gpsi, cage.triangle_normals())
    assert float((J - torch.eye(3, dtype=D64)).abs().max()) <= 1e-10


def test_rows_the_closed_form_does_not_serve() -> None:
    """Outside (the extension), on the cage and beside a sliver: autograd of the kernel, finite;
    a polygon's gradients reproduce the identity's."""
    cube = _cube()
    x = torch.tensor([[0.2, 0.1, 1.5], [0.3, -0.2, 1.0], [0.0, 0.0, 0.0]], dtype=D64)
    _, _, gphi, gpsi = F.green_derivatives(x, cube)
    ap, aq, _, _ = _autograd_rows(x, cube, "extend")
    ap = ap - ap.mean(dim=1, keepdim=True)  # (the gradients of phi are made to sum to 0 exactly)
    assert torch.isfinite(gphi).all() and torch.equal(gphi[:2], ap[:2]) and torch.equal(gpsi[:2], aq[:2])
    sliver = sliver_cube()
    y = torch.tensor([[0.2, -0.68, -0.99]], dtype=D64)  # a few hundred widths above the sliver
    _, _, gp, gs = F.green_derivatives(y, sliver)
    bp, bs, _, _ = _autograd_rows(y, sliver, "extend")
    assert torch.equal(gp, bp - bp.mean(dim=1, keepdim=True)) and torch.equal(gs, bs)
    poly = tc.Cage(torch.tensor([[0.0, 0], [2, 0], [2, 1], [1, 1.5], [0, 1]], dtype=D64))
    z = torch.tensor([[0.5, 0.5], [1.5, 0.7]], dtype=D64)
    _, _, gp2, gs2 = F.green_derivatives(z, poly)
    assert gp2.shape == (2, 5, 2) and gs2.shape == (2, 5, 2) and bool(torch.isfinite(gp2).all())
    J = torch.einsum("nvi,vj->nji", gp2, poly.vertices) + torch.einsum("nti,tj->nji", gs2, poly.edge_normals())
    assert float((J - torch.eye(2, dtype=D64)).abs().max()) <= 1e-10


def _bare(y: list, cage: tc.Cage) -> list:
    """``phi`` then ``psi`` of one point, 60 digits."""
    phi, psi = green3d_reference(y, cage.vertices, cage.triangles)
    return [*phi, *psi]


@pytest.mark.parametrize("name", ["cube", pytest.param("l_shape", marks=pytest.mark.slow)])
def test_hessians_match_high_precision_differences(name: str) -> None:
    """Both kernels' Hessians against 60-digit second differences of the mpmath closed forms, at
    points near faces, support planes, edge lines and corners (the native kernel where it loads)."""
    cage = _cube() if name == "cube" else l_shape().triangulated()
    X, cats = _sample(cage, 2, seed=1, far=False)
    nat = F.green_derivatives(
        X, cage, order=2, exterior="none", backend="native" if tc.backends.native.available() else "torch"
    )
    tor = F.green_derivatives(X, cage, order=2, exterior="none", backend="torch")
    for a, b in zip(nat[2:], tor[2:], strict=True):
        assert float((a - b).abs().max() / b.abs().max()) <= 1e-11
    for i in range(X.shape[0]):
        grad, hess = mvc_derivatives_reference(X[i].tolist(), lambda y: _bare(y, cage), cage.scale)
        ref_g, ref_h = torch.tensor(grad, dtype=D64), torch.tensor(hess, dtype=D64)
        got_h = torch.cat([nat[4][i], nat[5][i]])
        got_g = torch.cat([nat[2][i], nat[3][i]])
        assert float((got_h - ref_h).norm() / ref_h.norm()) <= 1e-9, (cats[i], X[i].tolist())
        assert float((got_g - ref_g).norm() / ref_g.norm()) <= 1e-9, (cats[i], X[i].tolist())


@pytest.mark.parametrize("name", ["cube", pytest.param("l_shape", marks=pytest.mark.slow)])
def test_far_field_matches_high_precision(name: str) -> None:
    """Far outside (``exterior="none"``): values, gradients and Hessians of both kernels against the
    60-digit closed forms and their differences, at points where some faces take the far-field rule
    (nearest corner ``FAR_RATIO`` longest edges away) and others the closed forms, and 1e2 to 1e6
    sizes away, where the closed forms alone lost up to 3e-7 (values)."""
    from torchcage.families.green.far_triangle import FAR_RATIO

    cage = _cube() if name == "cube" else l_shape().triangulated()
    v = cage.vertices
    L = float((v[cage.triangles.roll(-1, 1)] - v[cage.triangles]).norm(dim=-1).max())
    g = torch.Generator().manual_seed(5)
    d = torch.randn(6, 3, generator=g, dtype=D64)
    d = d / d.norm(dim=1, keepdim=True)
    centre = v.mean(0)
    R = float((v - centre).norm(dim=1).max())
    switch = FAR_RATIO * L
    dist = torch.tensor([switch * (1 - 1e-9), switch * (1 + 1e-9), R + switch, 1e2, 1e4, 1e6], dtype=D64)
    dist[3:] *= cage.scale
    X = centre + dist[:, None] * d
    backends = ["native", "torch"] if tc.backends.native.available() else ["torch"]
    outs = {}
    for b in backends:  # (the values from each backend's own kernel)
        derivatives = F.green_derivatives(X, cage, order=2, exterior="none", backend=b)
        outs[b] = (*F.green_coordinates(X, cage, exterior="none", backend=b), *derivatives[2:])
    for i in range(X.shape[0]):
        with mp.workdps(60):
            ref_v = torch.tensor([float(c) for c in _bare([mp.mpf(c) for c in X[i].tolist()], cage)], dtype=D64)
        grad, hess = mvc_derivatives_reference(X[i].tolist(), lambda y: _bare(y, cage), cage.scale * float(dist[i]))
        ref_g, ref_h = torch.tensor(grad, dtype=D64), torch.tensor(hess, dtype=D64)
        for b, out in outs.items():
            got = [torch.cat([out[k][i], out[k + 1][i]]) for k in (0, 2, 4)]
            for what, a, ref in zip(("values", "gradients", "Hessians"), got, (ref_v, ref_g, ref_h), strict=True):
                err = float((a - ref).norm() / ref.norm())
                assert err <= 1e-9, (b, what, float(dist[i]), err)


def test_hessians_reproduce_the_identity_and_match_autograd() -> None:
    """The second derivatives of ``sum phi_i v_i + sum psi_t n_t = x`` vanish, and the closed
    form agrees with double autograd of the torch kernel; outside points and polygons take the
    autograd rows (finite, symmetric, identity kept)."""
    cage = l_shape().triangulated()
    g = torch.Generator().manual_seed(3)
    v = cage.vertices
    lo, hi = v.min(0).values, v.max(0).values
    x = lo + (hi - lo) * torch.rand(200, 3, generator=g, dtype=D64)
    x = x[inside_cage(x, cage)][:12]
    x = torch.cat([x, torch.tensor([[0.3, 0.2, 2.5]], dtype=D64)])  # and one outside
    *_, hphi, hpsi = F.green_derivatives(x, cage, order=2)
    _, _, hp, hs = _kernel_rows(x[:-1], cage, order=2)
    hp = torch.cat([hp, _autograd_rows(x[-1:], cage, "extend", order=2)[2]])
    hs = torch.cat([hs, _autograd_rows(x[-1:], cage, "extend", order=2)[3]])
    assert float((hphi - hp).abs().max()) <= 1e-9 * float(hp.abs().max())
    assert float((hpsi - hs).abs().max()) <= 1e-9 * float(hs.abs().max())
    H = torch.einsum("nvab,vj->njab", hphi, v) + torch.einsum("ntab,tj->njab", hpsi, cage.triangle_normals())
    assert float(H[:-1].abs().max()) <= 1e-10 * cage.scale
    assert torch.equal(hphi, hphi.transpose(-1, -2))
    poly = tc.Cage(torch.tensor([[0.0, 0], [2, 0], [2, 1], [1, 1.5], [0, 1]], dtype=D64))
    z = torch.tensor([[0.5, 0.5], [1.5, 0.7]], dtype=D64)
    _, _, _, _, hp2, hs2 = F.green_derivatives(z, poly, order=2)
    H2 = torch.einsum("nvab,vj->njab", hp2, poly.vertices) + torch.einsum("ntab,tj->njab", hs2, poly.edge_normals())
    assert hp2.shape == (2, 5, 2, 2) and float(H2.abs().max()) <= 1e-10


def test_bad_order_and_backend() -> None:
    with pytest.raises(ValueError, match="order"):
        F.green_derivatives(torch.zeros(1, 3, dtype=D64), _cube(), order=3)
    with pytest.raises(ValueError, match="backend"):
        F.green_derivatives(torch.zeros(1, 3, dtype=D64), _cube(), backend="cuda")


@pytest.mark.parametrize("store", [0, 2])
def test_module_jacobian_and_hessian_match_autograd_of_the_deformation(store: int) -> None:
    """``GreenCoordinates.jacobian`` / ``.hessian`` against autograd of the functional deformation
    (stretch factors included) at points inside and one outside; a similarity's Jacobian is its
    scaled rotation and its Hessian vanishes."""
    from torch.autograd.functional import hessian, jacobian

    from torchcage.functional.deform import green_deformation

    cage = _cube()
    g = torch.Generator().manual_seed(5)
    pts = torch.rand(6, 3, generator=g, dtype=D64) * 1.8 - 0.9
    pts[0] = torch.tensor([0.3, 0.2, 1.3], dtype=D64)  # outside: the extension's derivatives
    gc = tc.GreenCoordinates(cage, pts, store_derivatives=store)
    Q = cage.vertices + 0.2 * torch.randn(cage.vertices.shape, generator=g, dtype=D64)
    J, H = gc.jacobian(Q), gc.hessian(Q)

    def deform(x: torch.Tensor) -> torch.Tensor:
        phi, psi = F.green_coordinates(x[None], cage)
        return green_deformation(phi, psi, cage.vertices, Q, cage.triangles)[0]

    for i in range(pts.shape[0]):
        assert float((jacobian(deform, pts[i]) - J[i]).abs().max()) <= 1e-12
        for a in range(3):
            Ha = hessian(lambda x, a=a: deform(x)[a], pts[i])
            assert float((Ha - H[i, a]).abs().max()) <= 1e-10 * (1 + float(Ha.abs().max()))
    R = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=D64))[0]
    S = 2 * cage.vertices @ R.T + 1
    assert float((gc.jacobian(S) - 2 * R).abs().max()) <= 1e-12
    assert float(gc.hessian(S).abs().max()) <= 1e-10


def test_module_derivatives_of_batched_cages() -> None:
    cube = _cube()
    batch = tc.Cage(torch.stack([cube.vertices, 2 * cube.vertices]), cube.triangles)
    pts = torch.tensor([[0.1, 0.2, 0.3], [-0.5, 0.4, 0.0]], dtype=D64)
    gc = tc.GreenCoordinates(batch, pts)
    J = gc.jacobian(batch.vertices)
    assert J.shape == (2, 2, 3, 3) and float((J - torch.eye(3, dtype=D64)).abs().max()) <= 1e-12
    with pytest.raises(ValueError, match="store_derivatives"):
        tc.GreenCoordinates(cube, pts, store_derivatives=3)


def test_autograd_through_the_closed_form() -> None:
    """``green_coordinates`` differentiated with respect to the points runs the closed-form
    gradients (double backward: the Hessians): gradcheck and gradgradcheck inside and outside (the
    extension), the same gradient as the torch kernel's autograd, and the cage's vertices still
    differentiable alongside."""
    from torchcage.families.green.ops import GreenGradFunction

    cage = _cube()
    g = torch.Generator().manual_seed(7)
    x = torch.rand(4, 3, generator=g, dtype=D64) * 1.8 - 0.9
    x = torch.cat([x, torch.tensor([[0.3, 0.2, 1.3]], dtype=D64)]).requires_grad_()
    f = lambda y: F.green_coordinates(y, cage)  # noqa: E731
    assert torch.autograd.gradcheck(f, (x,))
    assert torch.autograd.gradgradcheck(f, (x,))
    phi, psi = f(x)
    seen = []
    original = GreenGradFunction.forward

    def spy(*args):
        seen.append(1)
        return original(*args)

    GreenGradFunction.forward = staticmethod(spy)
    try:
        (gx,) = torch.autograd.grad((phi[:, 2] + psi[:, 5]).sum(), x)
    finally:
        GreenGradFunction.forward = staticmethod(original)
    assert seen
    ap, aq, _, _ = _kernel_rows(x[:-1].detach(), cage)
    assert float((gx[:-1] - ap[:, 2] - aq[:, 5]).abs().max()) <= 1e-12
    P = cage.vertices.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda y, Q: F.green_coordinates(y, tc.Cage(Q, cage.triangles)), (x, P))


@pytest.mark.parametrize("name", ["cube", pytest.param("sliver", marks=pytest.mark.slow)])
def test_second_derivatives_are_finite_everywhere(name: str) -> None:
    """Every adversarial category (on the cage, 1e-15 from it, support planes, edge lines, far up to
    1e9 sizes): finite gradients and Hessians, with the extension and without."""
    from torchcage.testing import adversarial_points

    cage = _cube() if name == "cube" else sliver_cube()
    pts = adversarial_points(cage, 12, seed=2)
    x = torch.cat(list(pts.values()))
    for exterior in ("extend", "none"):
        out = F.green_derivatives(x, cage, order=2, exterior=exterior)
        assert all(bool(torch.isfinite(t).all()) for t in out), exterior


@mp.workdps(40)
def _green2d_reference(y: list, vertices: list) -> list:
    """2D Green coordinates ``phi`` then ``psi`` of one point by tanh-sinh quadrature of their
    defining integrals (the double and single layers on each edge, split at the point's foot on
    the edge, where a near point makes the integrands peak), 40 digits."""
    E = len(vertices)
    phi, psi = [mp.mpf(0)] * E, []
    for j in range(E):
        a0, a1 = vertices[j], vertices[(j + 1) % E]
        ax, ay = mp.mpf(a1[0]) - a0[0], mp.mpf(a1[1]) - a0[1]
        length = mp.sqrt(ax * ax + ay * ay)
        nx, ny = ay / length, -ax / length

        def r2(t, a0=a0, ax=ax, ay=ay, nx=nx, ny=ny):
            dx, dy = a0[0] + t * ax - y[0], a0[1] + t * ay - y[1]
            return dx * dx + dy * dy, dx * nx + dy * ny

        foot = ((y[0] - a0[0]) * ax + (y[1] - a0[1]) * ay) / (length * length)
        span = [0, foot, 1] if 0 < foot < 1 else [0, 1]
        psi.append(-length * mp.quad(lambda t, r2=r2: mp.log(r2(t)[0]) / 2, span) / (2 * mp.pi))
        dn = lambda t, r2=r2: r2(t)[1] / r2(t)[0] / (2 * mp.pi)  # noqa: E731
        phi[j] += length * mp.quad(lambda t, dn=dn: (1 - t) * dn(t), span)
        phi[(j + 1) % E] += length * mp.quad(lambda t, dn=dn: t * dn(t), span)
    return [*phi, *psi]


@pytest.mark.slow
def test_polygon_closed_form_matches_quadrature_differences_and_autograd() -> None:
    """2D: gradients and Hessians against central differences of a 40-digit quadrature of the
    defining integrals (step 1e-12), against double autograd of the torch kernel, and the identity's
    derivatives; ``green_coordinates`` on a polygon differentiates through them (gradgradcheck)."""
    poly = tc.Cage(torch.tensor([[0.0, 0], [2, 0], [2, 1], [1, 1.5], [0, 1]], dtype=D64))
    x = torch.tensor([[0.5, 0.5], [1.999, 0.7], [1.0, 1.4999], [0.3, 1e-7]], dtype=D64)
    _, _, gp, gs, hp, hs = F.green_derivatives(x, poly, order=2)
    ref = _kernel_rows(x, poly, order=2)
    for got, want in zip((gp, gs, hp, hs), ref, strict=True):
        assert float((got - want).abs().max()) <= 1e-9 * float(want.abs().max())
    rows = poly.vertices.tolist()
    for i in range(2):
        grad, hess = mvc_derivatives_reference(x[i].tolist(), lambda y: _green2d_reference(y, rows), 1.0)
        got_g, got_h = torch.cat([gp[i], gs[i]]), torch.cat([hp[i], hs[i]])
        assert float((got_g - torch.tensor(grad, dtype=D64)).norm() / got_g.norm()) <= 1e-9
        assert float((got_h - torch.tensor(hess, dtype=D64)).norm() / got_h.norm()) <= 1e-9
    n = poly.edge_normals()
    J = torch.einsum("nvi,vj->nji", gp, poly.vertices) + torch.einsum("nei,ej->nji", gs, n)
    H = torch.einsum("nvab,vj->njab", hp, poly.vertices) + torch.einsum("neab,ej->njab", hs, n)
    assert float((J - torch.eye(2, dtype=D64)).abs().max()) <= 1e-10 and float(H.abs().max()) <= 1e-8
    xg = x[:2].clone().requires_grad_()
    assert torch.autograd.gradgradcheck(lambda y: F.green_coordinates(y, poly), (xg,))
