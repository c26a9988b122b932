"""Finite and right everywhere: the robustness issue's reproducers and a fast slice of the sweep.

Each reproducer is an example of a class of inputs (points on the cage, on support planes and edge
lines, near edges of coplanar faces, slivers, collapsed poses, large coordinates); the slice at the
end runs ``benchmarks/robustness.py`` on a few thousand adversarial queries.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import pytest
import torch
from support import data_path

import torchcage as tc
from torchcage import functional as F
from torchcage.testing import adversarial_points, sliver_cube, twisted_bar

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

D64 = torch.float64


def _cube() -> tc.Cage:
    return tc.load_cage(tc.data.path("cube.obj")).triangulated().to(D64)


def _finite(*ts: torch.Tensor | None) -> bool:
    return all(t is None or bool(torch.isfinite(t).all()) for t in ts)


def _fd_grad(f, x: torch.Tensor, h: float = 1e-6) -> torch.Tensor:
    """Central differences of a scalar function of ``x`` ``(1, 3)``."""
    return torch.stack([(f(x + h * e) - f(x - h * e)) / (2 * h) for e in torch.eye(x.shape[1], dtype=x.dtype)])


# ------------------------------------------------------------------------------ gradients
def test_warp_image_gradient_on_integer_polygon() -> None:
    """Reproducer 1: a 2D cage on pixel coordinates (points on its vertices and edges)."""
    pytest.importorskip("kornia")
    from torchcage.image import warp_image

    P = torch.tensor([[4.0, 4], [19, 4], [19, 19], [4, 19]], dtype=D64)
    D = P[None].clone().requires_grad_()
    out = warp_image(torch.rand(1, 1, 24, 24, dtype=D64), tc.Cage(P, None), D, method="mvc")
    out.sum().backward()
    assert _finite(D.grad)


def test_mvc2d_vertex_gradient_on_the_polygon() -> None:
    """2D MVC w.r.t. the polygon at points on its vertices and edges: finite, and along an edge
    the derivative of the linear interpolant (the foot's parameter on the edge)."""
    P = torch.tensor([[0.0, 0], [2, 0], [2, 2], [0, 2]], dtype=D64)
    x = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.5]], dtype=D64)
    V = P.clone().requires_grad_()
    lam = F.mean_value_coordinates(x, tc.Cage(V, None))
    (gV,) = torch.autograd.grad(lam[1, 1], V)
    assert _finite(gV)

    # lam_1 at x on edge (p0, p1) is t = (x - p0).(p1 - p0) / |p1 - p0|^2: d/dp1 = -(t / L) e - ..., check by FD
    def f(v1x: float) -> torch.Tensor:
        Q = P.clone()
        Q[1, 0] = v1x
        return F.mean_value_coordinates(x[1:2], tc.Cage(Q, None))[0, 1]

    fd = (f(2.0 + 1e-6) - f(2.0 - 1e-6)) / 2e-6
    assert abs(float(gV[1, 0]) - float(fd)) < 1e-8


def test_mvc3d_rest_vertex_gradient_at_a_cage_vertex() -> None:
    """Reproducer 2: MVC w.r.t. the rest cage at a point on a cage vertex."""
    cube = _cube()
    V = cube.vertices.clone().requires_grad_()
    lam = F.mean_value_coordinates(cube.vertices[:1], tc.Cage(V, cube.triangles))
    (g,) = torch.autograd.grad((lam * torch.arange(8.0, dtype=D64)).sum(), V)
    assert _finite(g)


@pytest.mark.parametrize(
    "x0",
    [(1.0, -4.0, -1.0), (3.0, 0.2, -1.0), (0.3, -1.001, 0.2), (0.2, 0.1, 0.3)],
    ids=["edge_line", "support_plane", "near_face", "inside"],
)
def test_green_point_gradient_agrees_with_finite_differences(x0) -> None:
    """Reproducer 3: GC w.r.t. the point on an edge's support line and a face's support plane
    outside the cage (derivatives kept there, not zeroed), near a face and inside."""
    cube = _cube()
    c1 = torch.arange(8.0, dtype=D64) + 1
    c2 = torch.arange(12.0, dtype=D64) * 0.1

    def f(y: torch.Tensor) -> torch.Tensor:
        phi, psi = F.green_coordinates(y, cube, backend="torch")
        return (phi @ c1 + psi @ c2).sum()

    x = torch.tensor([x0], dtype=D64, requires_grad=True)
    (g,) = torch.autograd.grad(f(x), x)
    fd = _fd_grad(f, x.detach())
    assert torch.allclose(g[0], fd, rtol=1e-6, atol=1e-8)


