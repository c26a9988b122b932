"""Learnable cages: batched rest cages, gradients with respect to the rest cage and the points,
modules over batches, the differentiable ``deform`` path."""

from __future__ import annotations

import pytest
import torch
from support import cube, extruded_polygon

import torchcage
from torchcage import functional as F
from torchcage.families.mean_value.ops import _torch_coordinates
from torchcage.families.mean_value.vjp3d import direct_vjp
from torchcage.testing import icosphere, twisted_bar

D64 = torch.float64


def _ball(n: int, radius: float = 0.9, seed: int = 0, dtype=D64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 3, generator=g, dtype=dtype)
    return x / x.norm(dim=1, keepdim=True) * torch.rand(n, 1, generator=g, dtype=dtype) ** (1 / 3) * radius


def _jitter(cage: torchcage.Cage, B: int, amount: float = 0.05, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    scale = 1 + 0.2 * torch.rand(B, 1, 1, generator=g, dtype=D64)
    return cage.vertices * scale + amount * torch.randn(B, *cage.vertices.shape, generator=g, dtype=D64)


# ------------------------------------------------------------------------------ batched cages
def test_batched_cage_basics():
    ico = icosphere()
    V = _jitter(ico, 3)
    bc = torchcage.Cage(V, ico.triangles)
    assert bc.is_batched and bc.batch_shape == (3,) and len(bc) == 3
    assert torch.equal(bc[1].vertices, V[1]) and not bc[1].is_batched
    assert torch.allclose(bc.signed_volume()[2], torchcage.Cage(V[2], ico.triangles).signed_volume())
    assert bc.triangle_normals().shape == (3, 80, 3)
    assert bc.to(torch.float32).vertices.dtype == torch.float32
    grid = torchcage.Cage(V.reshape(3, 1, 42, 3).expand(3, 2, 42, 3), ico.triangles)
    assert grid.batch_shape == (3, 2) and len(grid.unbind()) == 6
    with pytest.raises(IndexError, match="batch elements"):
        bc[0, 1]
    with pytest.raises(torchcage.CageError, match="one element at a time"):
        torchcage.save_cage("unused.obj", bc)


def test_one_bad_cage_in_a_batch_is_named():
    ico = icosphere()
    V = _jitter(ico, 4)
    bad = V.clone()
    bad[2, 5] = float("nan")
    with pytest.raises(torchcage.CageError, match=r"batch element \(2,\), vertex indices \[5\]"):
        torchcage.Cage(bad, ico.triangles)
    flat = V.clone()
    t = ico.triangles[7]
    flat[1, t[2]] = 0.5 * (flat[1, t[0]] + flat[1, t[1]])  # triangle 7 of element 1 collapses to a segment
    with pytest.raises(torchcage.DegenerateFaceError, match=r"triangles \[7\] in batch element \(1,\)"):
        torchcage.Cage(flat, ico.triangles)
    mixed = V.clone()
    mixed[3] = mixed[3] * torch.tensor([1.0, 1.0, -1.0], dtype=D64)  # a mirror turns element 3 inside out
    with pytest.raises(torchcage.CageOrientationError, match=r"batch element \(3,\)"):
        torchcage.Cage(mixed, ico.triangles)
    # all inside out: flipped once for the whole batch, like one cage
    with pytest.warns(UserWarning, match="flipped"):
        flipped = torchcage.Cage(V * torch.tensor([1.0, 1.0, -1.0], dtype=D64), ico.triangles)
    assert bool((flipped.signed_volume() > 0).all())
    # the hot-loop modes skip the geometry (no host synchronisation)
    torchcage.Cage(bad, ico.triangles, validate="topology")
    ico.with_vertices(bad)
    with pytest.raises(torchcage.CageError, match="NaN"):
        ico.with_vertices(bad, validate=True)


# ------------------------------------------------------------------------------ functional
CASES = {
    "mvc3d": (lambda: icosphere(), F.mean_value_coordinates),
    "gc3d": (lambda: icosphere(), F.green_coordinates),
    "qmvc": (lambda: twisted_bar(3, 30.0), F.quad_mean_value_coordinates),
    "qgc": (lambda: twisted_bar(3, 30.0), F.quad_green_coordinates),
}


@pytest.mark.parametrize("name", list(CASES))
def test_batched_functional_equals_unbatched(name):
    make, fn = CASES[name]
    cage = make()
    B = 3
    V = _jitter(cage, B, amount=0.01)
    bc = torchcage.Cage(V, cage.faces)
    centre = cage.vertices.mean(0)
    x = centre + 0.3 * _ball(3 * 40, seed=2).reshape(B, 40, 3)
    out = fn(x, bc)
    shared = fn(x[0], bc)  # one point set for every cage
    for b in range(B):
        ref = fn(x[b], torchcage.Cage(V[b], cage.faces))
        ref0 = fn(x[0], torchcage.Cage(V[b], cage.faces))
        for o, r, s, r0 in zip(*(t if isinstance(t, tuple) else (t,) for t in (out, ref, shared, ref0)), strict=True):
            assert o.shape[0] == B and (o[b] - r).abs().max() < 1e-12 and (s[b] - r0).abs().max() < 1e-12


def test_batched_2d_and_derivatives():
    square = torchcage.Cage(torch.tensor([[0.0, 0], [1, 0], [1, 1], [0, 1], [0.5, 1.3]], dtype=D64)[[0, 1, 2, 4, 3]])
    g = torch.Generator().manual_seed(3)
    V = square.vertices + 0.03 * torch.randn(2, 5, 2, generator=g, dtype=D64)
    bc = torchcage.Cage(V, None)
    x = 0.2 + 0.6 * torch.rand(2, 30, 2, generator=g, dtype=D64)
    w = F.mean_value_coordinates(x, bc)
    phi, psi = F.green_coordinates(x, bc)
    _, grad, hess = F.mean_value_derivatives(x, bc)
    for b in range(2):
        cb = torchcage.Cage(V[b])
        assert (w[b] - F.mean_value_coordinates(x[b], cb)).abs().max() < 1e-12
        assert (phi[b] - F.green_coordinates(x[b], cb)[0]).abs().max() < 1e-12
        _, gref, href = F.mean_value_derivatives(x[b], cb)
        assert (grad[b] - gref).abs().max() < 1e-10 and (hess[b] - href).abs().max() < 1e-9
    assert grad.shape == (2, 30, 5, 2) and hess.shape == (2, 30, 5, 2, 2) and psi.shape == (2, 30, 5)
    with pytest.raises(torchcage.PointsError, match="broadcast"):
        F.mean_value_coordinates(torch.rand(3, 30, 2, dtype=D64), bc)


def test_float32_batched_values():
    ico = icosphere()
    V = _jitter(ico, 2)
    x = _ball(2 * 200, seed=4).reshape(2, 200, 3)
    w64 = F.mean_value_coordinates(x, torchcage.Cage(V, ico.triangles))
    w32 = F.mean_value_coordinates(x.float(), torchcage.Cage(V.float(), ico.triangles))
    assert w32.dtype == torch.float32 and (w32.double() - w64).abs().max() < 1e-4


# ------------------------------------------------------------------------------ gradients
def _adversarial(cage: torchcage.Cage, n: int = 60) -> torch.Tensor:
    """Inside, near the support planes (on both sides), on faces, at a vertex and far outside."""
    p, tri = cage.vertices, cage.triangles
    centroid = p[tri].mean(1)
    nrm = cage.triangle_normals()
    edge_mid = 0.5 * (p[tri[:, 0]] + p[tri[:, 1]])
    return torch.cat(
        [
            _ball(n, seed=5) * 0.8 * cage.scale / 2,
            centroid[:6] - 1e-7 * nrm[:6],
            centroid[:4] + 1e-5 * nrm[:4],
            centroid[:3],
            edge_mid[:3],
            p[:2],
            1e3 * nrm[:3],
            3.0 * nrm[:3],
        ]
    )


def _plain_autograd(x: torch.Tensor, P: torch.Tensor, faces: torch.Tensor, g: torch.Tensor):
    """The reference: plain autograd of the torch kernel (no custom Function)."""
    xr, Pr = x.clone().requires_grad_(), P.clone().requires_grad_()
    lam = _torch_coordinates(xr, Pr, faces)
    return torch.autograd.grad((lam * g).sum(), [xr, Pr])


@pytest.mark.parametrize("make", [icosphere, lambda: cube().triangulated(), lambda: twisted_bar(quads=False)])
def test_rest_cage_gradients_match_autograd(make):
    """The point's and the rest vertices' gradients against plain autograd of the torch kernel,
    off the cage and on it (a face, an edge, a vertex: there the coordinates have a kink, and both
    take the derivatives of the largest holding face's interpolant); moving the points and the
    cage together changes nothing."""
    cage = make()
    x = _adversarial(cage)
    g = torch.randn(x.shape[0], cage.num_vertices, generator=torch.Generator().manual_seed(6), dtype=D64)
    on = torch.zeros(x.shape[0], dtype=torch.bool)
    on[-14:-6] = True  # (faces' centroids, edges' midpoints, vertices: see _adversarial)
    for rows in (~on, on):
        xr, Pr = x[rows].clone().requires_grad_(), cage.vertices.clone().requires_grad_()
        lam = F.mean_value_coordinates(xr, torchcage.Cage(Pr, cage.triangles, validate=False))
        gx, gP = torch.autograd.grad((lam * g[rows]).sum(), [xr, Pr])
        assert torch.isfinite(gx).all() and torch.isfinite(gP).all()
        assert (gx.sum(0) + gP.sum(0)).abs().max() <= 1e-10 * gP.abs().max()
        rx, rP = _plain_autograd(x[rows], cage.vertices, cage.triangles, g[rows])
        assert (gx - rx).abs().max() <= 1e-9 * rx.abs().max()
        assert (gP - rP).abs().max() <= 1e-9 * rP.abs().max()


def test_torch_and_native_direct_vjp_agree():
    from torchcage.backends import native as _native
    from torchcage.families.mean_value.vjp3d_native import native_vjp

    lib = _native.library()
    if lib is None:
        pytest.skip("native kernel unavailable")
    ico = icosphere()
    x = torch.cat([_ball(300, seed=7), _ball(50, radius=3.0, seed=8)])
    g = torch.randn(x.shape[0], 42, generator=torch.Generator().manual_seed(9), dtype=D64)
    a = direct_vjp(x, ico.vertices, ico.triangles, g, 1e-14)
    b = native_vjp(lib, x, ico.vertices, ico.triangles, g, 1e-14)
    assert torch.equal(a[2], b[2]) and bool(a[2][:300].all())
    assert (a[0] - b[0]).abs().max() < 1e-11 * a[0].abs().max() and (a[1] - b[1]).abs().max() < 1e-11 * a[1].abs().max()


def test_gradcheck_points_and_rest_cage():
    ico = cube().triangulated()  # a small cage: gradcheck perturbs every rest vertex coordinate
    V = _jitter(ico, 2, amount=0.02).requires_grad_()
    x = (0.5 * _ball(2 * 2, seed=10)).reshape(2, 2, 3).requires_grad_()

    def mvc(points, rest):
        return F.mean_value_coordinates(points, torchcage.Cage(rest, ico.triangles, validate=False))

    def gc(points, rest):
        return F.green_coordinates(points, torchcage.Cage(rest, ico.triangles, validate=False))

    assert torch.autograd.gradcheck(mvc, (x, V))
    assert torch.autograd.gradcheck(gc, (x, V))
    assert torch.autograd.gradgradcheck(lambda p: mvc(p, V.detach()), (x,))
    poly = torch.tensor([[0.0, 0], [1, 0], [1.2, 0.8], [0.1, 1]], dtype=D64).requires_grad_()
    y = torch.tensor([[0.4, 0.5], [0.7, 0.3]], dtype=D64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p, q: F.mean_value_coordinates(p, torchcage.Cage(q)), (y, poly))
    assert torch.autograd.gradcheck(lambda p, q: F.green_coordinates(p, torchcage.Cage(q)), (y, poly))


def test_green_backward_is_chunked_and_exact():
    cage = twisted_bar(quads=False)
    x = torch.tensor([[0.05, -0.1, 0.6], [0.2, 0.1, 1.4], [-0.3, 0.2, 0.9]], dtype=D64)
    x = x.repeat(700, 1) + 1e-3 * _ball(2100, seed=11)  # several backward chunks
    g1 = torch.randn(x.shape[0], cage.num_vertices, generator=torch.Generator().manual_seed(12), dtype=D64)
    g2 = torch.randn(x.shape[0], cage.triangles.shape[0], generator=torch.Generator().manual_seed(13), dtype=D64)
    xr, Pr = x.clone().requires_grad_(), cage.vertices.clone().requires_grad_()
    phi, psi = F.green_coordinates(xr, torchcage.Cage(Pr, cage.triangles, validate=False))
    gx, gP = torch.autograd.grad((phi * g1).sum() + (psi * g2).sum(), [xr, Pr])
    # reference: autograd through the torch kernel of each point separately (independent chunking)
    from torchcage.families.green.dispatch import green_flat

    xs, Ps = x[::300].clone().requires_grad_(), cage.vertices.clone().requires_grad_()
    a, b = green_flat(xs, torchcage.Cage(Ps, cage.triangles, validate=False), None, False, "torch")
    rx, rP = torch.autograd.grad((a * g1[::300]).sum() + (b * g2[::300]).sum(), [xs, Ps])
    assert (gx[::300] - rx).abs().max() < 1e-12 * rx.abs().max()
    xr2, Pr2 = x.clone().requires_grad_(), cage.vertices.clone().requires_grad_()
    a, b = green_flat(xr2, torchcage.Cage(Pr2, cage.triangles, validate=False), None, False, "torch")
    _, rP = torch.autograd.grad((a * g1).sum() + (b * g2).sum(), [xr2, Pr2])
    assert (gP - rP).abs().max() < 1e-12 * rP.abs().max()


# ------------------------------------------------------------------------------ modules
@pytest.mark.parametrize("module", [torchcage.MeanValueCoordinates, torchcage.GreenCoordinates])
def test_batched_modules(module):
    ico = icosphere()
    V = _jitter(ico, 3)
    x = 0.7 * _ball(3 * 25, seed=14).reshape(3, 25, 3)
    m = module(torchcage.Cage(V, ico.triangles), x)
    assert m.batch_shape == (3,)
    poses = torch.stack([V, 2 * V + 1])  # (2, 3, V, 3): two poses of each of the three cages
    out = m(poses)
    assert out.shape == (2, 3, 25, 3)
    for b in range(3):
        single = module(torchcage.Cage(V[b], ico.triangles), x[b])
        assert (out[:, b] - single(poses[:, b])).abs().max() < 1e-12
    assert (out[1] - (2 * x + 1)).abs().max() < 1e-10  # similarity reproduced
    with pytest.raises(ValueError, match=r"\(\*, 3, 42, 3\)"):
        m(V[:2])
    with pytest.raises(torchcage.PointsError, match="batched cage"):
        module(ico, x)


def test_module_from_points_that_require_grad_trains_twice():
    ico = icosphere()
    pts = (0.6 * _ball(50, seed=15)).requires_grad_()
    m = torchcage.MeanValueCoordinates(ico, pts * 1.0)
    assert not m.weights.requires_grad and not m.points.requires_grad
    offset = torch.zeros(42, 3, dtype=D64, requires_grad=True)
    opt = torch.optim.SGD([offset], lr=0.1)
    for _ in range(2):  # a kept graph would fail on the second backward
        opt.zero_grad()
        loss = (m(ico.vertices + offset) - 1.1 * pts.detach()).square().sum()
        loss.backward()
        opt.step()
    assert offset.grad is not None and torch.isfinite(offset.grad).all()


@pytest.mark.parametrize("method", ["mvc", "gc", "qmvc", "qgc"])
def test_deform_is_differentiable_in_the_rest_cage(method):
    cage = icosphere() if method in ("mvc", "gc") else twisted_bar(3, 30.0)
    B = 2
    rest = _jitter(cage, B, amount=0.01).requires_grad_()
    x = cage.vertices.mean(0) + 0.3 * _ball(B * 20, seed=16).reshape(B, 20, 3)
    bc = torchcage.Cage(rest, cage.faces, validate="topology")
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(17), dtype=D64))
    q = q * torch.det(q)
    y = torchcage.deform(x, bc, 1.5 * rest @ q.T + 0.2, method=method)
    if method in ("gc", "qgc", "mvc"):  # similarities are reproduced (mvc and qmvc: affine maps)
        assert (y - (1.5 * x @ q.T + 0.2)).abs().max() < 1e-9
    y.square().sum().backward()
    assert rest.grad is not None and torch.isfinite(rest.grad).all() and rest.grad.abs().max() > 0
    if method in ("mvc", "gc"):
        module = (torchcage.MeanValueCoordinates if method == "mvc" else torchcage.GreenCoordinates)(bc, x)
        assert (module(1.5 * rest.detach() @ q.T + 0.2) - y.detach()).abs().max() < 1e-12


