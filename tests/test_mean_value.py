"""Mean value coordinates (3D and 2D): properties, special cases, and agreement with mpmath."""

from __future__ import annotations

import math

import pytest
import torch
from reference import mvc2d_reference, mvc3d_reference, to_tensor
from support import HANDMADE, QMVC_MODELS, data_path, model_points

import torchcage
from torchcage import functional as F
from torchcage.testing import assert_interpolates, assert_linear_precision, assert_partition_of_unity


def sample_points(cage: torchcage.Cage, n: int, spread: float = 1.5, seed: int = 0) -> torch.Tensor:
    """Points in a box ``spread`` times the cage's bounding box, inside and outside."""
    g = torch.Generator().manual_seed(seed)
    v = cage.vertices
    lo, hi = v.min(0).values, v.max(0).values
    c, h = (lo + hi) / 2, (hi - lo) / 2 * spread
    return c + (torch.rand(n, cage.dim, generator=g, dtype=torch.float64) * 2 - 1) * h


def adversarial_points(cage: torchcage.Cage, seed: int = 0) -> torch.Tensor:
    """Points on and near the support planes of faces (outside the faces), on vertices, edges and
    faces, 1e-15..1e-3 away from them, and two to five cage sizes away."""
    g = torch.Generator().manual_seed(seed)
    v, tri = cage.vertices, cage.triangles
    p = v[tri]
    n = torch.nn.functional.normalize(torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1), dim=-1)
    scale = cage.scale
    pts = []
    faces = torch.randperm(tri.shape[0], generator=g)[:6]
    for f in faces.tolist():
        c = p[f].mean(0)
        bary = torch.rand(3, generator=g, dtype=torch.float64)
        on_face = (bary / bary.sum()) @ p[f]
        on_edge = 0.3 * p[f, 0] + 0.7 * p[f, 1]
        outside = c + 2.5 * (p[f, 0] - c) + 0.4 * (p[f, 1] - p[f, 2])  # in the plane, outside the face
        for d in [0.0, 1e-15, 1e-12, 1e-9, 1e-6, 1e-3]:
            for sgn in (1.0, -1.0):
                off = sgn * d * scale * n[f]
                pts += [outside + off, on_face + off, on_edge + off, p[f, 0] + off]
    dirs = torch.nn.functional.normalize(torch.randn(8, 3, generator=g, dtype=torch.float64), dim=-1)
    centre = v.mean(0)
    for k, r in enumerate([2.0, 3.0, 5.0] * 3):
        pts.append(centre + dirs[k % 8] * r * scale)
    return torch.stack(pts)


# ----------------------------------------------------------------------------- 3D properties
@pytest.mark.parametrize("name", list(HANDMADE))
def test_partition_and_linear_precision_handmade(name, backend):
    cage = HANDMADE[name]()
    x = torch.cat([sample_points(cage, 400), adversarial_points(cage)])
    w = F.mean_value_coordinates(x, cage, backend=backend)
    assert w.shape == (x.shape[0], cage.num_vertices)
    assert_partition_of_unity(w, atol=1e-12)
    assert_linear_precision(w, cage.vertices, x, rtol=1e-10)


@pytest.mark.parametrize("name", ["cube", "l_shape", pytest.param("twisted_bar", marks=pytest.mark.slow), "notched"])
def test_agrees_with_mpmath(name, backend):
    """Independent half-angle formulation in 60-digit arithmetic, at generic and adversarial points."""
    cage = HANDMADE[name]()
    x = torch.cat([sample_points(cage, 12, seed=3), adversarial_points(cage, seed=1)[::3]])
    w = F.mean_value_coordinates(x, cage, backend=backend)
    # The reference is singular exactly on faces' planes: skip points within 1e-13 of one.
    p = cage.vertices[cage.triangles]
    nrm = torch.nn.functional.normalize(torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1), dim=-1)
    dist = ((p[:, 0][None] - x[:, None]) * nrm[None]).sum(-1).abs().min(dim=1).values
    keep = dist > 1e-13 * cage.scale
    worst = 0.0
    for i in torch.nonzero(keep).flatten().tolist():
        ref = to_tensor(mvc3d_reference(x[i], cage.vertices, cage.triangles))
        worst = max(worst, float((w[i] - ref).abs().max()))
    assert keep.sum() > 20
    assert worst < 1e-12, worst


