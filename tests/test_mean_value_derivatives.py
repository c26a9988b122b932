"""Analytic gradients and Hessians of mean value coordinates, and the autograd Functions applying them.

References: central differences of the 60-digit mpmath coordinates (``tests/reference.py``), the
manufactured solution of Thiery et al. (Sec. 7.3: constant and linear precision of the
derivatives), and torch's gradcheck / gradgradcheck."""

from __future__ import annotations

import math

import mpmath as mp
import pytest
import torch
from reference import distance_to_triangles, mvc2d_reference, mvc3d_reference, mvc_derivatives_reference
from support import HANDMADE, data_path

import torchcage
from torchcage import functional as F
from torchcage.errors import CageError, PointsError
from torchcage.geometry import inside_cage

f64 = torch.float64

#: The analytic derivative kernels are native C; tests/test_torch_derivatives.py covers the torch path.
pytestmark = pytest.mark.native


def _size(cage: torchcage.Cage) -> float:
    return cage.scale


def _rel(a: torch.Tensor, ref: torch.Tensor) -> float:
    """Largest entry error relative to the largest entry of the reference (one point)."""
    return float((a - ref).abs().max() / ref.abs().max())


def _qmvc_cage(name: str) -> torchcage.Cage:
    return torchcage.load_cage(data_path("qmvc", f"{name}_Cage.obj")).triangulated()


def _cage(name: str) -> torchcage.Cage:
    return HANDMADE[name]() if name in HANDMADE else _qmvc_cage(name)


def _normals(cage: torchcage.Cage) -> tuple[torch.Tensor, torch.Tensor]:
    p = cage.vertices.to(f64)[cage.triangles]
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    return p, n / n.norm(dim=-1, keepdim=True)


def support_plane_points(cage: torchcage.Cage, heights, min_dist: float = 0.02) -> torch.Tensor:
    """Points at ``h * size`` from a face's support plane (both sides), their foot beyond a corner of
    the face (outside it), at least ``min_dist * size`` from the cage."""
    p, n = _normals(cage)
    size, pts = _size(cage), []
    T = p.shape[0]
    for k, h in enumerate(heights):
        for j in range(T):
            t = (7 * k + 5 * j) % T
            c = p[t].mean(0)
            x = c + 1.7 * (p[t][k % 3] - c) + h * size * n[t]
            if float(distance_to_triangles(x[None], cage.vertices, cage.triangles)[0]) >= min_dist * size:
                pts.append(x)
                break
    return torch.stack(pts)