def test_polygon_batch_module():
    poly = extruded_polygon([[0, 0], [1, 0], [1, 1], [0, 1]], 1.0)  # a box cage from a polygon
    bc = torchcage.Cage(torch.stack([poly.vertices, 1.1 * poly.vertices]), poly.triangles)
    m = torchcage.MeanValueCoordinates(bc, torch.tensor([[0.5, 0.5, 0.5]], dtype=D64))
    assert m.weights.shape == (2, 1, poly.num_vertices)


@pytest.mark.slow
def test_compiled_training_step():
    """torch.compile(fullgraph=False) of training steps holding a module and ``deform``: they run and
    agree with eager (the graph breaks are reported in docs/learning.md)."""
    ico = icosphere()
    rest0 = ico.vertices.expand(2, -1, -1).clone()
    x = 0.5 * _ball(600, seed=20).reshape(2, 300, 3)
    m = torchcage.MeanValueCoordinates(torchcage.Cage(rest0, ico.triangles), x)
    off = (0.01 * torch.randn(2, 42, 3, generator=torch.Generator().manual_seed(21), dtype=D64)).requires_grad_()

    def step_module(o):
        return m(rest0 + o).square().mean()

    def step_deform(o):
        cage = torchcage.Cage(rest0 + o, ico.triangles, validate="topology")
        return torchcage.deform(x, cage, rest0 + 2 * o).square().mean()

    for fn in (step_module, step_deform):
        torch._dynamo.reset()
        (g_eager,) = torch.autograd.grad(fn(off), off)
        loss = torch.compile(fn, fullgraph=False)(off)
        (g_comp,) = torch.autograd.grad(loss, off)
        assert torch.allclose(loss, fn(off), rtol=1e-12) and torch.allclose(g_comp, g_eager, rtol=1e-10, atol=1e-14)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_batched_values_and_gradients(dtype):
    ico = icosphere()
    rest = _jitter(ico, 3)
    x = 0.7 * _ball(3 * 100, seed=22).reshape(3, 100, 3)
    out = {}
    for device in ("cpu", "cuda"):
        r = rest.to(device, dtype).requires_grad_()
        p = x.to(device, dtype).requires_grad_()
        for method in ("mvc", "gc"):
            y = torchcage.deform(
                p, torchcage.Cage(r, ico.triangles.to(device), validate="topology"), 1.3 * r, method=method
            )
            gp, gr = torch.autograd.grad(y.square().sum(), [p, r])
            out[device, method] = (y.detach().cpu(), gp.cpu(), gr.cpu())
    tol = 1e-4 if dtype == torch.float32 else 1e-10
    for method in ("mvc", "gc"):
        for a, b in zip(out["cpu", method], out["cuda", method], strict=True):
            assert torch.isfinite(b).all() and (a - b).abs().max() <= tol * max(1.0, float(a.abs().max()))
