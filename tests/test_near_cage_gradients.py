"""Gradients of 3D mean value coordinates at points on and near the cage (issue 44, item 3).

The fused backward (``ops._joint_vjp``) hands the points it cannot take (near a face's support
plane, on the cage) to autograd of the torch kernel. Points on the cage used to evaluate the
regular formula at a stand-in point far outside (to keep the discarded branch's derivatives
finite), which took the far-field quadrature on every face: a hundred times an ordinary point.
These tests check that the regular formula now runs on the off-cage points only, and that the
gradients there are right: on faces, those of the barycentric interpolant (closed form, autograd);
within ``1e-12 .. 1e-4`` of the size from a face, on both sides, 60-digit central differences of
the mpmath reference (``tests/reference.py``), to the target of ``test_gradient_references``.
"""

from __future__ import annotations

import pytest
import torch
from reference import gradient_reference, mvc3d_reference

import torchcage as tc
from torchcage import functional as F
from torchcage.families.mean_value import kernel3d, ops
from torchcage.testing import icosphere, twisted_bar

D64 = torch.float64
TARGET = 1e-7  # relative, as tests/test_gradient_references.py
STEP = 1e-15  # of the size


def _cube() -> tc.Cage:
    return tc.load_cage(tc.data.path("cube.obj")).to(D64).triangulated()