def far_points(cage: torchcage.Cage, radii, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    v = cage.vertices.to(f64)
    centre = (v.max(0).values + v.min(0).values) / 2
    d = torch.randn(len(radii), cage.dim, generator=g, dtype=f64)
    d = d / d.norm(dim=1, keepdim=True)
    return centre + torch.tensor(radii, dtype=f64)[:, None] * _size(cage) * d


def interior_points(cage: torchcage.Cage, n: int, seed: int = 1) -> torch.Tensor:
    """Random points inside a 3D cage, at least 1e-2 of its size from it."""
    g = torch.Generator().manual_seed(seed)
    v = cage.vertices.to(f64)
    lo, hi = v.min(0).values, v.max(0).values
    x = lo + (hi - lo) * torch.rand(50 * n, 3, generator=g, dtype=f64)
    x = x[inside_cage(x, cage)]
    return x[distance_to_triangles(x, cage.vertices, cage.triangles) > 0.01 * _size(cage)][:n]


# ------------------------------------------------------------------ agreement with mpmath
@pytest.mark.parametrize(
    ("name", "n_inside"),
    # the data-set models are the slow tier's (the hand-made cages keep the property fast)
    [
        ("cube", 3),
        pytest.param("l_shape", 2, marks=pytest.mark.slow),
        pytest.param("ManHead", 2, marks=pytest.mark.slow),
        pytest.param("FireHydrant", 1, marks=pytest.mark.slow),
    ],
)
def test_3d_matches_high_precision_differences(name, n_inside):
    """Gradients and Hessians to 1e-8 relative (measured ~1e-12) at points 1e-3 .. 1e-12 of the
    cage size from faces' support planes (outside the faces, both sides), inside, and 2-5 cage
    sizes away: where the published formulas lose up to 8% in float64."""
    cage = _cage(name)
    heights = [1e-3, -1e-5, 1e-7, -1e-9, 1e-12] if name in ("cube", "l_shape") else [1e-3, -1e-7, 1e-12]
    radii = [2.0, 3.5, 5.0] if name in ("cube", "l_shape") else [2.0, 5.0]
    X = torch.cat([support_plane_points(cage, heights), interior_points(cage, n_inside), far_points(cage, radii)])
    _, G, H = F.mean_value_derivatives(X, cage)
    V, T = cage.vertices, cage.triangles
    for i in range(X.shape[0]):
        gr, hr = mvc_derivatives_reference(X[i].tolist(), lambda y: mvc3d_reference(y, V, T), _size(cage))
        gr, hr = torch.tensor(gr, dtype=f64), torch.tensor(hr, dtype=f64)
        assert _rel(G[i], gr) <= 1e-8, (i, X[i].tolist(), _rel(G[i], gr))
        assert _rel(H[i], hr) <= 1e-8, (i, X[i].tolist(), _rel(H[i], hr))


def _polygon(vertices) -> torchcage.Cage:
    return torchcage.Cage(torch.tensor(vertices, dtype=f64))


def _star(n: int = 7) -> torchcage.Cage:
    ang = torch.arange(2 * n, dtype=f64) * math.pi / n
    r = torch.where(torch.arange(2 * n) % 2 == 0, 1.0, 0.45).double()
    return torchcage.Cage(torch.stack([r * torch.cos(ang), r * torch.sin(ang)], dim=1))


def test_2d_matches_high_precision_differences():
    """2D: points near the edges' support lines (outside the edges), inside, and far away."""
    cage = _star()
    v, size = cage.vertices, cage.scale
    pts = []
    for k, h in enumerate([1e-3, -1e-6, 1e-9, -1e-12]):
        a, b = v[(3 * k) % v.shape[0]], v[(3 * k + 1) % v.shape[0]]
        e = (b - a) / (b - a).norm()
        nrm = torch.stack([-e[1], e[0]])
        pts.append(b + 0.6 * (b - a) + h * size * nrm)  # on the line beyond the edge's end
    pts += [torch.tensor([0.1, 0.05], dtype=f64), torch.tensor([-0.2, 0.1], dtype=f64)]
    X = torch.cat([torch.stack(pts), far_points(cage, [2.0, 5.0])])
    _, G, H = F.mean_value_derivatives(X, cage)
    for i in range(X.shape[0]):
        gr, hr = mvc_derivatives_reference(X[i].tolist(), lambda y: mvc2d_reference(y, v), size)
        gr, hr = torch.tensor(gr, dtype=f64), torch.tensor(hr, dtype=f64)
        assert _rel(G[i], gr) <= 1e-8 and _rel(H[i], hr) <= 1e-8, (i, _rel(G[i], gr), _rel(H[i], hr))


# ------------------------------------------------------------------ manufactured solution
@pytest.mark.parametrize("name", ["cube", "ManHead", pytest.param("FireHydrant", marks=pytest.mark.slow)])
def test_manufactured_solution_on_a_grid(name):
    """Sec. 7.3 of Thiery et al.: sum grad lam = 0, sum p grad lam^T = I, sum H lam = 0 and
    sum p_c H lam = 0 on a 50^3 grid over 1.25 x the cage's box (inside, outside, some points
    exactly on support planes). In units of the cage size: <= 1e-10 (Jacobian) and 1e-9 (Hessian)
    at every grid point farther than 1e-2 of the size from the cage; relative to the size of the
    summed terms (which grow like 1/distance^2 near the cage) <= 1e-10 at every grid point."""
    cage = _cage(name)
    V = cage.vertices.to(f64)
    lo, hi = V.min(0).values, V.max(0).values
    c, half = (lo + hi) / 2, (hi - lo) / 2 * 1.25
    t = torch.linspace(0, 1, 50, dtype=f64)
    X = c - half + 2 * half * torch.stack(torch.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3)
    size = cage.scale
    _, G, H = F.mean_value_derivatives(X, cage)
    assert torch.isfinite(G).all() and torch.isfinite(H).all()
    e1 = G.sum(1).abs().amax(-1) * size
    e2 = (torch.einsum("nvc,vd->ndc", G, V) - torch.eye(3, dtype=f64)).abs().amax((-1, -2))
    e3 = H.sum(1).abs().amax((-1, -2)) * size**2
    e4 = torch.einsum("nvcd,ve->necd", H, V).abs().amax((-1, -2, -3)) * size
    dist = torch.cat([distance_to_triangles(X[i : i + 4000], V, cage.triangles) for i in range(0, X.shape[0], 4000)])
    away = dist > 1e-2 * size
    assert away.float().mean() > 0.9
    assert e1[away].max() <= 1e-10 and e2[away].max() <= 1e-10, (e1[away].max(), e2[away].max())
    assert e3[away].max() <= 1e-9 and e4[away].max() <= 1e-9, (e3[away].max(), e4[away].max())
    gscale = G.abs().sum(1).amax(-1) * size
    hscale = H.abs().sum(1).amax((-1, -2)) * size**2
    assert (e1 / gscale).max() <= 1e-10 and (e3 / hscale).max() <= 1e-10 and (e4 / hscale).max() <= 1e-10


# ------------------------------------------------------------------ degenerate configurations
def _textbook_coordinates(x: torch.Tensor, cage: torchcage.Cage) -> torch.Tensor:
    """The vector form w_i = N_i . m / det of Ju et al., in plain torch ops (what autograd would
    differentiate without torchcage's Functions)."""
    a = cage.vertices.to(f64)[cage.triangles][None] - x[:, None, None, :]  # (n, T, 3, 3)
    N = [torch.linalg.cross(a[:, :, (e + 1) % 3], a[:, :, (e + 2) % 3], dim=-1) for e in range(3)]
    m = 0
    for e in range(3):
        j, k = (e + 1) % 3, (e + 2) % 3
        nn = N[e].norm(dim=-1, keepdim=True)
        theta = torch.atan2(nn, (a[:, :, j] * a[:, :, k]).sum(-1, keepdim=True))
        m = m + theta / 2 * N[e] / nn
    det = (a[:, :, 0] * N[0]).sum(-1)
    w = torch.stack([(N[i] * m).sum(-1) / det for i in range(3)], -1)  # (n, T, 3)
    W = torch.zeros(x.shape[0], cage.num_vertices, dtype=f64)
    W = W.index_add(1, cage.triangles.reshape(-1), w.reshape(x.shape[0], -1))
    return W / W.sum(1, keepdim=True)


def test_finite_on_support_planes_where_autograd_gives_nan():
    """Exactly on support planes and on an edge's support line, outside the cage: torchcage's
    derivatives are finite and agree with the 60-digit reference taken 1e-20 off the planes;
    autograd through the textbook formula returns NaN there (side by side)."""
    cage = HANDMADE["cube"]()  # [-1, 1]^3
    X = torch.tensor([[1.0, 0.3, 2.0], [1.0, 1.0, 2.5], [-0.4, 1.0, -1.7]], dtype=f64)
    offsets = [(1e-20, 0, 0), (1e-20, 1e-20, 0), (0, 1e-20, 0)]  # off every support plane through the point
    xa = X.clone().requires_grad_(True)
    lam_t = _textbook_coordinates(xa, cage)
    (g_t,) = torch.autograd.grad(lam_t[:, 0].sum(), xa)
    assert not torch.isfinite(g_t).all()
    xb = X.clone().requires_grad_(True)
    lam = F.mean_value_coordinates(xb, cage)
    (g,) = torch.autograd.grad(lam[:, 0].sum(), xb, create_graph=True)
    (h,) = torch.autograd.grad(g[:, 0].sum(), xb)
    assert torch.isfinite(g).all() and torch.isfinite(h).all()
    _, G, H = F.mean_value_derivatives(X, cage)
    assert torch.equal(g.detach(), G[:, 0]) and torch.allclose(h, H[:, 0, 0], rtol=0, atol=1e-15)
    for i, off in enumerate(offsets):
        y = [mp.mpf(float(v)) + mp.mpf(o) for v, o in zip(X[i], off, strict=True)]
        gr, hr = mvc_derivatives_reference(y, lambda z: mvc3d_reference(z, cage.vertices, cage.triangles), 3.5)
        assert _rel(G[i], torch.tensor(gr, dtype=f64)) <= 1e-8
        assert _rel(H[i], torch.tensor(hr, dtype=f64)) <= 1e-8


def test_on_the_cage():
    """On the cage the coordinates are not differentiable: the functional API says so; autograd
    gives the derivatives of the interpolating formula (finite, reproducing constants)."""
    cage = HANDMADE["cube"]()
    x = torch.tensor([[1.0, 0.2, 0.3], [0.1, 0.2, -0.3]], dtype=f64)
    with pytest.raises(PointsError, match="on the cage"):
        F.mean_value_derivatives(x, cage)
    xr = x.clone().requires_grad_(True)
    lam = F.mean_value_coordinates(xr, cage)
    J = torch.stack([torch.autograd.grad(lam[:, i].sum(), xr, retain_graph=True)[0] for i in range(8)], 1)
    assert torch.isfinite(J).all() and J.sum(1).abs().max() < 1e-12


# ------------------------------------------------------------------ autograd
def test_gradcheck_and_gradgradcheck_3d():
    cage = HANDMADE["l_shape"]()
    # the third point lies exactly on the top cap's support plane (z = 0.5), outside the cap
    x = torch.tensor([[0.5, -0.5, 0.3], [-0.5, 0.5, 0.2], [0.3, 0.35, 0.5], [3.0, 1.0, -2.0]], dtype=f64)
    x.requires_grad_(True)
    P = cage.vertices.to(f64).clone().requires_grad_(True)

    def f(x, P):
        return F.mean_value_coordinates(x, torchcage.Cage(P, cage.triangles, validate=False))

    assert torch.autograd.gradcheck(f, (x, P), fast_mode=True)
    assert torch.autograd.gradgradcheck(f, (x, P), fast_mode=True)


def test_gradcheck_and_gradgradcheck_2d():
    cage = _star()
    x = torch.tensor([[0.1, 0.2], [0.3, -0.1], [2.0, 0.5]], dtype=f64, requires_grad=True)
    P = cage.vertices.clone().requires_grad_(True)

    def f(x, P):
        return F.mean_value_coordinates(x, torchcage.Cage(P, validate=False))

    assert torch.autograd.gradcheck(f, (x, P))
    assert torch.autograd.gradgradcheck(f, (x, P))


def test_torch_func_transforms():
    """jacrev, hessian (forward over reverse), vmap and vmap(jacrev) agree with the kernels."""
    from torch.func import hessian, jacrev, vmap

    cage = HANDMADE["cube"]()
    X = torch.tensor([[0.1, 0.2, -0.3], [0.5, -0.6, 0.2], [2.0, 0.5, 0.1]], dtype=f64)
    lam, G, H = F.mean_value_derivatives(X, cage)

    def f(p):
        return F.mean_value_coordinates(p, cage)

    assert torch.allclose(vmap(f)(X), lam, atol=1e-15)
    assert torch.allclose(vmap(jacrev(f))(X), G, atol=1e-15)
    for i in range(X.shape[0]):
        assert torch.allclose(jacrev(f)(X[i]), G[i], atol=1e-15)
        assert torch.allclose(hessian(f)(X[i]), H[i], atol=1e-14)
        assert torch.allclose(jacrev(jacrev(f))(X[i]), H[i], atol=1e-14)


def test_third_derivatives_raise():
    cage = HANDMADE["cube"]()
    x = torch.tensor([[0.1, 0.2, -0.3]], dtype=f64, requires_grad=True)
    lam = F.mean_value_coordinates(x, cage)
    (g,) = torch.autograd.grad(lam[0, 0], x, create_graph=True)
    (h,) = torch.autograd.grad(g[0, 0], x, create_graph=True)
    with pytest.raises(RuntimeError, match="third derivatives"):
        torch.autograd.grad(h[0, 0], x)


# ------------------------------------------------------------------ API
def test_shapes_dtypes_and_errors():
    cage = HANDMADE["cube"]()
    x = torch.tensor([[[0.1, 0.2, -0.3], [0.5, -0.6, 0.2]]], dtype=torch.float32)
    lam, G, H = F.mean_value_derivatives(x, cage)
    assert lam.shape == (1, 2, 8) and G.shape == (1, 2, 8, 3) and H.shape == (1, 2, 8, 3, 3)
    assert G.dtype == torch.float32
    assert F.mean_value_derivatives(x, cage, order=1)[2] is None
    assert torch.equal(F.mean_value_gradients(x, cage), G) and torch.equal(F.mean_value_hessians(x, cage), H)
    assert torch.allclose(H, H.transpose(-1, -2))
    with pytest.raises(ValueError, match="order"):
        F.mean_value_derivatives(x, cage, order=3)
    with pytest.raises(PointsError, match="NaN"):
        F.mean_value_derivatives(torch.tensor([[float("nan"), 0, 0]]), cage)
    with pytest.raises(CageError, match="quads"):
        F.mean_value_derivatives(x, torchcage.load_cage(torchcage.data.path("cube.obj")))
    xs = torch.randn(5000, 3, dtype=f64) * 0.4
    _, Ga, Ha = F.mean_value_derivatives(xs, cage, chunk_size=700)
    _, Gb, Hb = F.mean_value_derivatives(xs, cage)
    assert torch.equal(Ga, Gb) and torch.equal(Ha, Hb)


# ------------------------------------------------------------------ module
@pytest.mark.parametrize("store", [0, 2])
def test_module_jacobian_and_hessian(store):
    """J = s R and H = 0 under a similarity; for a bent pose J and H equal torch.func derivatives
    of x -> mvc(x) @ V' at the embedded points; both differentiable w.r.t. the deformed vertices."""
    from torch.func import hessian, jacrev

    cage = HANDMADE["l_shape"]()
    pts = torch.tensor([[0.5, -0.5, 0.1], [-0.5, 0.5, -0.2], [-0.4, -0.3, 0.3]], dtype=f64)
    m = torchcage.MeanValueCoordinates(cage, pts, store_derivatives=store)
    R = torch.linalg.qr(torch.randn(3, 3, dtype=f64, generator=torch.Generator().manual_seed(3)))[0]
    P = 1.7 * cage.vertices.to(f64) @ R.T + torch.tensor([0.3, -2.0, 1.0], dtype=f64)
    assert (m.jacobian(P) - 1.7 * R).abs().max() < 1e-12
    assert m.hessian(P).abs().max() < 1e-11
    bent = cage.vertices.to(f64).clone()
    bent[:, 0] += 0.3 * bent[:, 2] ** 2
    bent = torch.stack([bent, 1.1 * bent])  # a batch of two poses
    J, H = m.jacobian(bent), m.hessian(bent)
    assert J.shape == (2, 3, 3, 3) and H.shape == (2, 3, 3, 3, 3)
    for i in range(3):
        ref_j = jacrev(lambda x: F.mean_value_coordinates(x[None], cage)[0] @ bent[0])(pts[i])
        ref_h = hessian(lambda x: F.mean_value_coordinates(x[None], cage)[0] @ bent[0])(pts[i])
        assert torch.allclose(J[0, i], ref_j, atol=1e-13) and torch.allclose(H[0, i], ref_h, atol=1e-12)
    v = bent[0].clone().requires_grad_(True)
    loss = ((m.jacobian(v) - torch.eye(3, dtype=f64)) ** 2).sum() + (m.hessian(v) ** 2).sum()
    loss.backward()
    assert torch.isfinite(v.grad).all() and v.grad.abs().max() > 0
    if store:
        assert set(m.state_dict()) >= {"gradients", "hessians"}
