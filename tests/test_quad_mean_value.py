"""Quad mean value coordinates: exact properties, interpolation on bilinear quads, agreement with a
dense-tessellation reference, symmetry, scale invariance, backends and gradients."""

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
    sheet_normal,
    triquad,
)

import torchcage
from torchcage import functional as F
from torchcage.testing import assert_linear_precision, assert_partition_of_unity


def dense_reference(cage: torchcage.Cage, x: torch.Tensor, m: int) -> torch.Tensor:
    """Independent QMVC reference: every quad tessellated into ``m x m`` bilinear sub-quads (two
    triangles each), triangle MVC on that fine cage, and the fine vertices' coordinates mapped back
    to the cage vertices through the bilinear basis. Converges to QMVC's exact integrals."""
    v, q = cage.vertices.to(torch.float64), cage.quads
    V = v.shape[0]
    t = torch.linspace(0, 1, m + 1, dtype=torch.float64)
    U, W = (a.reshape(-1) for a in torch.meshgrid(t, t, indexing="ij"))
    basis = torch.stack([(1 - U) * (1 - W), U * (1 - W), U * W, (1 - U) * W], 1)  # (G, 4)
    pos = torch.einsum("gk,qkc->qgc", basis, v[q]).reshape(-1, 3)
    B = torch.zeros(q.shape[0], basis.shape[0], V, dtype=torch.float64)
    for k in range(4):
        idx = q[:, k].view(-1, 1, 1).expand(-1, basis.shape[0], 1)
        B.scatter_add_(2, idx, basis[None, :, k : k + 1].expand(q.shape[0], -1, 1))
    allpos, allB = torch.cat([v, pos]), torch.cat([torch.eye(V, dtype=torch.float64), B.reshape(-1, V)])
    key = torch.round(allpos * 1e9).long()
    _, inv = torch.unique(key, dim=0, return_inverse=True)
    nv = int(inv.max()) + 1
    fpos = torch.zeros(nv, 3, dtype=torch.float64).index_copy(0, inv, allpos)
    fB = torch.zeros(nv, V, dtype=torch.float64).index_copy(0, inv, allB)
    gid = inv[V:].reshape(q.shape[0], m + 1, m + 1)
    a, b, c, d = gid[:, :-1, :-1], gid[:, 1:, :-1], gid[:, 1:, 1:], gid[:, :-1, 1:]
    tris = [torch.stack([a, b, c], -1).reshape(-1, 3), torch.stack([a, c, d], -1).reshape(-1, 3)]
    if cage.triangles.shape[0]:
        tris.append(inv[cage.triangles])
    fine = torchcage.Cage(fpos, torch.cat(tris))
    return F.mean_value_coordinates(x, fine) @ fB


# ----------------------------------------------------------------------------- exact properties
@pytest.mark.parametrize("make", [bent_box, triquad, lambda: box_cage(1, 2, 1)], ids=["bent", "triquad", "box"])
def test_partition_linear_precision_adversarial(make, backend):
    cage = make()
    x = torch.cat([box_points(cage, 300), quad_adversarial_points(cage)])
    w = F.quad_mean_value_coordinates(x, cage, backend=backend)
    assert torch.isfinite(w).all()
    assert_partition_of_unity(w, atol=1e-12)
    assert_linear_precision(w, cage.vertices, x, rtol=1e-10)


@pytest.mark.parametrize("model", QMVC_MODELS)
def test_data_cages_partition_and_linear_precision(model, backend):
    cage_file = data_path("qmvc", f"{model}_Cage.obj")
    cage = torchcage.load_cage(cage_file)
    pts = model_points(model, cage, 1500)
    if backend == "torch":
        pts = pts[torch.randperm(pts.shape[0], generator=torch.Generator().manual_seed(0))[:1500]]
    x = torch.cat([pts, quad_adversarial_points(cage)])
    w = F.quad_mean_value_coordinates(x, cage, backend=backend)
    assert torch.isfinite(w).all()
    assert_partition_of_unity(w, atol=1e-12)
    assert_linear_precision(w, cage.vertices.to(torch.float64), x, rtol=1e-10)