def test_support_plane_outside_face_contributes_nothing(backend):
    """Points exactly in the plane of faces (outside them) against the 60-digit reference taken
    1e-40 off the plane: the limit, where those faces contribute nothing."""
    import mpmath as mp

    cage = HANDMADE["l_shape"]()  # axis-aligned faces: planes x, y, z = const hold these points exactly
    x = torch.tensor([[2.0, 0.3, 0.5], [0.25, 1.0, -0.5], [-1.5, -1.0, 0.1], [0.5, 0.5, 0.5]], dtype=torch.float64)
    w = F.mean_value_coordinates(x, cage, backend=backend)
    assert_linear_precision(w, cage.vertices, x, rtol=1e-12)
    for i in range(x.shape[0]):
        off = [mp.mpf(float(c)) for c in x[i]]
        off[0] += mp.mpf("1e-40")
        off[1] += mp.mpf("1e-40")
        off[2] += mp.mpf("1e-40")
        ref = to_tensor(mvc3d_reference(off, cage.vertices, cage.triangles))
        assert (w[i] - ref).abs().max() < 1e-14


def test_interpolation_on_cage(backend):
    cage = HANDMADE["l_shape"]()
    v, tri = cage.vertices, cage.triangles
    g = torch.Generator().manual_seed(5)
    V = cage.num_vertices
    pts, expected = [], []
    for f in range(tri.shape[0]):
        b = torch.rand(3, generator=g, dtype=torch.float64)
        b = b / b.sum()
        for bary in (b, torch.tensor([0.0, 0.25, 0.75], dtype=torch.float64), torch.tensor([1.0, 0, 0]).double()):
            pts.append(bary @ v[tri[f]])
            e = torch.zeros(V, dtype=torch.float64)
            e[tri[f]] = bary
            expected.append(e)
    x, expected = torch.stack(pts), torch.stack(expected)
    w = F.mean_value_coordinates(x, cage, backend=backend)
    assert_interpolates(w, expected, atol=1e-12)
    w_vert = F.mean_value_coordinates(v, cage, backend=backend)
    assert torch.equal(w_vert, torch.eye(V, dtype=torch.float64))


def test_no_nan_on_and_near_everything(backend):
    cage = HANDMADE["twisted_bar"]()
    x = adversarial_points(cage, seed=7)
    w = F.mean_value_coordinates(x, cage, backend=backend)
    assert torch.isfinite(w).all()


@pytest.mark.parametrize("scale", [1e-6, 1e-3, 1.0, 1e3, 1e6])
def test_invariance_under_similarity(scale, backend):
    cage = HANDMADE["notched"]()
    x = torch.cat([sample_points(cage, 200, seed=2), adversarial_points(cage, seed=2)])
    w0 = F.mean_value_coordinates(x, cage, backend=backend)
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64))
    t = torch.tensor([0.3, -2.0, 1.5], dtype=torch.float64)

    def move(p):
        return (p @ q.T + t) * scale

    moved = torchcage.Cage(move(cage.vertices), cage.triangles)
    w1 = F.mean_value_coordinates(move(x), moved, backend=backend)
    assert (w1 - w0).abs().max() < 1e-10


def test_backends_agree():
    from torchcage.backends import native as _native

    if not _native.available():
        pytest.skip("native kernel unavailable")
    cage = HANDMADE["twisted_bar"]()
    x = torch.cat([sample_points(cage, 500, seed=4), adversarial_points(cage, seed=4)])
    a = F.mean_value_coordinates(x, cage, backend="native")
    b = F.mean_value_coordinates(x, cage, backend="torch")
    assert (a - b).abs().max() < 1e-12


