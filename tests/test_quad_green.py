"""Green coordinates for triquad cages: linear precision by construction, on-cage limits,
similarity (conformal) and rigid (area) reproduction, mirror symmetry, agreement with a densely
tessellated triangle-GC reference, backends and gradients."""

from __future__ import annotations

import pytest
import torch
from support import (
    QMVC_MODELS,
    bent_box,
    box_cage,
    box_points,
    data_path,
    model_points,
    quad_adversarial_points,
    triquad,
)

import torchcage
from torchcage import functional as F
from torchcage.families.green.stretch import triangle_frames


def normals(cage: torchcage.Cage) -> torch.Tensor:
    """The vectors ``psi`` multiplies at rest: unit triangle normals, then quad corner normals."""
    parts = []
    if cage.triangles.shape[0]:
        p = cage.vertices[cage.triangles].to(torch.float64)
        n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
        parts.append(torch.nn.functional.normalize(n, dim=-1))
    parts.append(cage.quad_corner_normals().reshape(-1, 3).to(torch.float64))
    return torch.cat(parts)


def fine_surface(cage: torchcage.Cage, verts: torch.Tensor, m: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Every quad of ``cage`` (with vertex positions ``verts``) split into ``m x m`` bilinear
    sub-quads of two triangles: ``(positions, triangles)`` of a closed triangle surface (the cage's
    triangles kept), vertices shared by position of the rest cage."""
    q, V = cage.quads, cage.num_vertices
    t = torch.linspace(0, 1, m + 1, dtype=torch.float64)
    U, W = (a.reshape(-1) for a in torch.meshgrid(t, t, indexing="ij"))
    basis = torch.stack([(1 - U) * (1 - W), U * (1 - W), U * W, (1 - U) * W], 1)
    rest = torch.cat(
        [cage.vertices.to(torch.float64), torch.einsum("gk,qkc->qgc", basis, cage.vertices[q].double()).reshape(-1, 3)]
    )
    pos = torch.cat([verts, torch.einsum("gk,qkc->qgc", basis, verts[q]).reshape(-1, 3)])
    _, inv = torch.unique(torch.round(rest * 1e9).long(), dim=0, return_inverse=True)
    nv = int(inv.max()) + 1
    fpos = torch.zeros(nv, 3, dtype=torch.float64).index_copy(0, inv, pos)
    gid = inv[V:].reshape(q.shape[0], m + 1, m + 1)
    a, b, c, d = gid[:, :-1, :-1], gid[:, 1:, :-1], gid[:, 1:, 1:], gid[:, :-1, 1:]
    tris = [torch.stack([a, b, c], -1).reshape(-1, 3), torch.stack([a, c, d], -1).reshape(-1, 3)]
    if cage.triangles.shape[0]:
        tris.append(inv[cage.triangles])
    return fpos, torch.cat(tris)


def winding_number(x: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """Sum of the signed solid angles of triangles ``(T, 3, 3)`` seen from ``x`` ``(N, 3)``, over
    4 pi (Van Oosterom and Strackee), in slices of points."""
    out = []
    for xs in x.split(64):
        a = corners[None] - xs[:, None, None, :]  # (n, T, 3, 3)
        R = a.norm(dim=-1)
        det = (a[..., 0, :] * torch.linalg.cross(a[..., 1, :], a[..., 2, :], dim=-1)).sum(-1)
        dots = [(a[..., i, :] * a[..., j, :]).sum(-1) for i, j in ((0, 1), (0, 2), (1, 2))]
        den = R.prod(-1) + dots[0] * R[..., 2] + dots[1] * R[..., 1] + dots[2] * R[..., 0]
        out.append((2 * torch.atan2(det, den)).sum(-1) / (4 * torch.pi))
    return torch.cat(out)


def inside_bilinear(x: torch.Tensor, cage: torchcage.Cage, levels: tuple[int, int] = (12, 24)) -> torch.Tensor:
    """Points inside the cage bounded by the bilinear quads (winding numbers with the quads
    tessellated at both ``levels`` agree), an independent test: the triangulated cage's interior differs
    near curved quads."""
    res = []
    v = cage.vertices.to(torch.float64)
    for m in levels:
        t = torch.linspace(0, 1, m + 1, dtype=torch.float64)
        U, W = (g.reshape(-1) for g in torch.meshgrid(t, t, indexing="ij"))
        basis = torch.stack([(1 - U) * (1 - W), U * (1 - W), U * W, (1 - U) * W], 1)
        grid = torch.einsum("gk,qkc->qgc", basis, v[cage.quads]).reshape(-1, m + 1, m + 1, 3)
        a, b, c, d = grid[:, :-1, :-1], grid[:, 1:, :-1], grid[:, 1:, 1:], grid[:, :-1, 1:]
        tris = [torch.stack([a, b, c], -2).reshape(-1, 3, 3), torch.stack([a, c, d], -2).reshape(-1, 3, 3)]
        if cage.triangles.shape[0]:
            tris.append(v[cage.triangles])
        res.append(winding_number(x, torch.cat(tris)) > 0.5)
    return res[0] & res[1]


def inside_points(cage: torchcage.Cage, n: int, spread: float = 1.0, seed: int = 0) -> torch.Tensor:
    x = box_points(cage, n, spread=spread, seed=seed)
    return x[inside_bilinear(x, cage)]


def assert_reproduces(phi: torch.Tensor, psi: torch.Tensor, cage: torchcage.Cage, x: torch.Tensor) -> None:
    err = (phi @ cage.vertices.to(torch.float64) + psi @ normals(cage) - x).abs().max() / cage.scale
    assert err <= 1e-10, f"linear precision {err:.2e}"
    assert (phi.sum(dim=1) - 1).abs().max() <= 1e-12


# ----------------------------------------------------------------------------- exact properties
@pytest.mark.parametrize("make", [bent_box, triquad, lambda: box_cage(1, 2, 1)], ids=["bent", "triquad", "box"])
def test_linear_precision_inside_and_on_the_cage(make, backend):
    cage = make()
    x = inside_points(cage, 300)
    on = quad_adversarial_points(cage, distances=(0.0,))[:-9].reshape(-1, 4, 3)[:, :3].reshape(-1, 3)
    pts = torch.cat([x, on])
    phi, psi = F.quad_green_coordinates(pts, cage, backend=backend)
    assert psi.shape == (pts.shape[0], cage.triangles.shape[0] + 4 * cage.quads.shape[0])
    assert torch.isfinite(phi).all() and torch.isfinite(psi).all()
    assert_reproduces(phi, psi, cage, pts)


def test_unit_cube_linear_precision(backend):
    """(A third-party QGC implementation misses this by 8.6e-3.)"""
    cube = box_cage(size=(1.0, 1.0, 1.0))
    g = torch.Generator().manual_seed(4)
    x = torch.rand(200, 3, generator=g, dtype=torch.float64) * 0.98 - 0.49
    phi, psi = F.quad_green_coordinates(x, cube, backend=backend)
    assert_reproduces(phi, psi, cube, x)


@pytest.mark.parametrize("model", QMVC_MODELS)
def test_data_cages_linear_precision(model, backend):
    cage = torchcage.load_cage(data_path("qmvc", f"{model}_Cage.obj"))
    g = torch.Generator().manual_seed(0)
    pts = model_points(model, cage, 400)
    pts = pts[torch.randperm(pts.shape[0], generator=g)[: 300 if backend == "native" else 60]]
    x = pts[inside_bilinear(pts, cage, (6, 12))]
    phi, psi = F.quad_green_coordinates(x, cage, backend=backend)
    assert torch.isfinite(psi).all()
    assert_reproduces(phi, psi, cage, x)


# ----------------------------------------------------------------------------- deformation
@pytest.mark.parametrize("scale", [1e-3, 1.0, 2.5, 1e3])
def test_similarity_reproduced_with_the_conformal_correction(scale):
    cage = triquad()
    x = inside_points(cage, 150)
    module = torchcage.QuadGreenCoordinates(cage, x)
    R = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5)))[0]
    R = R * torch.sign(torch.det(R))
    t = torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)
    moved = module(scale * cage.vertices @ R.T + t)
    err = (moved - (scale * x @ R.T + t)).abs().max() / (scale * cage.scale)
    assert err <= 1e-9


def test_area_variant_reproduces_rigid_motions_only():
    cage = bent_box()
    x = inside_points(cage, 150)
    module = torchcage.QuadGreenCoordinates(cage, x, correction="area")
    R = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(6)))[0]
    R = R * torch.sign(torch.det(R))
    t = torch.tensor([1.0, 2.0, -0.5], dtype=torch.float64)
    assert (module(cage.vertices @ R.T + t) - (x @ R.T + t)).abs().max() <= 1e-9 * cage.scale
    assert (module(2 * cage.vertices) - 2 * x).abs().max() > 1e-3  # not scale-invariant, by design


def test_mirror_symmetric_deformation_stays_symmetric():
    cage = bent_box()
    mirror = torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    x = inside_points(cage, 150)
    x = torch.cat([x, x * mirror])
    v = cage.vertices
    deformed = v.clone()
    deformed[:, 2] = v[:, 2] * (1 + 0.4 * v[:, 0] ** 2)  # even in x: a symmetric edit
    deformed[:, 1] = v[:, 1] + 0.2 * v[:, 0] ** 2
    for correction in ("conformal", "area"):
        y = torchcage.QuadGreenCoordinates(cage, x, correction=correction)(deformed)
        half = x.shape[0] // 2
        assert (y[half:] - y[:half] * mirror).abs().max() <= 1e-10


def tessellated_green(cage: torchcage.Cage, x: torch.Tensor, deformed: torch.Tensor, m: int) -> torch.Tensor:
    """Reference: triangle Green coordinates on the quads tessellated ``m x m`` (in rest and deformed
    pose alike), with the area-based Neumann condition ``N'_t / |N_t|``."""
    rest_pos, tris = fine_surface(cage, cage.vertices.to(torch.float64), m)
    def_pos, _ = fine_surface(cage, deformed, m)
    phi, psi = F.green_coordinates(x, torchcage.Cage(rest_pos, tris))
    u0, v0, _ = triangle_frames(rest_pos, tris)
    u1, v1, _ = triangle_frames(def_pos, tris)
    N0, N1 = torch.linalg.cross(u0, v0, dim=-1), torch.linalg.cross(u1, v1, dim=-1)
    return phi @ def_pos + psi @ (N1 / N0.norm(dim=-1, keepdim=True))


def test_area_variant_converges_to_tessellated_green_coordinates():
    """Measured on the bent box, max error vs m = 32 (reference m = 16 vs 32: 5e-5): n = 1: 3.4e-3,
    2: 2.0e-3, 4: 7.8e-4, 8: 2.6e-4; GC on the triangulated cage: 0.106."""
    cage = bent_box()
    x = inside_points(cage, 60, spread=0.6)
    g = torch.Generator().manual_seed(0)
    deformed = cage.vertices + 0.25 * torch.randn(cage.vertices.shape, generator=g, dtype=torch.float64)
    ref = tessellated_green(cage, x, deformed, 32)
    err = {
        n: (torchcage.QuadGreenCoordinates(cage, x, n, correction="area")(deformed) - ref).abs().max() for n in (1, 8)
    }
    assert err[8] < 5e-4
    assert err[8] < err[1] / 4
    triangulated = (torchcage.GreenCoordinates(cage.triangulated(), x)(deformed) - ref).abs().max()
    assert triangulated > 20 * err[8]


def test_collapsed_deformed_quad_stays_finite():
    cage = bent_box()
    x = inside_points(cage, 40)
    module = torchcage.QuadGreenCoordinates(cage, x)
    deformed = cage.vertices.clone()
    deformed[cage.quads[0]] = deformed[cage.quads[0]].mean(0)  # quad 0 collapsed to a point
    assert torch.isfinite(module(deformed)).all()


# ----------------------------------------------------------------------------- backends, gradients, API
@pytest.mark.filterwarnings("ignore::torchcage.OutsideCageWarning")  # (far points, on purpose)
def test_backends_agree():
    from torchcage.backends import native as _native

    if not _native.available():
        pytest.skip("no C compiler")
    cage = triquad()
    v, tri = cage.vertices.to(torch.float64), cage.triangles
    assert tri.shape[0] > 0
    on_tri = torch.cat([v[tri].mean(1), 0.5 * (v[tri[:, 0]] + v[tri[:, 1]])])  # on the triangles, their edges
    far = 3 * cage.scale * torch.randn(20, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    x = torch.cat(
        [inside_points(cage, 200), quad_adversarial_points(cage, distances=(0.0, 1e-6, 1e-3))[:-9], on_tri, far]
    )
    phi, psi = F.quad_green_coordinates(on_tri, cage, backend="native")  # the limit from inside
    assert_reproduces(phi, psi, cage, on_tri)
    for n in (1, 2):
        a = F.quad_green_coordinates(x, cage, n, backend="native")
        b = F.quad_green_coordinates(x, cage, n, backend="torch")
        # (the native Riemann sum takes Van Oosterom's solid angle: measured <= 2e-11)
        for u, w in zip(a, b, strict=True):
            torch.testing.assert_close(u, w, atol=1e-10, rtol=0)


def test_gradients():
    cage = bent_box()
    x = inside_points(cage, 30, spread=0.7)[:2].clone().requires_grad_(True)
    torch.autograd.gradcheck(lambda p: F.quad_green_coordinates(p, cage, 1), (x,), eps=1e-6, atol=1e-6, fast_mode=True)
    module = torchcage.QuadGreenCoordinates(cage, x.detach())
    verts = (cage.vertices * 1.1).requires_grad_(True)
    torch.autograd.gradcheck(module, (verts,), eps=1e-6, atol=1e-6, fast_mode=True)


def test_module_batches_state_dict_and_errors():
    cage = triquad()
    x = inside_points(cage, 30)
    m = torchcage.QuadGreenCoordinates(cage, x)
    poses = torch.stack([cage.vertices, 2 * cage.vertices, cage.vertices + 1])
    out = m(poses)
    assert out.shape == (3, x.shape[0], 3)
    torch.testing.assert_close(out[1], 2 * x, atol=1e-9, rtol=0)
    m2 = torchcage.QuadGreenCoordinates(cage, torch.zeros_like(x), 1)
    m2.load_state_dict(m.state_dict())
    torch.testing.assert_close(m2(poses), out)
    with pytest.raises(ValueError, match="correction"):
        torchcage.QuadGreenCoordinates(cage, x, correction="lipman")
    with pytest.raises(ValueError, match="positive integer"):
        F.quad_green_coordinates(x, cage, n=0)
    with pytest.raises(ValueError, match=r"past 10000.*tol="):  # (the kernels' C ints and scratch stay bounded)
        F.quad_green_coordinates(x, cage, n=10_001)
    with pytest.raises(ValueError, match="shape"):
        m(poses[..., :2])