def test_nearly_flat_quads_keep_linear_precision(backend):
    """Quads bent by 1e-7 of their size, points 1e-12..1e-3 from them and in their plane beside
    them (absolute thresholds lose linear precision here)."""
    cage = box_cage(2, 1, 1)
    v = cage.vertices.clone()
    top = v[:, 2] > 0
    v[top & (v[:, 0] > 0.5) & (v[:, 1] > 0), 2] += 1e-7
    cage = torchcage.Cage(v, cage.quads)
    g = torch.Generator().manual_seed(1)
    xy = torch.rand(200, 2, generator=g, dtype=torch.float64) * 2.4 - 1.2
    xy[:, 0] *= 2
    pts = []
    for d in [0.0, 1e-12, 1e-9, 1e-6, 1e-3, -1e-12, -1e-9, -1e-6, -1e-3]:
        pts.append(torch.cat([xy, torch.full((200, 1), 1.0 + d, dtype=torch.float64)], 1))
    x = torch.cat(pts)
    w = F.quad_mean_value_coordinates(x, cage, backend=backend)
    assert_partition_of_unity(w, atol=1e-12)
    assert_linear_precision(w, v, x, rtol=1e-10)


def test_triangle_cage_gives_mean_value_coordinates(backend):
    cage = bent_box().triangulated()
    x = box_points(cage, 200)
    w = F.quad_mean_value_coordinates(x, cage, backend=backend)
    torch.testing.assert_close(w, F.mean_value_coordinates(x, cage), atol=1e-13, rtol=0)


# ----------------------------------------------------------------------------- interpolation
def test_bilinear_interpolation_on_nonplanar_quads(backend):
    cage = bent_box()
    g = torch.Generator().manual_seed(3)
    uv = torch.rand(cage.quads.shape[0], 5, 2, generator=g, dtype=torch.float64)
    c = cage.vertices[cage.quads]  # (Q, 4, 3)
    b = torch.stack([(1 - uv[..., 0]) * (1 - uv[..., 1]), uv[..., 0] * (1 - uv[..., 1]),
                     uv[..., 0] * uv[..., 1], (1 - uv[..., 0]) * uv[..., 1]], dim=-1)  # fmt: skip
    x = torch.einsum("qsk,qkc->qsc", b, c).reshape(-1, 3)
    expected = torch.zeros(x.shape[0], cage.num_vertices, dtype=torch.float64)
    expected.scatter_add_(1, cage.quads.repeat_interleave(5, 0), b.reshape(-1, 4))
    w = F.quad_mean_value_coordinates(x, cage, backend=backend)
    torch.testing.assert_close(w, expected, atol=1e-12, rtol=0)
    # ... and the limit from either side: 1e-9 of the size off the sheet, coordinates within ~1e-7.
    n = torch.stack([sheet_normal(c[q], *uv[q, s].tolist()) for q in range(c.shape[0]) for s in range(5)])
    for sgn in (1.0, -1.0):
        w = F.quad_mean_value_coordinates(x + sgn * 1e-9 * cage.scale * n, cage, backend=backend)
        assert (w - expected).abs().max() < 1e-6


def test_cage_vertices_and_edges_interpolate(backend):
    cage = triquad()
    e = cage.unique_edges()
    x = torch.cat([cage.vertices, 0.3 * cage.vertices[e[:, 0]] + 0.7 * cage.vertices[e[:, 1]]])
    on_edges = torch.zeros(e.shape[0], cage.num_vertices, dtype=torch.float64)
    on_edges.scatter_add_(1, e, torch.tensor([[0.3, 0.7]], dtype=torch.float64).expand(e.shape[0], 2))
    expected = torch.cat([torch.eye(cage.num_vertices, dtype=torch.float64), on_edges])
    torch.testing.assert_close(F.quad_mean_value_coordinates(x, cage, backend=backend), expected, atol=1e-12, rtol=0)


