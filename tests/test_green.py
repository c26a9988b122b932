"""Green coordinates for triangle cages: identity, quadrature, similarity, on-cage limits."""

from __future__ import annotations

import math

import pytest
import torch
from support import HANDMADE, QMVC_MODELS, data_path

import torchcage
from torchcage import functional as F
from torchcage._core.common import collapsed_gauss


def winding_number(x: torch.Tensor, cage: torchcage.Cage) -> torch.Tensor:
    """Generalised winding number by the Van Oosterom-Strackee solid angle (independent of the
    library's edge-sum form); 1 inside, 0 outside."""
    a = cage.vertices[cage.triangles][None] - x[:, None, None]  # (n, T, 3, 3)
    R = a.norm(dim=-1)
    det = torch.linalg.det(a)
    d01, d12, d20 = (
        (a[..., 0, :] * a[..., 1, :]).sum(-1),
        (a[..., 1, :] * a[..., 2, :]).sum(-1),
        (a[..., 2, :] * a[..., 0, :]).sum(-1),
    )
    den = R[..., 0] * R[..., 1] * R[..., 2] + d01 * R[..., 2] + d12 * R[..., 0] + d20 * R[..., 1]
    return (2 * torch.atan2(det, den)).sum(-1) / (4 * math.pi)


def inside_points(cage: torchcage.Cage, n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    v = cage.vertices
    lo, hi = v.min(0).values, v.max(0).values
    x = lo + (hi - lo) * torch.rand(4 * n, 3, generator=g, dtype=torch.float64)
    return x[winding_number(x, cage) > 0.5][:n]


def quadrature(x: torch.Tensor, cage: torchcage.Cage, levels: int = 4) -> tuple[torch.Tensor, torch.Tensor]:
    """The defining integrals by brute force: each triangle split into 4**levels pieces, a 10x10
    collapsed Gauss rule on each; phi_i = int Gamma_i h / (4 pi r^3), psi_t = int 1 / (4 pi r)."""
    bary, w = collapsed_gauss(10, torch.float64, x.device)
    sub = torch.tensor([[[1.0, 0, 0], [0, 1, 0], [0, 0, 1]]], dtype=torch.float64)
    for _ in range(levels):  # midpoint subdivision in barycentric space
        a, b, c = sub[:, 0], sub[:, 1], sub[:, 2]
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        sub = torch.cat([torch.stack(t, 1) for t in ([a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca])])
    nodes = torch.einsum("qk,skj->sqj", bary, sub).reshape(-1, 3)  # barycentric coords of all nodes
    weights = (w[None] / sub.shape[0]).expand(sub.shape[0], -1).reshape(-1) * 2  # sums to 1 per triangle
    p = cage.vertices[cage.triangles]  # (T, 3, 3)
    xi = torch.einsum("qk,tkj->tqj", nodes, p)  # (T, Q, 3)
    cross = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    area, n = cross.norm(dim=-1) / 2, torch.nn.functional.normalize(cross, dim=-1)
    d = xi[None] - x[:, None, None]  # (N, T, Q, 3)
    r = d.norm(dim=-1)
    h = (d * n[None, :, None]).sum(-1)
    psi = (weights / r).sum(-1) * area / (4 * math.pi)
    dens = weights * h / r**3 * area[None, :, None] / (4 * math.pi)  # (N, T, Q)
    phi = torch.zeros(x.shape[0], cage.num_vertices, dtype=torch.float64)
    for k in range(3):
        phi.index_add_(1, cage.triangles[:, k], (dens * nodes[:, k]).sum(-1))
    return phi, psi


@pytest.mark.parametrize("name", list(HANDMADE))
def test_identity_inside(name):
    cage = HANDMADE[name]()
    x = inside_points(cage, 300)
    phi, psi = F.green_coordinates(x, cage)
    assert (phi.sum(1) - 1).abs().max() < 1e-12
    assert (phi @ cage.vertices + psi @ cage.triangle_normals() - x).abs().max() / cage.scale < 1e-10


@pytest.mark.parametrize("model", QMVC_MODELS)
def test_identity_inside_paper_cages(model):
    cage = torchcage.load_cage(data_path("qmvc", f"{model}_Cage.obj")).triangulated()
    x = inside_points(cage, 400, seed=1)
    phi, psi = F.green_coordinates(x, cage)
    assert (phi @ cage.vertices + psi @ cage.triangle_normals() - x).abs().max() / cage.scale < 1e-10


def test_agrees_with_quadrature():
    cage = HANDMADE["l_shape"]()
    x = torch.tensor([[-0.5, -0.5, 0.0], [0.5, -0.4, 0.1], [-0.4, 0.6, -0.2]], dtype=torch.float64)
    phi, psi = F.green_coordinates(x, cage)
    qphi, qpsi = quadrature(x, cage)
    assert (phi - qphi).abs().max() < 1e-8
    assert (psi - qpsi).abs().max() < 1e-8


def test_on_and_near_the_cage():
    cage = HANDMADE["twisted_bar"]()
    p, tri = cage.vertices, cage.triangles
    nrm = cage.triangle_normals()
    g = torch.Generator().manual_seed(2)
    b = torch.rand(tri.shape[0], 3, generator=g, dtype=torch.float64)
    b = b / b.sum(1, keepdim=True)
    on_face = torch.einsum("tk,tkj->tj", b, p[tri])
    on_edge = 0.5 * (p[tri[:, 0]] + p[tri[:, 1]])
    pts = [on_face, on_edge, p]
    for d in [1e-15, 1e-9, 1e-4]:
        pts.append(on_face - d * cage.scale * nrm)  # just inside
    x = torch.cat(pts)
    phi, psi = F.green_coordinates(x, cage)
    assert torch.isfinite(phi).all() and torch.isfinite(psi).all()
    assert (phi.sum(1) - 1).abs().max() < 1e-12
    assert (phi @ p + psi @ nrm - x).abs().max() / cage.scale < 1e-10


def test_module_similarity_and_gradients():
    cage = HANDMADE["twisted_bar"]()
    x = inside_points(cage, 200, seed=3)
    gc = torchcage.GreenCoordinates(cage, x)
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64))
    if torch.det(q) < 0:
        q = -q
    t = torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)
    for s in (0.3, 1.0, 7.0):
        out = gc(s * cage.vertices @ q.T + t)
        assert (out - (s * x @ q.T + t)).abs().max() / (s * cage.scale) < 1e-9
    poses = torch.stack([cage.vertices, 2 * cage.vertices])
    assert gc(poses).shape == (2, 200, 3)
    small = torchcage.GreenCoordinates(cage, x[:3])
    v = (cage.vertices + 0.05 * torch.randn(cage.vertices.shape, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(small, (v,))


def test_errors():
    with pytest.raises(torchcage.CageError, match="triangulated"):
        F.green_coordinates(
            torch.zeros(1, 3, dtype=torch.float64), torchcage.load_cage(torchcage.data.path("cube.obj"))
        )
    with pytest.raises(torchcage.PointsError, match=r"\(\.\.\., 2\)"):
        F.green_coordinates(torch.zeros(1, 3, dtype=torch.float64), torchcage.Cage([[0.0, 0], [1, 0], [0, 1]]))


def test_inside_points_on_the_planes_of_other_faces():
    """Inside the L-shape, on and next to the planes of its inner walls (outside those faces)."""
    cage = HANDMADE["l_shape"]()
    pts = []
    for d in [0.0, 1e-15, -1e-15, 1e-12, 1e-9, -1e-9, 1e-6]:
        pts += [[d, -0.5, 0.1], [-0.5, d, -0.2], [0.5 + d, -0.5, 0.3], [-0.3, -0.7, d]]
    x = torch.tensor(pts, dtype=torch.float64)
    phi, psi = F.green_coordinates(x, cage)
    assert (phi @ cage.vertices + psi @ cage.triangle_normals() - x).abs().max() < 1e-14


def test_native_and_torch_kernels_agree():
    from torchcage.backends import native as _native

    if not _native.available():
        pytest.skip("native kernel unavailable")
    cage = HANDMADE["notched"]()
    p, tri = cage.vertices, cage.triangles
    nrm = cage.triangle_normals()
    centroids = p[tri].mean(1)
    edges_mid = 0.5 * (p[tri[:, 0]] + p[tri[:, 1]])
    far = 3.0 * torch.randn(50, 3, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    x = torch.cat(
        [inside_points(cage, 300, seed=6), centroids, edges_mid, p, centroids - 1e-9 * nrm, centroids + 1e-3 * nrm, far]
    )
    a = F.green_coordinates(x, cage, backend="native")
    b = F.green_coordinates(x, cage, backend="torch")
    assert (a[0] - b[0]).abs().max() < 1e-12 and (a[1] - b[1]).abs().max() < 1e-12
    c = F.green_coordinates(x, cage, backend="native", chunk_size=7)  # written block by block
    assert torch.equal(a[0], c[0]) and torch.equal(a[1], c[1])
    xr = x[:3].clone().requires_grad_(True)
    phi, _ = F.green_coordinates(xr, cage, backend="native")  # values native, derivatives recomputed by torch
    (g_native,) = torch.autograd.grad(phi.sum(), xr)
    phi, _ = F.green_coordinates(xr, cage, backend="torch")
    (g_torch,) = torch.autograd.grad(phi.sum(), xr)
    assert phi.requires_grad and torch.allclose(g_native, g_torch, rtol=0, atol=1e-12)