def test_green_point_gradient_at_a_cage_corner_is_finite() -> None:
    cube = _cube()
    x = cube.vertices[:1].clone().requires_grad_()
    phi, psi = F.green_coordinates(x, cube)
    (g,) = torch.autograd.grad((phi * torch.arange(8.0, dtype=D64)).sum() + psi.sum(), x)
    assert _finite(g)


def test_green_module_on_a_sliver_cage() -> None:
    """Reproducer 4: a sliver triangle (height 1e-9): finite backward, rest pose reproduced."""
    cage = sliver_cube()
    pts = torch.rand(40, 3, dtype=D64, generator=torch.Generator().manual_seed(0)) * 1.8 - 0.9
    m = tc.GreenCoordinates(cage, pts)
    V = cage.vertices.clone().requires_grad_()
    m(V).sum().backward()
    assert _finite(V.grad)
    assert torch.allclose(m(cage.vertices), pts, atol=1e-10)


def test_conformal_stretch_is_exact_on_slivers_and_zero_when_collapsed() -> None:
    from torchcage.families.green.stretch import conformal_stretch

    u0 = torch.tensor([1.0, 0.0, 0.0], dtype=D64)
    v0 = torch.tensor([0.5, 1e-9, 0.0], dtype=D64)
    assert abs(float(conformal_stretch(u0, v0, u0, v0)) - 1.0) < 1e-6  # the published form gave 0 or NaN
    R = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=D64)
    assert abs(float(conformal_stretch(u0, v0, 3 * R @ u0, 3 * R @ v0)) - 3.0) < 1e-6
    z = torch.zeros(3, dtype=D64, requires_grad=True)
    s = conformal_stretch(u0, v0, z, z)
    (g,) = torch.autograd.grad(s, z)
    assert float(s) == 0.0 and _finite(g)


@pytest.mark.parametrize("kind", ["gc", "qgc"])
def test_green_modules_at_a_collapsed_pose(kind: str) -> None:
    """Reproducer 5: all deformed vertices equal: finite gradients (zero stretch derivative)."""
    cq = tc.load_cage(tc.data.path("cube.obj")).to(D64)
    pts = torch.rand(20, 3, dtype=D64, generator=torch.Generator().manual_seed(1)) * 1.6 - 0.8
    m = tc.GreenCoordinates(cq.triangulated(), pts) if kind == "gc" else tc.QuadGreenCoordinates(cq, pts)
    V = torch.zeros(8, 3, dtype=D64, requires_grad=True)
    out = m(V)
    out.sum().backward()
    assert _finite(out, V.grad)


def test_qgc_rest_vertex_gradient_matches_finite_differences() -> None:
    """Reproducer 6 (QGC w.r.t. the cage): the SVD basis of A's null space had NaN gradients; the
    pseudo-inverse and the null-space projector are differentiated instead. gradcheck in float64."""
    bar = twisted_bar(levels=4)
    x = torch.tensor([[0.2571, 0.1355, 1.4445]], dtype=D64)

    def f(V: torch.Tensor):
        return F.quad_green_coordinates(x, tc.Cage(V, bar.faces))

    assert torch.autograd.gradcheck(
        f, (bar.vertices.clone().requires_grad_(),), eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True
    )


def test_qgc_rest_vertex_gradient_on_the_cage_is_finite() -> None:
    cq = tc.load_cage(tc.data.path("cube.obj")).to(D64)
    pts = adversarial_points(cq, 4, seed=3)
    x = torch.cat([pts[k] for k in ("vertex", "edge", "face", "near_edge")])
    V = cq.vertices.clone().requires_grad_()
    phi, psi = F.quad_green_coordinates(x, tc.Cage(V, cq.faces))
    (g,) = torch.autograd.grad(phi.sum() + psi.sum(), V)
    assert _finite(g)