# ----------------------------------------------------------------------------- reference and symmetry
def test_converges_to_dense_tessellation_as_n_grows():
    """Planar-quad cube: the error against the tessellated exact integrals shrinks like 1/n^2
    (measured: n = 4: 6.5e-3, 8: 2.8e-3, 16: 7e-4, 32: 1.7e-4)."""
    cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
    x = box_points(cube, 60, spread=0.8)
    ref = dense_reference(cube, x, 64)
    err = {n: (F.quad_mean_value_coordinates(x, cube, n) - ref).abs().max().item() for n in (4, 16, 32)}
    assert err[4] < 2e-2
    assert err[16] < err[4] / 4
    assert err[32] < 5e-4


def test_nonplanar_quads_close_to_dense_tessellation():
    cage = bent_box()
    x = box_points(cage, 40, spread=0.7)
    ref = dense_reference(cage, x, 48)
    assert (F.quad_mean_value_coordinates(x, cage, 16) - ref).abs().max() < 2e-3


def test_mirror_symmetry(backend):
    cage = bent_box()
    v = cage.vertices
    mirror = torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    # The vertex permutation of the mirror: vertex i goes to perm[i].
    perm = torch.cdist(v * mirror, v).argmin(dim=1)
    assert torch.equal(perm[perm], torch.arange(v.shape[0]))
    x = box_points(cage, 300)
    w = F.quad_mean_value_coordinates(x, cage, backend=backend)
    wm = F.quad_mean_value_coordinates(x * mirror, cage, backend=backend)
    torch.testing.assert_close(wm[:, perm], w, atol=1e-10, rtol=0)


@pytest.mark.parametrize("scale", [1e-6, 1e-3, 1e3, 1e6])
def test_invariance_under_similarity(scale, backend):
    """Moving the scene moves nothing, to 1e-10. (Within 1e-9 of the cage size from a quad, the
    rounding of the moved inputs is amplified like 1e-19 / distance: excluded, documented.)"""
    cage = triquad()
    x = torch.cat([box_points(cage, 200), quad_adversarial_points(cage, distances=(0.0, 1e-6, 1e-3))[:-9]])
    w = F.quad_mean_value_coordinates(x, cage, backend=backend)
    R = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2)))[0]
    t = torch.tensor([0.3, -2.0, 1.0], dtype=torch.float64) * scale
    moved = torchcage.Cage(cage.vertices @ R.T * scale + t, cage.faces)
    ws = F.quad_mean_value_coordinates(x @ R.T * scale + t, moved, backend=backend)
    torch.testing.assert_close(ws, w, atol=1e-10, rtol=0)


def test_backends_agree():
    from torchcage.backends import native as _native

    if not _native.available():
        pytest.skip("no C compiler")
    cage = triquad()
    x = torch.cat([box_points(cage, 400), quad_adversarial_points(cage, distances=(0.0, 1e-6, 1e-3))])
    for n in (1, 4):
        a = F.quad_mean_value_coordinates(x, cage, n, backend="native")
        b = F.quad_mean_value_coordinates(x, cage, n, backend="torch")
        torch.testing.assert_close(a, b, atol=1e-10, rtol=0)  # measured: <= 7e-12 (far points)


# ----------------------------------------------------------------------------- gradients, API
@pytest.mark.slow
def test_gradients_wrt_points_match_finite_differences():
    cage = bent_box()
    x = box_points(cage, 6, spread=0.9).requires_grad_(True)
    torch.autograd.gradcheck(lambda p: F.quad_mean_value_coordinates(p, cage, 2), (x,), eps=1e-6, atol=1e-6)
    # Finite everywhere off the cage, near quads included.
    near = quad_adversarial_points(cage, distances=(1e-9, 1e-6, 1e-3))[:48].clone().requires_grad_(True)
    (F.quad_mean_value_coordinates(near, cage) ** 2).sum().backward()
    assert torch.isfinite(near.grad).all()