def _face_points(cage: tc.Cage, k: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``k`` points inside random faces: ``(points (k, 3), faces (k,), barycentric weights (k, 3))``."""
    g = torch.Generator().manual_seed(seed)
    f = torch.randint(0, cage.triangles.shape[0], (k,), generator=g)
    w = 0.1 + torch.rand(k, 3, generator=g, dtype=D64)  # away from the edges
    w = w / w.sum(-1, keepdim=True)
    y = (w[..., None] * cage.vertices[cage.triangles[f]]).sum(-2)
    return y, f, w


def _grads(x: torch.Tensor, cage: tc.Cage, cot: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Gradients of ``sum cot * lam`` with respect to the points and the rest vertices (the fused
    first-order backward)."""
    xx, V = x.clone().requires_grad_(), cage.vertices.clone().requires_grad_()
    lam = F.mean_value_coordinates(xx, tc.Cage(V, cage.triangles, validate=False))
    (lam * cot).sum().backward()
    return xx.grad, V.grad


def test_points_on_the_cage_skip_the_regular_formula(monkeypatch):
    """Autograd of the torch kernel evaluates the face weights of the off-cage points only (it
    evaluated them for every point, at a far stand-in for those on the cage)."""
    cage = _cube()
    y, _, _ = _face_points(cage, 6, 0)
    x = torch.cat([y, torch.tensor([[0.1, 0.2, -0.3], [0.4, -0.5, 0.2]], dtype=D64)])
    seen: list[int] = []
    inner = kernel3d.face_weights

    def spy(pts, *args, **kwargs):
        seen.append(pts.shape[0])
        return inner(pts, *args, **kwargs)

    monkeypatch.setattr(kernel3d, "face_weights", spy)
    xx = x.clone().requires_grad_()
    lam = ops._torch_coordinates(xx, cage.vertices, cage.triangles)  # (the backward's fallback)
    (gx,) = torch.autograd.grad((lam * lam).sum(), xx)
    assert seen and max(seen) == 2, seen
    assert torch.isfinite(gx).all()


@pytest.mark.parametrize("cage_name", ["cube", "icosphere"])
def test_on_face_gradients_are_the_interpolants(cage_name):
    """On a face the coordinates are its barycentric coordinates: the rest vertices' gradient and
    the point's in-plane gradient are theirs (autograd of the closed form, area ratios)."""
    if cage_name == "cube":
        cage = _cube()
    else:
        ico = icosphere()
        g = torch.Generator().manual_seed(1)
        cage = tc.Cage(ico.vertices.to(D64) * 1.05 + 0.02 * torch.randn(42, 3, generator=g, dtype=D64), ico.triangles)
    y, f, _ = _face_points(cage, 8, 2)
    x = torch.cat([y, 0.3 * cage.vertices[:2]])  # two ordinary points alongside
    cot = torch.randn(x.shape[0], cage.num_vertices, generator=torch.Generator().manual_seed(3), dtype=D64)
    gx, gP = _grads(x, cage, cot)

    # reference: barycentric coordinates of the on-face points, ordinary points by the torch kernel
    V = cage.vertices.clone().requires_grad_()
    xr = x.clone().requires_grad_()
    p = V[cage.triangles[f]]  # (k, 3, 3)
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    a = p - xr[: len(f), None, :]
    area = torch.stack(
        [(torch.linalg.cross(a[:, (i + 1) % 3], a[:, (i + 2) % 3], dim=-1) * n).sum(-1) for i in range(3)]
    )
    bary = (area / (n * n).sum(-1)).T  # (k, 3)
    lam_face = torch.zeros(len(f), cage.num_vertices, dtype=D64).scatter(1, cage.triangles[f], bary)
    lam_rest = F.mean_value_coordinates(xr[len(f) :], tc.Cage(V, cage.triangles, validate=False), backend="torch")
    lam = torch.cat([lam_face, lam_rest])
    gx_ref, gP_ref = torch.autograd.grad((lam * cot).sum(), (xr, V))

    assert torch.allclose(gP, gP_ref, rtol=1e-10, atol=1e-10 * float(gP_ref.abs().max()))
    unit = (n / n.norm(dim=-1, keepdim=True)).detach()
    tangential = gx[: len(f)] - (gx[: len(f)] * unit).sum(-1, keepdim=True) * unit
    tangential_ref = gx_ref[: len(f)] - (gx_ref[: len(f)] * unit).sum(-1, keepdim=True) * unit
    assert torch.allclose(tangential, tangential_ref, rtol=1e-10, atol=1e-10 * float(tangential_ref.abs().max()))
    assert torch.allclose(gx[len(f) :], gx_ref[len(f) :], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize(
    "distance", [1e-12, pytest.param(1e-9, marks=pytest.mark.slow), pytest.param(1e-6, marks=pytest.mark.slow), 1e-4]
)
def test_near_face_gradients_against_mpmath(distance):
    """Within ``1e-12 .. 1e-4`` of the size from a face, on both sides: the gradients with respect
    to the point and the rest vertices against 60-digit central differences of the mpmath
    reference, the same points batched with ordinary ones and with points on the cage."""
    cage = _cube()
    y, f, _ = _face_points(cage, 2, 4)
    p = cage.vertices[cage.triangles[f]]
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True)
    near = torch.cat([y + distance * cage.scale * n, y - distance * cage.scale * n])  # outside, inside
    x = torch.cat([near, y, torch.tensor([[0.1, 0.2, -0.3]], dtype=D64)])
    c = torch.randn(cage.num_vertices, generator=torch.Generator().manual_seed(5), dtype=D64)
    gx, gP_all = _grads(x, cage, c.expand(x.shape[0], -1))
    rows = cage.vertices.tolist()
    cs = c.tolist()

    def f_ref(z, verts):
        return sum(a * b for a, b in zip(cs, mvc3d_reference(z, verts, cage.triangles), strict=True))

    flat = [v for r in rows for v in r]
    for i in range(near.shape[0]):
        xi = near[i].tolist()
        ref = torch.tensor(gradient_reference(lambda z, r=rows: f_ref(z, r), xi, cage.scale, STEP), dtype=D64)
        assert float((gx[i] - ref).norm() / ref.norm()) <= TARGET, (i, distance)
        (_, gP) = _grads(near[i : i + 1], cage, c[None])
        refv = gradient_reference(
            lambda z, xi=xi: f_ref(xi, [z[k * 3 : k * 3 + 3] for k in range(len(rows))]), flat, cage.scale, STEP
        )
        refv = torch.tensor(refv, dtype=D64).reshape(-1, 3)
        assert float((gP - refv).norm() / refv.norm()) <= TARGET, (i, distance)
    assert torch.isfinite(gP_all).all() and torch.isfinite(gx).all()


def test_fused_backward_on_the_cage_matches_the_autograd_path():
    """Per point on a face and at a vertex (each alone, so that the rest vertices' gradient is that
    point's): the fused backward (closed form on the cage) against autograd of the torch kernel
    (``ops._vertex_vjp``, the path every such point took before)."""
    ico = icosphere()
    g = torch.Generator().manual_seed(6)
    cage = tc.Cage(ico.vertices.to(D64) * 1.05 + 0.02 * torch.randn(42, 3, generator=g, dtype=D64), ico.triangles)
    y, _, _ = _face_points(cage, 4, 7)
    x = torch.cat([y, cage.vertices[:2]])
    cot = torch.randn(x.shape[0], cage.num_vertices, generator=g, dtype=D64)
    for i in range(x.shape[0]):
        gx, gP = _grads(x[i : i + 1], cage, cot[i : i + 1])
        c0 = cot[i : i + 1] - cot[i : i + 1].mean(dim=-1, keepdim=True)
        with torch.no_grad():  # (first order: no graph of the reference)
            ref = ops._vertex_vjp(x[i : i + 1], cage.vertices, cage.triangles, c0)
        scale = max(float(ref.abs().max()), 1.0)
        assert float((gP - ref).abs().max()) <= 1e-12 * scale, i
        # (the closed form of the near-cage kernel on faces: the same sums in another order)
        ref_x = ops._point_grad(x[i : i + 1], cage.vertices, cage.triangles, c0)
        assert float((gx - ref_x).abs().max()) <= 1e-14 * max(float(ref_x.abs().max()), 1.0), i


@pytest.mark.parametrize("cage_name", ["icosphere", "twisted bar"])
@pytest.mark.parametrize("native", [True, False])
def test_on_edge_gradients_are_one_faces_interpolant(monkeypatch, native, cage_name):
    """On an edge the coordinates have a kink. The point's gradient and the rest vertices' are both
    those of the barycentric interpolant of the larger face holding the point (autograd of its
    closed form, as the torch kernel's values), so that they agree: moving the point and the cage
    together changes nothing (``gx + sum_j gP_j = 0``; the point's gradient used to come from the
    first face and broke it). The twisted bar's quads are split into two halves of equal areas: of
    areas within ``kernel3d.AREA_TIE`` the first face is taken, by every kernel. With
    ``native=False`` the kernel's closed form is bypassed (``ops._on_face_vjp``)."""
    if native and not tc.backends.native.available():
        pytest.skip("needs the native kernels")
    if not native:
        _old_path(monkeypatch)
    cage = _jittered_icosphere(6) if cage_name == "icosphere" else twisted_bar(quads=False).to(D64)
    g = torch.Generator().manual_seed(7)
    f = torch.arange(cage.triangles.shape[0])  # (one edge of every face)
    p = cage.vertices[cage.triangles[f]]
    t = 0.05 + 0.9 * torch.rand(f.shape[0], 1, generator=g, dtype=D64)
    x = p[:, 0] * t + p[:, 1] * (1 - t)
    cot = torch.randn(x.shape[0], cage.num_vertices, generator=g, dtype=D64)
    if native:  # (the kernel's closed form takes every one of them)
        from torchcage._core.common import on_cage_tolerance
        from torchcage.families.mean_value.vjp3d_native import native_vjp_near

        lib = tc.backends.native.library()
        assert bool(native_vjp_near(lib, x, cage.vertices, cage.triangles, cot, on_cage_tolerance(cage))[2].all())
    gx, gP = _grads(x, cage, cot)  # (all at once: gP sums over the points)
    assert float((gx.sum(0) + gP.sum(0)).abs().max()) <= 1e-12 * float(gP.abs().max())

    V = cage.vertices.clone().requires_grad_()
    xr = x.clone().requires_grad_()
    lam = []
    for i in range(x.shape[0]):  # the larger face holding the edge (of two within AREA_TIE, the first)
        tri = cage.triangles
        area = _holds_edge(cage, int(f[i])) * cage.triangle_normals(unit=False).norm(dim=-1)
        k = int(torch.nonzero(area >= area.max() * (1 - kernel3d.AREA_TIE)).flatten().min())
        q = V[tri[k]]
        n = torch.linalg.cross(q[1] - q[0], q[2] - q[0], dim=-1)
        a = q - xr[i]
        bary = torch.stack([(torch.linalg.cross(a[(j + 1) % 3], a[(j + 2) % 3], dim=-1) * n).sum() for j in range(3)])
        lam.append(torch.zeros(cage.num_vertices, dtype=D64).index_put((tri[k],), bary / (n * n).sum()))
    gx_ref, gP_ref = torch.autograd.grad((torch.stack(lam) * cot).sum(), (xr, V))
    assert torch.allclose(gP, gP_ref, rtol=1e-10, atol=1e-10 * float(gP_ref.abs().max()))
    assert torch.allclose(gx, gx_ref, rtol=1e-10, atol=1e-10 * float(gx_ref.abs().max()))


def _jittered_icosphere(seed: int) -> tc.Cage:
    ico = icosphere()
    g = torch.Generator().manual_seed(seed)
    return tc.Cage(ico.vertices.to(D64) * 1.05 + 0.02 * torch.randn(42, 3, generator=g, dtype=D64), ico.triangles)


def _near_points(cage: tc.Cage, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Points ``1e-6 .. 1e-3`` of the size from faces, on both sides, ``(16, 3)``, and as far inside
    the cage from edges (both adjacent faces' planes near), ``(4, 3)``."""
    y, f, _ = _face_points(cage, 8, seed)
    p = cage.vertices[cage.triangles[f]]
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True)
    d = torch.tensor([1e-6, 1e-5, 1e-4, 1e-3] * 2, dtype=D64)[:, None] * cage.scale
    faces = torch.cat([y + d * n, y - d * n])
    t = torch.rand(4, 1, generator=torch.Generator().manual_seed(seed + 1), dtype=D64)
    e = p[:4, 0] * t + p[:4, 1] * (1 - t)
    inward = p[:4].mean(dim=1) - e
    edges = e - d[:4] * (n[:4] + inward / inward.norm(dim=-1, keepdim=True))
    return faces, edges


def _holds_edge(cage: tc.Cage, f: int) -> torch.Tensor:
    """``(T,)`` mask of the two faces holding the edge from corner 0 to corner 1 of face ``f``."""
    tri = cage.triangles
    return (tri == tri[f, 0]).any(1) & (tri == tri[f, 1]).any(1)


def _between_faces(cage: tc.Cage, seed: int, k: int = 3) -> torch.Tensor:
    """``(2k, 3)`` points ``1e-6`` and ``1e-4`` of the size inside the cage from edges, along the
    inward bisector of the two faces or off it toward either face: the foot point lies inside both
    faces (the nearer one takes the identity for its ``c / h`` term, the other its direct
    derivative; off the bisector, the first face in order or the second is the nearer)."""
    g = torch.Generator().manual_seed(seed)
    tri = cage.triangles
    f = torch.randint(0, tri.shape[0], (k,), generator=g)
    t = 0.2 + 0.6 * torch.rand(k, 1, generator=g, dtype=D64)
    out = []
    for d in (1e-6, 1e-4):
        for i in range(k):
            a, b = tri[f[i], 0], tri[f[i], 1]
            q = cage.vertices[tri[torch.nonzero(_holds_edge(cage, int(f[i]))).flatten()]]  # (2, 3, 3)
            n = torch.linalg.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0], dim=-1)
            n = n / n.norm(dim=-1, keepdim=True)
            e = cage.vertices[a] * t[i] + cage.vertices[b] * (1 - t[i])
            # (off the bisector on either side: the first face or the second is the nearer, f*)
            s = (0.5, 0.35, 0.65)[i % 3]
            bis = s * n[0] + (1 - s) * n[1]
            out.append(e - d * cage.scale * bis / bis.norm())
    return torch.stack(out)