def test_qmvc_gradients_on_the_cage() -> None:
    """Reproducer 7: QMVC at a cage corner (w.r.t. the point); on a quad the derivative is the
    tangential derivative of the bilinear interpolant (finite differences along the face)."""
    cq = tc.load_cage(tc.data.path("cube.obj")).to(D64)
    c = torch.arange(8.0, dtype=D64) + 1
    x = cq.vertices[:1].clone().requires_grad_()
    (g,) = torch.autograd.grad(F.quad_mean_value_coordinates(x, cq) @ c, x)
    assert _finite(g)
    x0 = torch.tensor([[0.2, 0.3, 1.0]], dtype=D64)
    x = x0.clone().requires_grad_()
    V = cq.vertices.clone().requires_grad_()
    gx, gV = torch.autograd.grad((F.quad_mean_value_coordinates(x, tc.Cage(V, cq.faces)) @ c).sum(), (x, V))
    assert _finite(gx, gV)

    def f(y: torch.Tensor) -> torch.Tensor:
        return (F.quad_mean_value_coordinates(y, cq) @ c).sum()

    fd = _fd_grad(f, x0)
    assert torch.allclose(gx[0, :2], fd[:2], atol=1e-8)


@pytest.mark.parametrize("model", ["Beast", "Ogre"])
def test_qmvc_rest_vertex_gradient_at_vertices_of_a_triquad_cage(model: str) -> None:
    """A point on a quad-only vertex of a triquad cage: the triangles' kernel took sqrt(0)."""
    cage = tc.load_cage(data_path("qmvc", f"{model}_Cage.obj")).to(D64)
    V = cage.vertices.clone().requires_grad_()
    w = F.quad_mean_value_coordinates(cage.vertices[:40], tc.Cage(V, cage.faces))
    (g,) = torch.autograd.grad((w * torch.arange(w.shape[1], dtype=D64)).sum(), V)
    assert _finite(g)


# ------------------------------------------------------------------------------ values
def test_qgc_torch_at_cage_vertices() -> None:
    """Reproducer 11."""
    cage = tc.load_cage(data_path("qmvc", "FireHydrant_Cage.obj")).to(D64)
    phi, psi = F.quad_green_coordinates(cage.vertices[:20], cage, backend="torch")
    assert _finite(phi, psi)


def test_green_native_on_an_edge_at_large_coordinates(backend: str) -> None:
    """Reproducer 12: the edge integral's log argument overflowed to inf (then 0 * inf)."""
    bench = tc.load_cage(data_path("qmvc", "Bench_Cage.obj")).triangulated().to(D64)
    big = tc.Cage(bench.vertices * 1e6, bench.triangles)
    e = bench.triangles[0]
    x = (0.5 * (big.vertices[e[0]] + big.vertices[e[1]]))[None]
    phi, psi = F.green_coordinates(x, big, backend=backend)
    assert _finite(phi, psi)
    assert abs(float(phi.sum()) - 1) < 1e-12


@pytest.mark.parametrize("offset", [1e-14, 1e-13, 3e-15])
def test_green_near_the_edge_of_coplanar_faces(backend: str, offset: float) -> None:
    """Reproducer 13: two coplanar faces split the solid angle near their shared edge without a
    gap (each edge's perpendicular is computed once for both faces)."""
    cage = tc.load_cage(data_path("qmvc", "SpikyBox_Cage.obj")).triangulated().to(D64)
    pts = adversarial_points(cage, 400, seed=0)
    from torchcage.geometry import inside_cage

    x = pts["near_edge"]
    x = x[inside_cage(x, cage)]
    phi, psi = F.green_coordinates(x, cage, backend=backend)
    assert float((phi.sum(1) - 1).abs().max()) < 1e-12
    # and the cube's face diagonals (coplanar triangles), just inside
    cube = _cube()
    y = torch.tensor([[0.3, 0.3, 1 - offset], [-0.5, 0.5, 1 - offset]], dtype=D64)
    phi, psi = F.green_coordinates(y, cube, backend=backend)
    assert float((phi.sum(1) - 1).abs().max()) < 1e-12
    assert torch.allclose(phi @ cube.vertices + psi @ cube.triangle_normals(), y, atol=1e-12)


def test_green_near_a_vertex(backend: str) -> None:
    """Points 1e-15..1e-3 of the size from vertices of a twisted bar: the perpendicular to each edge
    from its nearer end keeps the sides right (the midpoint form lost 1e-4 of partition of unity)."""
    from torchcage.geometry import inside_cage

    bar = twisted_bar(quads=False)
    x = adversarial_points(bar, 300, seed=0)["near_vertex"]
    x = x[inside_cage(x, bar)]
    phi, _ = F.green_coordinates(x, bar, backend=backend)
    assert float((phi.sum(1) - 1).abs().max()) < 1e-12