def test_gradients_wrt_cage_vertices():
    cage = bent_box()
    x = box_points(cage, 4, spread=0.8)

    def f(verts: torch.Tensor) -> torch.Tensor:
        return F.quad_mean_value_coordinates(x, torchcage.Cage(verts, cage.quads, validate=False), 1)

    torch.autograd.gradcheck(f, (cage.vertices.clone().requires_grad_(True),), eps=1e-6, atol=1e-6, fast_mode=True)


def test_float32_batches_and_chunks():
    cage = triquad()
    x = box_points(cage, 50).reshape(5, 10, 3)
    w64 = F.quad_mean_value_coordinates(x, cage)
    assert w64.shape == (5, 10, cage.num_vertices)
    w32 = F.quad_mean_value_coordinates(x.float(), cage, chunk_size=7, dtype=torch.float32)
    assert w32.dtype == torch.float32
    torch.testing.assert_close(w32.double(), w64, atol=1e-4, rtol=0)


def test_errors_and_inputs_untouched():
    cage = bent_box()
    x = box_points(cage, 5)
    before = x.clone()
    F.quad_mean_value_coordinates(x, cage)
    assert torch.equal(x, before)
    with pytest.raises(ValueError, match="positive integer"):
        F.quad_mean_value_coordinates(x, cage, n=0)
    with pytest.raises(ValueError, match=r"past 10000.*tol="):  # (the kernels' C ints and scratch stay bounded)
        F.quad_mean_value_coordinates(x, cage, n=10_001)
    with pytest.raises(ValueError, match="backend must be one of 'auto', 'native', 'torch', 'triton'"):
        F.quad_mean_value_coordinates(x, cage, backend="cuda")
    with pytest.raises(torchcage.PointsError, match="NaN"):
        F.quad_mean_value_coordinates(torch.tensor([[float("nan"), 0.0, 0.0]], dtype=torch.float64), cage)
    with pytest.raises(torchcage.PointsError, match="shape"):
        F.quad_mean_value_coordinates(x[:, :2], cage)
    square = torchcage.Cage(torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], dtype=torch.float64))
    with pytest.raises(torchcage.CageError, match="3D cage"):
        F.quad_mean_value_coordinates(torch.full((1, 2), 0.5, dtype=torch.float64), square)
    # An invalid (folded) quad: refused by default, computed with a warning on request.
    v = box_cage().vertices.clone()
    q = box_cage().quads
    v[q[0, 1]] = v[q[0, 3]] * 1.0 + (v[q[0, 3]] - v[q[0, 0]]) * 0.2  # folds quad 0 over itself
    bad = torchcage.Cage(v, q, check_intersections=False)  # the fold also passes through the cage
    assert bad.invalid_quads().numel() > 0
    with pytest.raises(torchcage.CageError, match="not valid"):
        F.quad_mean_value_coordinates(x, bad)
    with pytest.warns(UserWarning, match="allow_invalid"):
        F.quad_mean_value_coordinates(torch.zeros(1, 3, dtype=torch.float64), bad, allow_invalid=True)


def test_module_matches_functional_and_batches():
    cage = triquad()
    x = box_points(cage, 40)
    m = torchcage.QuadMeanValueCoordinates(cage, x)
    torch.testing.assert_close(m(cage.vertices), x, atol=1e-12, rtol=0)
    poses = torch.stack([cage.vertices * 1.5, cage.vertices + 1.0])
    w = F.quad_mean_value_coordinates(x, cage)
    torch.testing.assert_close(m(poses), w @ poses, atol=1e-12, rtol=0)
    verts = (cage.vertices * 1.1).requires_grad_(True)
    m(verts).sum().backward()
    torch.testing.assert_close(verts.grad, w.sum(0)[:, None].expand(-1, 3), atol=1e-12, rtol=0)
    m2 = torchcage.QuadMeanValueCoordinates(cage, torch.zeros(40, 3, dtype=torch.float64), n=1)
    m2.load_state_dict(m.state_dict())
    torch.testing.assert_close(m2(poses), m(poses))