def test_chunking_batching_and_dtype(dtype, device):
    cage = HANDMADE["cube"]().to(device=device)
    x = sample_points(HANDMADE["cube"](), 300).to(device)
    ref = F.mean_value_coordinates(x, cage)
    assert (F.mean_value_coordinates(x, cage, chunk_size=7) - ref).abs().max() < 1e-14
    batched = F.mean_value_coordinates(x.reshape(3, 100, 3), cage)
    assert batched.shape == (3, 100, 8) and torch.equal(batched.reshape(300, 8), ref)
    out = F.mean_value_coordinates(x.to(dtype), cage.to(dtype))
    assert out.dtype == dtype and out.device.type == device
    assert (out.double() - ref).abs().max() < (1e-6 if dtype == torch.float32 else 1e-14)
    low = F.mean_value_coordinates(x, cage, dtype=torch.float32)
    assert low.dtype == torch.float32 and (low.double() - ref).abs().max() < 1e-4


def test_autograd_points_and_vertices():
    """gradcheck with respect to points (analytic kernels) and rest-cage vertices (autograd of the
    torch kernel); includes a point near a face whose foot lies on the face's diagonal line (s = 0),
    where abs() once gave a wrong derivative. The native forward kernel serves graphs too now."""
    cage = HANDMADE["cube"]()
    x = torch.tensor(
        [[0.1, 0.2, -0.3], [0.5, -0.4, 0.2], [1.5, 0.3, 0.2], [0.99, 0.1, 0.1], [0.3, 0.3, 0.9999], [4.0, -3.0, 2.0]],
        dtype=torch.float64,
    )
    xr = x.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: F.mean_value_coordinates(p, cage), (xr,))
    v = cage.vertices.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda vv: F.mean_value_coordinates(x, torchcage.Cage(vv, cage.triangles, validate=False)), (v,)
    )
    poly = star()
    y = torch.tensor([[0.1, 0.2], [0.3, -0.2], [2.0, 0.5]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p: F.mean_value_coordinates(p, poly), (y,))
    from torchcage.backends import native as _native

    if _native.available():
        assert torch.autograd.gradcheck(lambda p: F.mean_value_coordinates(p, cage, backend="native"), (xr,))
    else:  # backend="native" insists, with a graph too
        with pytest.raises(RuntimeError, match="native kernel"):
            F.mean_value_coordinates(xr, cage, backend="native")


def test_progress_reporting(capsys):
    cage = HANDMADE["cube"]()
    x = sample_points(cage, 100)
    calls = []
    w = F.mean_value_coordinates(x, cage, chunk_size=30, progress=lambda done, total: calls.append((done, total)))
    assert calls == [(30, 100), (60, 100), (90, 100), (100, 100)]
    # (bitwise equal with the native kernel; the torch kernel's reductions may round differently)
    torch.testing.assert_close(w, F.mean_value_coordinates(x, cage, progress=True), rtol=0, atol=1e-14)


def test_inputs_not_modified_and_errors():
    cage = torchcage.load_cage(torchcage.data.path("cube.obj"))
    x = torch.zeros(2, 3, dtype=torch.float64)
    with pytest.raises(torchcage.CageError, match="quad_mean_value_coordinates"):
        F.mean_value_coordinates(x, cage)
    tri = cage.triangulated()
    before = x.clone()
    F.mean_value_coordinates(x, tri)
    assert torch.equal(x, before)
    with pytest.raises(torchcage.PointsError, match="NaN or inf"):
        F.mean_value_coordinates(torch.tensor([[0.0, float("nan"), 0.0]]), tri)
    with pytest.raises(torchcage.PointsError, match=r"\(\.\.\., 3\)"):
        F.mean_value_coordinates(torch.zeros(4, 2), tri)
    with pytest.raises(TypeError, match="floating-point"):
        F.mean_value_coordinates(torch.zeros(4, 3, dtype=torch.int64), tri)
    with pytest.raises(ValueError, match="backend"):
        F.mean_value_coordinates(x, tri, backend="gpu")


# ----------------------------------------------------------------------------- data sets
@pytest.mark.parametrize("model", QMVC_MODELS)
def test_qmvc_cages_triangulated(model):
    cage = torchcage.load_cage(data_path("qmvc", f"{model}_Cage.obj")).triangulated()
    x = model_points(model, cage, 2000)
    x = torch.cat([x[:: max(1, x.shape[0] // 20000)], sample_points(cage, 2000, spread=2.0), adversarial_points(cage)])
    w = F.mean_value_coordinates(x, cage)
    assert_partition_of_unity(w, atol=1e-12)
    assert_linear_precision(w, cage.vertices, x, rtol=1e-10)


# ----------------------------------------------------------------------------- 2D
def star(n: int = 7) -> torchcage.Cage:
    ang = torch.arange(2 * n, dtype=torch.float64) * math.pi / n
    r = torch.where(torch.arange(2 * n) % 2 == 0, 1.0, 0.45).double()
    return torchcage.Cage(torch.stack([r * torch.cos(ang), r * torch.sin(ang)], dim=1))


def test_2d_properties_and_mpmath(backend):
    cage = star()
    x = sample_points(cage, 300, seed=1)
    w = F.mean_value_coordinates(x, cage, backend=backend)
    assert_partition_of_unity(w, atol=1e-12)
    assert_linear_precision(w, cage.vertices, x, rtol=1e-10)
    worst = max(float((w[i] - to_tensor(mvc2d_reference(x[i], cage.vertices))).abs().max()) for i in range(40))
    assert worst < 1e-12


def test_2d_interpolation_and_near_edges(backend):
    cage = star()
    v, e = cage.vertices, cage.edges
    V = cage.num_vertices
    t = torch.linspace(0, 1, 7, dtype=torch.float64)
    pts = (v[e[:, 0]][:, None] * (1 - t)[None, :, None] + v[e[:, 1]][:, None] * t[None, :, None]).reshape(-1, 2)
    expected = torch.zeros(pts.shape[0], V, dtype=torch.float64)
    rows = torch.arange(pts.shape[0])
    j = e[:, 0].repeat_interleave(len(t))
    k = e[:, 1].repeat_interleave(len(t))
    tt = t.repeat(e.shape[0])
    expected.index_put_((rows, j), 1 - tt, accumulate=True)
    expected.index_put_((rows, k), tt, accumulate=True)
    assert_interpolates(F.mean_value_coordinates(pts, cage, backend=backend), expected, atol=1e-12)
    normal = cage.edge_normals()
    for d in [1e-15, 1e-9, 1e-4]:
        near = pts + d * normal.repeat_interleave(len(t), dim=0)
        w = F.mean_value_coordinates(near, cage, backend=backend)
        assert torch.isfinite(w).all()
        assert_linear_precision(w, v, near, rtol=1e-10)


def test_2d_backends_agree():
    cage = star()
    x = torch.cat([sample_points(cage, 2000, spread=2.0, seed=9), cage.vertices, cage.vertices + 1e-13])
    a = F.mean_value_coordinates(x, cage, backend="torch")
    b = F.mean_value_coordinates(x, cage)
    assert (a - b).abs().max() < 1e-12


@pytest.mark.parametrize("name", ["Gil_Gecko", "LBClogo", "cactus", "woody"])
def test_2d_clockwise_data_keeps_vertex_order(name):
    with pytest.warns(UserWarning, match="clockwise"):
        cage = torchcage.load_cage(data_path("lbc2d", f"{name}-control-edgeset.obj"))
    raw = torchcage.io.read_obj(data_path("lbc2d", f"{name}-control-edgeset.obj"))[0]
    assert torch.equal(cage.vertices, torch.as_tensor(raw[:, :2]))
    x = sample_points(cage, 500, spread=1.2, seed=3)
    w = F.mean_value_coordinates(x, cage)
    assert_partition_of_unity(w, atol=1e-12)
    assert_linear_precision(w, cage.vertices, x, rtol=1e-10)
    i = 0
    ref = to_tensor(mvc2d_reference(x[i], cage.vertices.flip(0)))
    assert (w[i] - ref.flip(0)).abs().max() < 1e-12