def test_qgc_on_the_edges_of_twisted_quads(backend: str) -> None:
    """Points on a quad edge: the fan triangle over that edge is empty (it was a sliver seen from its
    own edge, with a garbage solid angle: linear precision 45 native, 1.3 torch)."""
    bar = twisted_bar()
    x = adversarial_points(bar, 60, seed=0)["edge"]
    phi, psi = F.quad_green_coordinates(x, bar, backend=backend)
    N = bar.quad_corner_normals().reshape(-1, 3)
    assert float((phi @ bar.vertices + psi @ N - x).abs().max()) < 1e-12


def test_qgc_within_a_few_tolerances_of_twisted_quad_edges(backend: str) -> None:
    """A point 0.9 tolerances from the edge shared by two twisted quads measured 1.25 tolerances
    from its projection (not the nearest point of a curved sheet): neither quad took it as on the
    cage, and the fan from its projection on the edge ran along the tetrahedron's faces on both
    sides of the sheet (PU off by 0.44, LP 0.7). Such points are now on the quad (a band of 4
    tolerances): partition of unity is exact; linear precision keeps about 4e-5 (open: the
    neighbouring quad's fan has a sliver over the shared edge, seen from 2.5 tolerances)."""
    from torchcage._core.common import on_cage_tolerance

    bar = twisted_bar()
    tol = on_cage_tolerance(bar)
    x = adversarial_points(bar, 200, seed=3)["edge"]
    g = torch.Generator().manual_seed(0)
    d = torch.randn(x.shape, generator=g, dtype=D64)
    x = x + d / d.norm(dim=1, keepdim=True) * (2.5 * tol)
    phi, psi = F.quad_green_coordinates(x, bar, backend=backend)
    inside = tc.geometry.inside_cage(x, bar)
    N = bar.quad_corner_normals().reshape(-1, 3)
    assert float((phi[inside].sum(1) - 1).abs().max()) < 1e-12
    assert float((phi[inside] @ bar.vertices + psi[inside] @ N - x[inside]).abs().max()) < 1e-3


def test_green_a_few_tolerances_from_a_vertex(backend: str) -> None:
    """Sweep finding at 1e6 queries (once Green coordinates were checked outside the cage too): a
    point 4 tolerances outside the sliver cube's corner was reproduced to 7.5e-6, both kernels (the
    corner's faces seen from there are known to a few per mille). Points that close to a vertex are
    now taken at the vertex (its limit from inside); their derivative w.r.t. the point is 0."""
    cage = sliver_cube()
    x = torch.tensor([[1.0 + 5.35e-14, -1.0 + 7.5e-15, -1.0 - 7.8e-15]], dtype=D64)
    for kind in ("gc", "qgc"):
        c = cage if kind == "gc" else tc.load_cage(tc.data.path("cube.obj")).to(D64)
        phi, psi = (F.green_coordinates if kind == "gc" else F.quad_green_coordinates)(x, c, backend=backend)
        N = c.triangle_normals() if kind == "gc" else c.quad_corner_normals().reshape(-1, 3)
        assert float((phi @ c.vertices + psi @ N - x).abs().max()) < 1e-12, kind
    xg = x.clone().requires_grad_()
    phi, psi = F.green_coordinates(xg, cage)
    (g,) = torch.autograd.grad(phi.sum() + psi.sum(), xg)
    assert torch.equal(g, torch.zeros_like(g))


def test_qmvc_just_off_planar_quads(backend: str) -> None:
    """Reproducer 10's class: points within a few tolerances of a planar quad (above it, and near
    its edges outside) got no weight from it (linear precision 0.04 on Bench, 0.15 on the cube)."""
    cube = tc.load_cage(tc.data.path("cube.obj")).to(D64)
    e = torch.tensor([-1.0, -0.785, 1.0], dtype=D64)
    vals = [4e-15, 9e-15, 1.2e-14, 2e-14, 1e-13]
    x = torch.stack([e + torch.tensor([-a, 0.0, b], dtype=D64) for a in vals for b in vals])
    w = F.quad_mean_value_coordinates(x, cube, backend=backend)
    assert float((w @ cube.vertices - x).abs().max()) < 1e-12
    bench = tc.load_cage(data_path("qmvc", "Bench_Cage.obj")).to(D64)
    y = adversarial_points(bench, 200, seed=0)["near_face"]
    w = F.quad_mean_value_coordinates(y, bench, backend=backend)
    assert float((w @ bench.vertices - y).abs().max()) / bench.scale < 1e-10