def _old_path(monkeypatch) -> None:
    """Send every point that is not regular to the general path (autograd of the whole torch
    kernel for the rest vertices, the native analytic gradient for the point), as before the split."""

    def none(lib, x, P, faces, g, tol, in_kernel=True):
        return torch.zeros_like(x), torch.zeros_like(P), torch.zeros(x.shape[0], dtype=torch.bool)

    monkeypatch.setattr(ops, "_split_vjp", none)


@pytest.mark.skipif(not tc.backends.native.available(), reason="needs the native kernels")
def test_split_near_cage_backward_matches_the_whole_point_autograd(monkeypatch):
    """Points near faces (both sides), near edges, on faces, at a vertex and ordinary ones, with a
    random cotangent: the split backward (native products over the regular faces, autograd of the
    split form over the others; closed form on the cage) against the path every such point took
    before (autograd of the whole torch kernel), to rounding. The points near faces take the split."""
    from torchcage._core.common import on_cage_tolerance
    from torchcage.families.mean_value.vjp3d_native import native_vjp_near

    cage = _jittered_icosphere(8)
    near_faces, near_edges = _near_points(cage, 9)
    on_faces, _, _ = _face_points(cage, 3, 10)
    between = _between_faces(cage, 20)
    x = torch.cat([near_faces, near_edges, on_faces, cage.vertices[3:4], 0.4 * cage.vertices[:3], between])
    cot = torch.randn(x.shape[0], cage.num_vertices, generator=torch.Generator().manual_seed(11), dtype=D64)
    gx, gP = _grads(x, cage, cot)
    c0 = cot - cot.mean(dim=-1, keepdim=True)
    split = native_vjp_near(
        tc.backends.native.library(), x, cage.vertices, cage.triangles, c0, on_cage_tolerance(cage)
    )[2]
    # (the kernel takes the points near faces and edges, on faces, at the vertex and between faces)
    n_near = near_faces.shape[0] + near_edges.shape[0]
    assert bool(split[: n_near + on_faces.shape[0] + 1].all()) and bool(split[-between.shape[0] :].all())
    _old_path(monkeypatch)
    gx_ref, gP_ref = _grads(x, cage, cot)
    # (near an edge both paths lose about eps / distance: 1e-12 at 1e-6 of the size, the split one
    # nearer the 60-digit reference, test_split_near_edge_against_mpmath)
    assert float((gP - gP_ref).abs().max()) <= 1e-11 * float(gP_ref.abs().max())
    err = (gx - gx_ref).norm(dim=-1) / gx_ref.norm(dim=-1).clamp_min(1.0)
    assert float(err[: near_faces.shape[0]].max()) <= 1e-13, err
    # (between two faces, 1e-6 of the size from the edge, both paths are 1e-11 .. 2e-11 from the
    # 60-digit reference: eps / distance)
    assert float(err.max()) <= 1e-10, err