def test_qmvc_on_the_plane_of_a_nearly_planar_quad(backend: str) -> None:
    """A point on a nearly planar quad's plane far from it came out "inside" its tetrahedron (the
    signs of kappa at their rounding level) and got O(1) weights (linear precision 1.5)."""
    cactus = tc.load_cage(data_path("qmvc", "Cactus_Cage.obj")).to(D64)
    y = adversarial_points(cactus, 60, seed=0)["plane"]
    w = F.quad_mean_value_coordinates(y, cactus, backend=backend)
    assert float((w @ cactus.vertices - y).abs().max()) / cactus.scale < 1e-10


def test_on_cage_tolerance_follows_the_coordinates() -> None:
    """A cage translated by 1e6: points on its faces carry rounding errors of eps * 1e6."""
    cube = _cube()
    far = tc.Cage(cube.vertices + 1e6, cube.triangles)
    x = adversarial_points(far, 50, seed=0)["face"]
    phi, psi = F.green_coordinates(x, far)
    assert float((phi @ far.vertices + psi @ far.triangle_normals() - x).abs().max()) < 1e-8


# ------------------------------------------------------------------------------ the sweep's slice
@pytest.mark.parametrize("family", ["mvc3d", "mvc2d", "mvc_derivatives", "qmvc", "gc", "qgc", "lbc", "image"])
def test_robustness_slice(family: str) -> None:
    """A few thousand adversarial queries per family: no non-finite value or gradient, and the
    float64 bounds met by every family outside the far field (see docs/accuracy.md)."""
    import robustness

    robustness.LBC_CELLS = 400  # (a coarse mesh keeps the three LBC solves to seconds)
    robustness.DEFORMED_CATEGORIES = ("vertex", "near_edge")  # (modules on two categories only)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        results = robustness.run([family], None, per_category=40, grad_k=6, dtype=None)
    st, _ = results[family]
    assert st.queries > 0
    assert st.bad_values == 0 and st.bad_grads == 0, st.errors[:5]
    assert not st.errors, st.errors[:5]
    if family != "image":
        assert st.pu[0] < 1e-9, st.pu
        assert st.lp[0] < 1e-8, st.lp
        # relative to the distance, out to 1e9 cage sizes
        assert st.far[0] < 1e-8, st.far


@pytest.mark.parametrize("category", ["near_edge", "near_vertex"])
def test_qgc_bounds_near_twisted_edges_and_corners(backend: str, category: str) -> None:
    """The float64 bounds 1e-15..1e-3 of the size from the edges and corners of the twisted bar's
    quads (they were PU 8.7e-5 and LP 2.2e-4 near edges, 3e-6 near corners): the fan's apex moves
    along the projection's ruling away from a nearby edge (no sliver), and a needle's normal comes
    from its two shorter edges."""
    import robustness

    bar = twisted_bar()
    x = adversarial_points(bar, 300, seed=0)[category]
    inside, sure = robustness._inside(x, bar)
    x = x[inside & sure]
    phi, psi = F.quad_green_coordinates(x, bar, backend=backend)
    N = bar.quad_corner_normals().reshape(-1, 3)
    assert float((phi.sum(1) - 1).abs().max()) < 1e-12
    assert float((phi @ bar.vertices + psi @ N - x).norm(dim=1).max()) < 1e-10 * bar.scale


def test_qgc_near_an_edge_between_a_triangle_and_a_quad(backend: str) -> None:
    """Ogre's triquad cage 1e-15..1e-3 of the size from its edges: next to an edge shared by a
    triangle face and a quad, the two see the point with the same bits (PU was 9e-11 at 3e-9 of
    the size, the quad's fan built from corners minus the point, the face from the corners)."""
    import robustness

    cage = tc.load_cage(data_path("qmvc", "Ogre_Cage.obj")).to(D64)
    x = adversarial_points(cage, 300, seed=0)["near_edge"]
    inside, sure = robustness._inside(x, cage)
    x = x[inside & sure]
    phi, psi = F.quad_green_coordinates(x, cage, backend=backend)
    T = cage.triangles
    n = torch.nn.functional.normalize(
        torch.linalg.cross(*(cage.vertices[T][:, i] - cage.vertices[T][:, 0] for i in (1, 2)), dim=-1), dim=-1
    )
    N = torch.cat([n, cage.quad_corner_normals().reshape(-1, 3)])
    assert float((phi.sum(1) - 1).abs().max()) < 1e-12
    assert float((phi @ cage.vertices + psi @ N - x).norm(dim=1).max()) < 1e-10 * cage.scale


@pytest.mark.parametrize("model", ["FireHydrant", "Bench", pytest.param("Beast", marks=pytest.mark.slow)])
def test_qgc_near_edges_of_data_cages(backend: str, model: str) -> None:
    """1,000 near-edge points per category: points a few tolerances from an edge of a planar quad,
    in its plane but off it, got no solid angle from the native fan (PU off by 3e-2 on FireHydrant
    and Bench); 4e-14 from an edge between a triangle and a quad (Beast), the native fan's edge
    direction differed by an ulp from the triangle face's (7e-6)."""
    import robustness

    cage = tc.load_cage(data_path("qmvc", f"{model}_Cage.obj")).to(D64)
    pts, side = adversarial_points(cage, 1000, seed=0, sides=True)
    x, known = pts["near_edge"], side["near_edge"]
    inside, sure = robustness._inside(x, cage)
    agree = (known == 0) | ~sure | (inside == (known < 0))
    x = x[torch.where(torch.isnan(known), sure & inside, (known <= 0) & agree)]
    phi, _ = F.quad_green_coordinates(x, cage, backend=backend)
    assert float((phi.sum(1) - 1).abs().max()) < 1e-12


def test_green_on_a_cage_far_from_the_origin_sums_to_one(backend: str) -> None:
    """On the cube translated by 1e6, a partition-of-unity defect of 8e-15 cost 4e-9 of the size in
    ``phi @ V`` near an edge: the coordinates are divided by their sum where that helps."""
    cube = tc.load_cage(tc.data.path("cube.obj")).to(D64).triangulated()
    shifted = tc.Cage(cube.vertices + 1e6, cube.triangles)
    x = adversarial_points(shifted, 200, seed=1)["near_edge"]
    phi, psi = F.green_coordinates(x, shifted, backend=backend)
    rec = phi @ shifted.vertices + psi @ shifted.triangle_normals()
    assert float((phi.sum(1) - 1).abs().max()) < 4 * torch.finfo(D64).eps
    assert float((rec - x).norm(dim=1).max()) < 1e-9 * shifted.scale


@pytest.mark.parametrize("kind", ["gc", "gc_none", "qgc"])
def test_green_modules_warn_about_points_outside(kind: str) -> None:
    """Reproducer 14: points outside what the coordinates cover warn with their count (GC: beyond
    the exterior band; bare GC and QGC: every outside point)."""
    cq = tc.load_cage(tc.data.path("cube.obj")).to(D64)
    pts = torch.tensor([[0.1, 0.2, 0.3], [3.0, 0.0, 0.0], [0.0, -2.5, 0.1], [0.0, 1.2, 0.0]], dtype=D64)
    if kind == "gc":
        with pytest.warns(tc.OutsideCageWarning, match="2 of 4 points lie farther than 0.25 .* [(]3 outside"):
            m = tc.GreenCoordinates(cq.triangulated(), pts)
        assert torch.allclose(m(cq.vertices), pts, atol=1e-12)  # the rest pose reproduces all of them
    elif kind == "gc_none":
        with pytest.warns(tc.OutsideCageWarning, match="3 of 4 points lie outside"):
            tc.GreenCoordinates(cq.triangulated(), pts, exterior="none")
    else:
        with pytest.warns(tc.OutsideCageWarning, match="3 of 4 points lie outside"):
            tc.QuadGreenCoordinates(cq, pts)