@pytest.mark.parametrize("distance", [1e-6, 1e-4, 1e-3])
def test_split_near_cage_gradcheck(distance):
    """``gradcheck`` (float64, central differences of the forward) of the points' and the rest
    vertices' gradients at points ``distance`` times the size from faces, on both sides, and from
    edges: the split backward where the native kernels serve, else the general path."""
    cage = _jittered_icosphere(12)
    y, f, _ = _face_points(cage, 2, 13)
    p = cage.vertices[cage.triangles[f]]
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True)
    e = 0.5 * (p[:1, 0] + p[:1, 1])
    inward = p[:1].mean(dim=1) - e
    step = distance * cage.scale
    # (and between two faces: along the inward bisector, the foot point inside both)
    q = cage.vertices[cage.triangles[torch.nonzero(_holds_edge(cage, f[0])).flatten()]]
    nq = torch.linalg.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0], dim=-1)
    bis = (nq / nq.norm(dim=-1, keepdim=True)).sum(0)
    x = torch.cat(
        [
            y + step * n,
            y - step * n,
            e - step * (n[:1] + inward / inward.norm(dim=-1, keepdim=True)),
            e - step * bis[None] / bis.norm(),
        ]
    )
    cot = torch.randn(x.shape[0], cage.num_vertices, generator=torch.Generator().manual_seed(14), dtype=D64)

    def loss(xx, V):
        return (F.mean_value_coordinates(xx, tc.Cage(V, cage.triangles, validate=False)) * cot).sum()

    inputs = (x.clone().requires_grad_(), cage.vertices.clone().requires_grad_())
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-3 * step, atol=1e-6, rtol=1e-5, fast_mode=True)


@pytest.mark.slow
def test_split_near_edge_against_mpmath():
    """Points ``1e-6`` of the size inside the cage from an edge (near both adjacent faces'
    planes, the foot point inside one of them, or inside both): the split backward's gradients with respect to the
    point and the rest vertices against 60-digit central differences of the mpmath reference."""
    cage = _jittered_icosphere(8)
    c = torch.randn(cage.num_vertices, generator=torch.Generator().manual_seed(15), dtype=D64)
    rows, cs = cage.vertices.tolist(), c.tolist()
    flat = [v for r in rows for v in r]

    def f_ref(z, verts):
        return sum(a * b for a, b in zip(cs, mvc3d_reference(z, verts, cage.triangles), strict=True))

    # (the foot point inside one face; inside both, along the bisector)
    for x in (_near_points(cage, 9)[1][:1], _between_faces(cage, 21, k=1)[:1]):
        gx, gP = _grads(x, cage, c[None])
        xi = x[0].tolist()
        ref = torch.tensor(gradient_reference(lambda z, xi=xi: f_ref(z, rows), xi, cage.scale, STEP), dtype=D64)
        assert float((gx[0] - ref).norm() / ref.norm()) <= TARGET
        refv = gradient_reference(
            lambda z, xi=xi: f_ref(xi, [z[k * 3 : k * 3 + 3] for k in range(len(rows))]), flat, cage.scale, STEP
        )
        refv = torch.tensor(refv, dtype=D64).reshape(-1, 3)
        assert float((gP - refv).norm() / refv.norm()) <= TARGET