@pytest.mark.parametrize("scale", [1e6, 1e9])
def test_mvc_far_field_relative_linear_precision(backend: str, scale: float) -> None:
    """Reproducer 9: far points are normalised by the weights' first moment (the sum cancels to
    size / distance of its terms), and faces seen tiny always take the far-field rule."""
    for cage in (_cube(), sliver_cube()):
        g = torch.Generator().manual_seed(0)
        d = torch.randn(50, 3, dtype=D64, generator=g)
        x = d / d.norm(dim=1, keepdim=True) * scale * cage.scale
        w = F.mean_value_coordinates(x, cage, backend=backend)
        rel = (w @ cage.vertices - x).norm(dim=1) / x.norm(dim=1)
        assert float(rel.max()) < 1e-12


@pytest.mark.parametrize("family", ["mvc", "qmvc", "derivatives"])
def test_far_field_on_a_cage_far_from_the_origin(backend: str, family: str) -> None:
    """The cube translated by 1e6, 1e2..1e9 sizes away: the moment normalisation leaves the sum
    off 1 by 3e-11 at 500 sizes, which ``w @ V`` multiplied by 1e6 (2.5e-8 relative); the defect
    is spread over the vertices (the centred LP kept). Relative LP <= 1e-9, and the derivatives'
    sum over the vertices vanishes (the gradient of the partition of unity)."""
    cube = tc.load_cage(tc.data.path("cube.obj")).to(D64)
    cube = tc.Cage(cube.vertices + torch.tensor([1e6, -2e6, 5e5], dtype=D64), cube.quads)
    cage = cube if family == "qmvc" else cube.triangulated()
    g = torch.Generator().manual_seed(3)
    d = torch.randn(30, 3, dtype=D64, generator=g)
    c = cage.vertices.mean(0)
    x = torch.cat([c + d / d.norm(dim=1, keepdim=True) * s * cage.scale for s in (1e2, 5e2, 3e3, 1e5, 1e9)])
    if family == "mvc":
        w = F.mean_value_coordinates(x, cage, backend=backend)
    elif family == "qmvc":
        w = F.quad_mean_value_coordinates(x, cage, backend=backend)
    else:
        w, grad, hess = F.mean_value_derivatives(x, cage, order=2, backend=backend)
        scale = (x - c).norm(dim=1)[:, None]
        assert float((grad.sum(1).norm(dim=1, keepdim=True) * scale).max()) < 1e-6
        assert float((hess.sum(1).flatten(1).norm(dim=1, keepdim=True) * scale**2).max()) < 1e-6
    rel = (w @ cage.vertices - x).norm(dim=1) / (x - c).norm(dim=1)
    assert float(rel.max()) < 1e-9, float(rel.max())


@pytest.mark.parametrize("model", ["cube", "Beast"])
def test_qmvc_far_field_relative_linear_precision(backend: str, model: str) -> None:
    """Quads seen small take the Gauss rule of their defining integrals
    (the mean vector of Cramer's form cancels there), and a triquad cage's triangles take the
    far-field rule (their own sum does not show the cancellation). Relative LP <= 1e-8 from 1e2 to
    1e9 cage sizes (it was 2e4 at 1e9)."""
    quads = tc.load_cage(tc.data.path("cube.obj")).to(D64)
    cage = quads if model == "cube" else tc.load_cage(data_path("qmvc", "Beast_Cage.obj"))
    g = torch.Generator().manual_seed(0)
    d = torch.randn(20, 3, dtype=D64, generator=g)
    d = d / d.norm(dim=1, keepdim=True)
    c = cage.vertices.mean(0)
    for scale in (1e2, 3e2, 1e3, 1e6, 1e9):
        x = c + d * scale * cage.scale
        w = F.quad_mean_value_coordinates(x, cage, backend=backend)
        rel = (w @ cage.vertices - x).norm(dim=1) / (x - c).norm(dim=1)
        assert float(rel.max()) < 1e-8, (scale, float(rel.max()))


def test_qmvc_on_a_triangle_cage_equals_mvc(backend: str) -> None:
    """Sweep finding at 1e6 queries: QMVC on a cage without quads took every triangle as part of a
    triquad cage (the far-field rule for every point), LP 1.3e-8 on the sliver cube's face planes
    where MVC has 7e-12. Without quads QMVC is MVC."""
    cage = sliver_cube()
    x = adversarial_points(cage, 500, seed=0)["plane"]
    a = F.quad_mean_value_coordinates(x, cage, backend=backend)
    b = F.mean_value_coordinates(x, cage, backend=backend)
    assert torch.allclose(a, b, rtol=0, atol=1e-12)