@pytest.mark.skipif(not tc.backends.native.available(), reason="needs the native kernels")
def test_split_pairs_forward_mode_matches_autograd_of_the_split_form():
    """The kernel's forward-mode derivatives of the split form on the careful pairs (with the
    ``c / h`` term's ``dh`` coefficient from ``sum wbar w = 0``) against autograd of the torch
    split form over the same pairs (``in_kernel=False``), near faces and edges."""
    from torchcage._core.common import on_cage_tolerance

    cage = _jittered_icosphere(16)
    lib, tol = tc.backends.native.library(), on_cage_tolerance(cage)
    # (near an edge both lose about eps / distance, as in the test against the whole-point autograd)
    from torchcage.families.mean_value.vjp3d_native import native_vjp_near

    points = (*_near_points(cage, 17), _between_faces(cage, 19))
    for x, rtol in zip(points, (1e-13, 1e-11, 1e-10), strict=True):
        g = torch.randn(x.shape[0], cage.num_vertices, generator=torch.Generator().manual_seed(18), dtype=D64)
        g = g - g.mean(dim=-1, keepdim=True)
        gx, gP, split = ops._split_vjp(lib, x, cage.vertices, cage.triangles, g, tol)
        gx_ref, gP_ref, split_ref = ops._split_vjp(lib, x, cage.vertices, cage.triangles, g, tol, in_kernel=False)
        assert torch.equal(split, split_ref) and bool(split.all())
        if x is points[2]:  # (two faces around every foot point: one takes the identity, one not)
            pair = native_vjp_near(lib, x, cage.vertices, cage.triangles, g, tol, False)[3]
            assert bool(((pair == 2).sum(1) == 1).all()) and bool(((pair == 3).sum(1) == 1).all())
        assert float((gP - gP_ref).abs().max()) <= rtol * float(gP_ref.abs().max())
        assert float((gx - gx_ref).abs().max()) <= rtol * float(gx_ref.abs().max())