def test_qmvc_far_blend_is_continuous(backend: str) -> None:
    """Between 10^1.5 and 10^2.5 quad sizes the Riemann estimate blends into the Gauss rule: along
    a ray through the blend the coordinates are smooth. (A switch at one ratio is a jump of about
    1e-6 of the weights: the largest second difference was then 900 times the median; here it is
    below 10 times.)"""
    cube = tc.load_cage(tc.data.path("cube.obj")).to(D64)  # six quads
    size = float((cube.vertices[0] - cube.vertices[6]).norm())  # the quads' diagonal (2 sqrt 2)
    direction = torch.tensor([0.3, 0.5, 0.81], dtype=D64)
    t = torch.logspace(1.4, 2.6, 10000, dtype=D64)  # distances in quad sizes
    w = F.quad_mean_value_coordinates(direction / direction.norm() * t[:, None] * size, cube, backend=backend)
    w = w / t[:, None]  # (far outside, the coordinates grow like the distance)
    d2 = (w[2:] - 2 * w[1:-1] + w[:-2]).abs().max(dim=1).values
    assert float(d2.max()) < 50 * float(d2.median()), (float(d2.max()), float(d2.median()))


@pytest.mark.parametrize("dim", [2, 3])
def test_mvc_derivatives_far_field(backend: str, dim: int) -> None:
    """The native kernels normalise by the weights' first moment as
    a jet (value, gradient, Hessian), and the 2D edge cross product takes the edge from its
    vertices. Relative LP of the coordinates, ``sum_i grad lam_i v_i^T = I`` and
    ``sum_i H lam_i v_i = 0`` hold to 1e-10 out to 1e9 cage sizes (the 3D kernel had 1.4e-6, the
    2D one 1.0 at 1e9)."""
    cage = sliver_cube() if dim == 3 else tc.load_cage(tc.data.path("blob2d.obj")).to(D64)
    g = torch.Generator().manual_seed(0)
    d = torch.randn(20, dim, dtype=D64, generator=g)
    d = d / d.norm(dim=1, keepdim=True)
    c = cage.vertices.mean(0)
    for scale in (1e2, 1e4, 1e6, 1e9):
        x = c + d * scale * cage.scale
        lam, grad, hess = F.mean_value_derivatives(x, cage, backend=backend)
        r = (x - c).norm(dim=1)
        assert float(((lam @ cage.vertices - x).norm(dim=1) / r).max()) < 1e-10, scale
        eye = torch.eye(dim, dtype=D64)
        assert float((torch.einsum("nvc,vd->ncd", grad, cage.vertices) - eye).abs().max()) < 1e-10, scale
        hlp = torch.einsum("nvcd,ve->necd", hess, cage.vertices).abs().flatten(1).max(dim=1).values
        assert float((hlp * r).max()) < 1e-10, scale


def test_mvc2d_far_field(backend: str) -> None:
    P = tc.load_cage(tc.data.path("blob2d.obj")).to(D64)
    g = torch.Generator().manual_seed(0)
    d = torch.randn(50, 2, dtype=D64, generator=g)
    x = d / d.norm(dim=1, keepdim=True) * 1e9 * P.scale
    w = F.mean_value_coordinates(x, P, backend=backend)
    assert float(((w @ P.vertices - x).norm(dim=1) / x.norm(dim=1)).max()) < 1e-12


def test_float32_dtype_is_accurate_and_does_not_raise_far_away() -> None:
    """Reproducer 8: ``dtype=torch.float32`` (computed in float64, returned in float32): linear
    precision within 1e-4 of the size on the cage and near it, far points do not raise."""
    bar = twisted_bar(quads=False)
    pts = adversarial_points(bar, 100, seed=0)
    x = torch.cat([pts[k] for k in ("edge", "near_edge", "near_vertex", "plane", "face")])
    for backend in ("torch", "auto"):
        w = F.mean_value_coordinates(x.float(), bar.to(torch.float32), dtype=torch.float32, backend=backend)
        assert w.dtype == torch.float32
        assert float((w.double() @ bar.vertices - x).abs().max()) / bar.scale < 1e-4
    far = pts["far"].float()
    w = F.mean_value_coordinates(far, bar.to(torch.float32), dtype=torch.float32, backend="torch")
    assert _finite(w)
