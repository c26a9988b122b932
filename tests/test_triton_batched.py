"""Batched rest cages in one Triton launch: mean value and Green coordinates of a batch of 3D
triangle cages with one topology (the kernel's cage axis, tables built for the batch at once) agree with the loop
of single-cage Triton calls, for points inside, outside, on faces, edges and vertices and far away,
shared by every cage or one set per cage. Run by Triton's interpreter on CPU tensors
(``TRITON_INTERPRET=1``) or on a GPU when there is one, as ``tests/test_triton.py``."""

from __future__ import annotations

import pytest
import torch
from support import TRITON_DEVICE, require_triton

import torchcage
from torchcage import functional as F
from torchcage.families.mean_value.kernel3d import triangle_cage_data
from torchcage.testing import sliver_cube

pytestmark = pytest.mark.triton

require_triton()

from torchcage.families.green.triton import gc3d as _gc3d  # noqa: E402
from torchcage.families.mean_value.triton import mvc2d as _mvc2d  # noqa: E402
from torchcage.families.mean_value.triton import mvc3d as _mvc3d  # noqa: E402
from torchcage.families.mean_value.triton import mvcd2d as _mvcd2d  # noqa: E402

DEVICE = TRITON_DEVICE
D64 = torch.float64


def _cages(B: int, seed: int = 0, shift: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """``(B, 8, 3)`` jittered, scaled cubes (float64) and their 12 triangles (small: the interpreter
    runs a face at a time); ``shift`` moves the last cage that far from the origin (computed
    relative to its centre)."""
    cube = torchcage.load_cage(torchcage.data.path("cube.obj")).to(D64).triangulated()
    g = torch.Generator().manual_seed(seed)
    V = cube.vertices * (1 + 0.3 * torch.rand(B, 1, 1, generator=g, dtype=D64))
    V = V + 0.03 * torch.randn(B, 8, 3, generator=g, dtype=D64)
    V[-1] += shift
    return V, cube.triangles


def _points(V: torch.Tensor, tri: torch.Tensor, seed: int = 1, far: bool = False) -> torch.Tensor:
    """Points of every kind for the cage ``V`` ``(8, 3)``: inside, on vertices, on edge midpoints,
    on faces, just off faces on both sides (39); with ``far``, outside, far and very far away
    instead (12: the far pass, slow in the interpreter)."""
    g = torch.Generator().manual_seed(seed)
    c = V.mean(0)
    d = torch.nn.functional.normalize(torch.randn(12, 3, generator=g, dtype=D64), dim=1)
    if far:
        r = torch.tensor([2.0, 3.0, 5.0, 10.0, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9], dtype=D64)
        return c + r[:, None] * d  # (from 1e3 radii on: the first-moment normaliser)
    p = V[tri]
    bary = torch.rand(12, 3, generator=g, dtype=D64)
    on_face = (bary[:, :, None] * p).sum(1) / bary.sum(1, keepdim=True)
    nrm = torch.nn.functional.normalize(torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1), dim=1)
    return torch.cat(
        [
            c + 0.4 * torch.rand(8, 1, generator=g, dtype=D64) * d[:8],  # inside
            V[:4],  # on vertices
            0.5 * (p[:3, 0] + p[:3, 1]),  # on edges
            on_face[:4],  # on faces
            on_face[4:8] + 1e-9 * nrm[4:8],  # just outside the faces
            on_face[8:12] - 1e-7 * nrm[8:12],  # just inside
            on_face[:12:2] + 1e-3 * nrm[:12:2],  # near outside
            on_face[1:12:2] - 1e-2 * nrm[1:12:2],  # near inside
        ]
    )


def _assert_close(out: torch.Tensor, ref: torch.Tensor) -> None:
    """Within 1e-12 (float64) or 1e-5 (float32) of ``ref``, relative to ``max(1, |ref|)``: the same
    kernel on the same tables (the batch's built by batched tensor ops, which may round apart)."""
    assert out.shape == ref.shape and out.dtype == ref.dtype
    tol = 1e-12 if out.dtype == D64 else 1e-5
    err = (out.double() - ref.double()).abs() / ref.double().abs().clamp_min(1.0)
    assert bool(torch.isfinite(out).all()) and float(err.max()) <= tol, float(err.max())


class _Launches:
    """Counts the calls of a Triton kernel's wrapper (``module.name``: the mean value kernel's by
    default), with their batch sizes."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, module: object = _mvc3d, name: str = "mvc3d_triton") -> None:
        self.batches: list[int] = []
        real = getattr(module, name)

        def wrapper(x, tables, *args, **kwargs):
            self.batches.append(int(tables["P"].shape[0]))
            return real(x, tables, *args, **kwargs)

        monkeypatch.setattr(module, name, wrapper)


@pytest.mark.parametrize("dtype", [torch.float32, D64], ids=["float32", "float64"])
@pytest.mark.parametrize("B", [1, 2])
def test_batched_launch_equals_the_loop(dtype: torch.dtype, B: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Points one set per cage (XB = B) and shared (XB = 1), on and near the cages, the last cage
    1e3 from the origin: the whole batch is one launch and element by element the single-cage
    Triton call; in float64 the rows sum to one and reproduce the points."""
    V, tri = _cages(B, shift=1e3 if B > 1 else 0.0)
    cage = torchcage.Cage(V.to(dtype).to(DEVICE), tri.to(DEVICE))
    per_cage = torch.stack([_points(V[b], tri, seed=b) for b in range(B)]).to(dtype).to(DEVICE)
    opts = {"backend": "triton", "dtype": dtype}
    launches = _Launches(monkeypatch)
    for pts in (per_cage, per_cage[0]):
        launches.batches.clear()
        out = F.mean_value_coordinates(pts, cage, **opts)
        assert launches.batches == [B]  # one launch for the whole batch
        ref = torch.stack(
            [F.mean_value_coordinates(pts if pts.ndim == 2 else pts[b], cage[b], **opts) for b in range(B)]
        )
        _assert_close(out, ref)
        if dtype == D64:
            W, X = out.cpu(), (pts if pts.ndim == 3 else pts.expand(B, -1, -1)).cpu()
            assert float((W.sum(-1) - 1).abs().max()) < 1e-12
            assert float((W @ V - X).norm(dim=-1).max()) < 1e-9 * (1 + V.abs().max())


def test_outside_and_far_points() -> None:
    """Points from 2 to 1e9 radii (the far pass with its quadrature, the first-moment normaliser,
    ``far_unity``), shared by two cages, one of them 1e3 from the origin."""
    V, tri = _cages(2, seed=5, shift=1e3)
    cage = torchcage.Cage(V.to(DEVICE), tri.to(DEVICE))
    x = _points(V[0], tri, far=True).to(DEVICE)
    out = F.mean_value_coordinates(x, cage, backend="triton")
    for b in range(2):
        _assert_close(out[b], F.mean_value_coordinates(x, cage[b], backend="triton"))
    W = out.cpu()
    y = x.cpu() - V.mean(1, keepdim=True)
    # (far away the coordinates are of size distance / size: their sum is 1 to their rounding)
    assert bool(((W.sum(-1) - 1).abs() <= 1e-13 * W.abs().sum(-1).clamp_min(1.0)).all())
    assert float(((W @ V - x.cpu()).norm(dim=-1) / y.norm(dim=-1)).max()) < 1e-8


def test_blocks_and_cages_in_one_grid() -> None:
    """The kernel itself with small blocks (13 points, blocks of 8: two programs per cage, the
    last partial), points one set per cage and shared, against the kernel on each cage's own
    tables (the shared points' cage 0 is the per-cage call's cage 0)."""
    V, tri = _cages(2, seed=4, shift=5.0)
    V, tri = V.to(DEVICE), tri.to(DEVICE)
    x = torch.stack([_points(V[b].cpu(), tri.cpu(), seed=7 + b)[6:19] for b in range(2)]).to(DEVICE)  # (2, 13, 3)
    tol = torch.full((2,), 1e-13, dtype=D64)
    tables = _mvc3d.batch_tables(V, tri, tol)

    def single(b: int, X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        one = _mvc3d.triton_tables(triangle_cage_data(torchcage.Cage(V[b], tri), D64))
        one["tol"] = tol[b : b + 1].to(DEVICE)
        return _mvc3d.mvc3d_triton(X, one, block=8)

    W, flags = _mvc3d.mvc3d_triton(x, tables, block=8)
    Ws, fs = _mvc3d.mvc3d_triton(x[:1], tables, block=8)
    assert W.shape == Ws.shape == (2, 13, 8) and flags.shape == fs.shape == (2, 13)
    assert int((flags == 1).sum()) > 0 and int((flags == 0).sum()) > 0  # on the cage and off it
    for b, (Wb, fb) in enumerate(single(b, x[b]) for b in range(2)):
        _assert_close(W[b], Wb)
        assert torch.equal(flags[b], fb)
    _assert_close(Ws[0], W[0])
    Wb, fb = single(1, x[0])
    _assert_close(Ws[1], Wb)
    assert torch.equal(fs[1], fb)
    with pytest.raises(ValueError, match="for tables of 2 cages"):
        _mvc3d.mvc3d_triton(torch.zeros(3, 5, 3, dtype=D64, device=DEVICE), tables)


def _sliver_batch() -> tuple[torchcage.Cage, torch.Tensor]:
    """The sliver cube and a stretched copy (a batch of two, on the device), and 26 points shared by
    both: inside the box, and just outside six of its vertices (some see the sliver from a few widths)."""
    one = sliver_cube()
    V = torch.stack([one.vertices, one.vertices * torch.tensor([1.0, 1.5, 0.8], dtype=D64)])
    cage = torchcage.Cage(V.to(DEVICE), one.triangles.to(DEVICE))
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(20, 3, generator=g, dtype=D64) - 0.5) * 1.6 * one.vertices.abs().amax()
    return cage, torch.cat([x, one.vertices[:6] * 1.001]).to(DEVICE)


def test_thin_faces_in_a_batch_are_redone_by_the_torch_kernel() -> None:
    """The sliver cube and a stretched copy: points that see the sliver from a few widths are
    flagged by the kernel and redone, per cage, by the torch kernel's swept form, as one cage."""
    cage, x = _sliver_batch()
    tables = _mvc3d.batch_tables(cage.vertices, cage.triangles, torch.full((2,), 1e-13, dtype=D64))
    assert int((_mvc3d.mvc3d_triton(x[None], tables)[1] == 2).sum()) > 0
    out = F.mean_value_coordinates(x, cage, backend="triton")
    for b in range(2):
        _assert_close(out[b], F.mean_value_coordinates(x, cage[b], backend="triton"))
        ref = F.mean_value_coordinates(x.cpu(), cage[b].to("cpu"), backend="torch")
        assert float(((out[b].cpu() - ref).abs() / ref.abs().clamp_min(1.0)).max()) < 1e-10


def test_undefined_points_are_named_by_element(monkeypatch: pytest.MonkeyPatch) -> None:
    V, tri = _cages(3)
    real = _mvc3d.mvc3d_triton

    def launch(x, tables, *args, **kwargs):
        W, flags = real(x, tables, *args, **kwargs)
        W[1, 4, 0] = float("nan")  # as a row whose total weight vanishes
        return W, flags

    monkeypatch.setattr(_mvc3d, "mvc3d_triton", launch)
    x = torch.zeros(5, 3, dtype=D64, device=DEVICE)
    with pytest.raises(torchcage.PointsError, match=r"undefined at points \[4\] in batch element \(1,\)"):
        F.mean_value_coordinates(x, torchcage.Cage(V.to(DEVICE), tri.to(DEVICE)), backend="triton")


def test_no_points() -> None:
    V, tri = _cages(2)
    cage = torchcage.Cage(V.to(DEVICE), tri.to(DEVICE))
    for pts in (torch.zeros(0, 3, dtype=D64), torch.zeros(2, 0, 3, dtype=D64)):
        assert F.mean_value_coordinates(pts.to(DEVICE), cage, backend="triton").shape == (2, 0, 8)


# ----------------------------------------------------------------------------------- Green


def _normals(V: torch.Tensor, tri: torch.Tensor) -> torch.Tensor:
    """Outward unit normals ``(B, T, 3)`` of the cages ``V`` ``(B, V, 3)``."""
    p = V[:, tri]
    return torch.nn.functional.normalize(
        torch.linalg.cross(p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :]), dim=-1
    )


@pytest.mark.parametrize("dtype", [torch.float32, D64], ids=["float32", "float64"])
@pytest.mark.parametrize("B", [1, 2])
def test_batched_green_launch_equals_the_loop(dtype: torch.dtype, B: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Green coordinates (the exterior continued) of points one set per cage and shared, on and near
    the cages, the last cage 1e3 from the origin: one launch for the whole batch and element by
    element the single-cage Triton call; in float64, ``phi @ V + psi @ N`` reproduces the points."""
    V, tri = _cages(B, shift=1e3 if B > 1 else 0.0)
    cage = torchcage.Cage(V.to(dtype).to(DEVICE), tri.to(DEVICE))
    per_cage = torch.stack([_points(V[b], tri, seed=b) for b in range(B)]).to(dtype).to(DEVICE)
    launches = _Launches(monkeypatch, _gc3d, "gc3d_triton")
    for pts in (per_cage, per_cage[0]):
        launches.batches.clear()
        phi, psi = F.green_coordinates(pts, cage, backend="triton")
        assert launches.batches == [B]  # one launch for the whole batch
        refs = [F.green_coordinates(pts if pts.ndim == 2 else pts[b], cage[b], backend="triton") for b in range(B)]
        _assert_close(phi, torch.stack([r[0] for r in refs]))
        _assert_close(psi, torch.stack([r[1] for r in refs]))
        if dtype == D64:
            X = (pts if pts.ndim == 3 else pts.expand(B, -1, -1)).cpu()
            rebuilt = phi.cpu() @ V + psi.cpu() @ _normals(V, tri)
            assert float((rebuilt - X).norm(dim=-1).max()) < 1e-9 * (1 + V.abs().max())


def test_batched_green_far_points_and_thin_faces() -> None:
    """Points from 2 to 1e9 radii (the far-field rule) shared by two cages, one 1e3 from the origin;
    and the sliver cube with a stretched copy, whose points that see the sliver from a few widths
    are flagged and redone per cage by the torch kernel: element by element the single-cage call,
    and the torch kernel's values."""
    V, tri = _cages(2, seed=5, shift=1e3)
    cage = torchcage.Cage(V.to(DEVICE), tri.to(DEVICE))
    x = _points(V[0], tri, far=True).to(DEVICE)
    phi, psi = F.green_coordinates(x, cage, backend="triton")
    for b in range(2):
        ref = F.green_coordinates(x, cage[b], backend="triton")
        _assert_close(phi[b], ref[0])
        _assert_close(psi[b], ref[1])
    cage, x = _sliver_batch()
    tables = _gc3d.batch_tables(cage.vertices, cage.triangles, torch.full((2,), 1e-13, dtype=D64))
    assert int((_gc3d.gc3d_triton(x[None], tables)[2] == 2).sum()) > 0  # (the kernel flags some)
    phi, psi = F.green_coordinates(x, cage, backend="triton")
    for b in range(2):
        ref = F.green_coordinates(x.cpu(), cage[b].to("cpu"), backend="torch")
        for out, r in ((phi[b], ref[0]), (psi[b], ref[1])):
            assert float(((out.cpu() - r).abs() / r.abs().clamp_min(1.0)).max()) < 1e-10


def test_batched_green_kernel_blocks_and_point_batches() -> None:
    """The kernel itself with small blocks (13 points, blocks of 8: two programs per cage, the last
    partial), points one set per cage and shared, against the kernel on each cage's own tables;
    a point batch that is neither 1 nor the cages' is refused."""
    from torchcage.families.green.kernel3d import triangle_green_data

    V, tri = _cages(2, seed=4, shift=5.0)
    V, tri = V.to(DEVICE), tri.to(DEVICE)
    x = torch.stack([_points(V[b].cpu(), tri.cpu(), seed=7 + b)[6:19] for b in range(2)]).to(DEVICE)
    tol = torch.full((2,), 1e-13, dtype=D64)
    tables = _gc3d.batch_tables(V, tri, tol)
    outs = _gc3d.gc3d_triton(x, tables, block=8)
    shared = _gc3d.gc3d_triton(x[:1], tables, block=8)
    assert outs[0].shape == (2, 13, 8) and outs[1].shape == (2, 13, 12) and outs[2].shape == (2, 13)
    assert int((outs[2] == 1).sum()) > 0 and int((outs[2] == 0).sum()) > 0  # on the cage and off it
    for b in range(2):
        cage = torchcage.Cage(V[b], tri)
        one = _gc3d.triton_tables(triangle_green_data(cage, D64), cage.vertices)
        one["tol"] = tol[b : b + 1].to(DEVICE)
        for X, got in ((x[b], [o[b] for o in outs]), (x[0], [o[b] for o in shared])):
            ref = _gc3d.gc3d_triton(X, one, block=8)
            _assert_close(got[0], ref[0])
            _assert_close(got[1], ref[1])
            assert torch.equal(got[2], ref[2])
    with pytest.raises(ValueError, match="for tables of 2 cages"):
        _gc3d.gc3d_triton(torch.zeros(3, 5, 3, dtype=D64, device=DEVICE), tables)


# ----------------------------------------------------------------------------------- polygons


def _polygons(B: int, shift: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """``(B, 8, 2)`` jittered star-shaped octagons (float64, counter-clockwise) and their edges;
    ``shift`` moves the last one that far from the origin."""
    g = torch.Generator().manual_seed(3)
    angle = torch.arange(8, dtype=D64) * (torch.pi / 4)
    V = (1 + 0.25 * torch.rand(B, 8, 1, generator=g, dtype=D64)) * torch.stack([angle.cos(), angle.sin()], dim=-1)
    V[-1] += shift
    return V, torch.stack([torch.arange(8), torch.arange(8).roll(-1)], dim=1)


def _polygon_points(V: torch.Tensor, seed: int) -> torch.Tensor:
    """Points for the polygon ``V`` ``(8, 2)``: inside, on vertices and edges, just off the edges,
    outside, far (1e4) and very far (1e7: the first-moment normaliser)."""
    g = torch.Generator().manual_seed(seed)
    c = V.mean(0)
    d = torch.nn.functional.normalize(torch.randn(12, 2, generator=g, dtype=D64), dim=1)
    edge = V + 0.3 * (V.roll(-1, 0) - V)
    return torch.cat([c + 0.5 * d[:6], V[:3], edge[:3], edge[3:6] * (1 + 1e-9), c + 3 * d[6:8],
                      c + 1e4 * d[8:10], c + 1e7 * d[10:12]])  # fmt: skip


@pytest.mark.parametrize("dtype", [torch.float32, D64], ids=["float32", "float64"])
def test_batched_polygons_in_one_launch_equal_the_loop(dtype: torch.dtype, monkeypatch: pytest.MonkeyPatch) -> None:
    """2D mean value coordinates of three polygons (the last 1e3 from the origin), points one set
    per polygon and shared: one launch for the batch and element by element the single-polygon
    Triton call; in float64 the rows sum to one and reproduce the points."""
    V, edges = _polygons(3, shift=1e3)
    cage = torchcage.Cage(V.to(dtype).to(DEVICE), edges.to(DEVICE))
    per = torch.stack([_polygon_points(V[b], seed=b) for b in range(3)]).to(dtype).to(DEVICE)
    opts = {"backend": "triton", "dtype": dtype}
    launches = _Launches(monkeypatch, _mvc2d, "mvc2d_triton")
    for pts in (per, per[0]):
        launches.batches.clear()
        out = F.mean_value_coordinates(pts, cage, **opts)
        assert launches.batches == [3]  # one launch for the whole batch
        ref = torch.stack(
            [F.mean_value_coordinates(pts if pts.ndim == 2 else pts[b], cage[b], **opts) for b in range(3)]
        )
        _assert_close(out, ref)
        if dtype == D64:
            W, X = out.cpu(), (pts if pts.ndim == 3 else pts.expand(3, -1, -1)).cpu()
            near = (X - V.mean(1, keepdim=True)).norm(dim=-1) < 10
            # (far away the coordinates are of size distance / size: their sum is 1 to their rounding)
            assert bool(((W.sum(-1) - 1).abs() <= 1e-13 * W.abs().sum(-1).clamp_min(1.0)).all())
            assert float((W @ V - X).norm(dim=-1)[near].max()) < 1e-9 * (1 + V.abs().max())


def test_batched_polygon_kernel_blocks_and_point_batches() -> None:
    """The 2D kernel with small blocks (two programs per polygon, the last partial) against each
    polygon's own tables, points one set per polygon and shared; a point batch that is neither 1 nor
    the polygons' is refused."""
    V, edges = _polygons(2, shift=5.0)
    V, edges = V.to(DEVICE), edges.to(DEVICE)
    x = torch.stack([_polygon_points(V[b].cpu(), seed=4 + b)[:13] for b in range(2)]).to(DEVICE)  # (2, 13, 2)
    tol = torch.full((2,), 1e-13, dtype=D64)
    tables = _mvc2d.batch_tables(V, edges, tol)
    W, flags = _mvc2d.mvc2d_triton(x, tables, block=8)
    Ws, fs = _mvc2d.mvc2d_triton(x[:1], tables, block=8)
    assert W.shape == (2, 13, 8) and int((flags == 1).sum()) > 0 and int((flags == 0).sum()) > 0
    for b in range(2):
        one = _mvc2d.batch_tables(V[b : b + 1], edges, tol[b : b + 1])
        for X, got, gf in ((x[b], W[b], flags[b]), (x[0], Ws[b], fs[b])):
            ref, rf = _mvc2d.mvc2d_triton(X, one, block=8)
            _assert_close(got, ref)
            assert torch.equal(gf, rf)
    with pytest.raises(ValueError, match="for tables of 2 polygons"):
        _mvc2d.mvc2d_triton(torch.zeros(3, 5, 2, dtype=D64, device=DEVICE), tables)


# ------------------------------------------------------------------------- polygons: derivatives
def _off_polygon_points(V: torch.Tensor, seed: int) -> torch.Tensor:
    """:func:`_polygon_points` without the points on the polygon (the derivatives refuse them)."""
    x = _polygon_points(V, seed)
    return torch.cat([x[:6], x[12:]])


@pytest.mark.parametrize("order", [1, 2])
def test_batched_polygon_derivatives_in_one_launch_equal_the_loop(order: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Gradients and Hessians of 2D mean value coordinates of three polygons (the last 1e3 from the
    origin), points one set per polygon and shared: one launch per chunk for the batch
    (``mvcd2d_triton_batch``), element by element the single-polygon Triton call, and linear
    precision (``sum_i grad_i v_i^T = I``, ``sum_i hess_i v_i = 0``) near the polygons."""
    V, edges = _polygons(3, shift=1e3)
    cage = torchcage.Cage(V.to(DEVICE), edges.to(DEVICE))
    per = torch.stack([_off_polygon_points(V[b], seed=b) for b in range(3)]).to(DEVICE)
    launches = _Launches(monkeypatch, _mvcd2d, "mvcd2d_triton_batch")
    for pts in (per, per[0]):
        launches.batches.clear()
        out = F.mean_value_derivatives(pts, cage, order, backend="triton")
        assert launches.batches == [3]  # one launch for the whole batch
        refs = [F.mean_value_derivatives(pts if pts.ndim == 2 else pts[b], cage[b], order, backend="triton")
                for b in range(3)]  # fmt: skip
        assert launches.batches == [3, 1, 1, 1]
        for k in range(3 if order == 2 else 2):
            _assert_close(out[k], torch.stack([r[k] for r in refs]))
        X = (pts if pts.ndim == 3 else pts.expand(3, -1, -1)).cpu()
        near = (X - V.mean(1, keepdim=True)).norm(dim=-1) < 10
        Vc = V - V.mean(1, keepdim=True)  # (the identities about the centre: the derivatives sum to 0)
        G = torch.einsum("bnvc,bvd->bncd", out[1].cpu(), Vc)
        assert float((G - torch.eye(2, dtype=D64))[near].abs().max()) < 1e-9
        if order == 2:
            H = torch.einsum("bnvcd,bve->bncde", out[2].cpu(), Vc)
            assert float(H[near].abs().max()) < 1e-8
    assert out[2] is None if order == 1 else out[2].shape == (3, per.shape[1], 8, 2, 2)


def test_batched_polygon_derivative_kernel_blocks_and_point_batches() -> None:
    """The 2D derivative kernel with small blocks (two programs per polygon, the last partial)
    against each polygon's own tables, points one set per polygon and shared, on-polygon rows
    included (flag 1, the interpolant's derivative); a point batch that is neither 1 nor the
    polygons' is refused."""
    V, edges = _polygons(2, shift=5.0)
    V, edges = V.to(DEVICE), edges.to(DEVICE)
    x = torch.stack([_polygon_points(V[b].cpu(), seed=4 + b)[:13] for b in range(2)]).to(DEVICE)  # (2, 13, 2)
    tol = torch.full((2,), 1e-13, dtype=D64)
    tables = _mvcd2d.batch_tables(V, edges, tol)
    out = _mvcd2d.mvcd2d_triton_batch(x, tables, 2, block=8)
    shared = _mvcd2d.mvcd2d_triton_batch(x[:1], tables, 2, block=8)
    assert out[0].shape == (2, 13, 8) and int((out[3] == 1).sum()) > 0 and int((out[3] == 0).sum()) > 0
    for b in range(2):
        one = _mvcd2d.batch_tables(V[b : b + 1], edges, tol[b : b + 1])
        for X, got in ((x[b], out), (x[0], shared)):
            ref = _mvcd2d.mvcd2d_triton_batch(X[None], one, 2, block=8)
            for k in range(3):
                _assert_close(got[k][b], ref[k][0])
            assert torch.equal(got[3][b], ref[3][0])
    with pytest.raises(ValueError, match="for tables of 2 polygons"):
        _mvcd2d.mvcd2d_triton_batch(torch.zeros(3, 5, 2, dtype=D64, device=DEVICE), tables, 1)


def test_batched_polygon_derivatives_name_the_element() -> None:
    """Points on a polygon of the batch (not differentiable there) and NaN points are refused,
    naming the element, as the loop names them."""
    V, edges = _polygons(3)
    cage = torchcage.Cage(V.to(DEVICE), edges.to(DEVICE))
    pts = torch.stack([_off_polygon_points(V[b], seed=b)[:6] for b in range(3)]).to(DEVICE)
    on = pts.clone()
    on[2, 4] = V[2, 3].to(DEVICE)
    with pytest.raises(torchcage.PointsError, match=r"points \[4\] in batch element \(2,\) lie on the cage"):
        F.mean_value_derivatives(on, cage, backend="triton")
    bad = pts.clone()
    bad[1, 0, 0] = float("nan")
    with pytest.raises(torchcage.PointsError, match=r"batch element \(1,\)"):
        F.mean_value_derivatives(bad, cage, backend="triton")


# ------------------------------------------------------------------------ quad mean value coordinates
def _triquads(B: int, shift: float = 0.0) -> torchcage.Cage:
    """``B`` jittered, scaled copies (float64, on the device) of the cube with one face split into
    two triangles (5 quads, 2 triangles: small, the interpreter runs a quad at a time); ``shift``
    moves the last one that far from the origin."""
    cube = torchcage.load_cage(torchcage.data.path("cube.obj")).to(D64)
    q = cube.quads
    faces = [q[0, [0, 1, 2]].tolist(), q[0, [0, 2, 3]].tolist(), *q[1:].tolist()]
    g = torch.Generator().manual_seed(5)
    V = cube.vertices * (1 + 0.2 * torch.rand(B, 1, 1, generator=g, dtype=D64))
    V = V + 0.02 * torch.randn(B, *cube.vertices.shape, generator=g, dtype=D64)
    V[-1] += shift
    return torchcage.Cage(V.to(DEVICE), faces)


def _quad_points(V: torch.Tensor, cage: torchcage.Cage, seed: int) -> torch.Tensor:
    """Points for the triquad cage ``V`` ``(V, 3)``: inside, on a vertex, on a quad's middle and a
    triangle's, just off them, outside, far (1e4) and very far (1e7: the first-moment normaliser)."""
    g = torch.Generator().manual_seed(seed)
    c = V.mean(0)
    d = torch.nn.functional.normalize(torch.randn(8, 3, generator=g, dtype=D64), dim=1)
    quad = V[cage.quads[3].cpu()].mean(0)
    tri = V[cage.triangles[1].cpu()].mean(0)
    return torch.cat([c + 0.3 * d[:4], V[:1], quad[None], tri[None], quad[None] * (1 + 1e-9), c + 3 * d[4:6],
                      c + 1e4 * d[6:7], c + 1e7 * d[7:8]])  # fmt: skip


def test_batched_quad_mean_value_launches_equal_the_loop(monkeypatch: pytest.MonkeyPatch) -> None:
    """Quad mean value coordinates of three triquad cages (the last 1e3 from the origin), points
    one set per cage and shared: one launch of the triangle kernel and one of the quad kernel for
    the batch, element by element the single-cage Triton call; rows sum to one and reproduce the
    points near the cages."""
    from torchcage.families.quad_mean_value.triton import qmvc3d as _qmvc3d

    cage = _triquads(3, shift=1e3)
    V = cage.vertices.cpu()
    per = torch.stack([_quad_points(V[b], cage, seed=b) for b in range(3)]).to(DEVICE)
    quads = _Launches(monkeypatch, _qmvc3d, "qmvc3d_triton")
    tris = _Launches(monkeypatch, _mvc3d, "mvc3d_triton")
    for pts in (per, per[0]):
        quads.batches.clear()
        tris.batches.clear()
        out = F.quad_mean_value_coordinates(pts, cage, n=2, backend="triton")
        assert quads.batches == [3] and tris.batches == [3]  # one launch each for the whole batch
        ref = torch.stack(
            [F.quad_mean_value_coordinates(pts if pts.ndim == 2 else pts[b], cage[b], n=2, backend="triton")
             for b in range(3)]
        )  # fmt: skip
        _assert_close(out, ref)
        W, X = out.cpu(), (pts if pts.ndim == 3 else pts.expand(3, -1, -1)).cpu()
        near = (X - V.mean(1, keepdim=True)).norm(dim=-1) < 10
        assert bool(((W.sum(-1) - 1).abs() <= 1e-12 * W.abs().sum(-1).clamp_min(1.0)).all())
        assert float((W @ V - X).norm(dim=-1)[near].max()) < 1e-9 * (1 + V.abs().max())


def test_batched_quad_kernel_blocks_and_point_batches() -> None:
    """The quad kernel with small blocks (programs per cage, the last partial) against each cage's
    own tables, points one set per cage and shared, rows on a quad included (flag 1); a point
    batch that is neither 1 nor the cages' is refused."""
    from torchcage.families.quad_mean_value.triton import qmvc3d as _qmvc3d

    cage = _triquads(2, shift=5.0)
    V = cage.vertices
    x = torch.stack([_quad_points(V[b].cpu(), cage, seed=7 + b) for b in range(2)]).to(DEVICE)  # (2, 13, 3)
    tol = torch.full((2,), 1e-12, dtype=D64)
    tables = _qmvc3d.batch_tables(V, cage.quads, tol, 2)
    for X in (x, x[:1]):
        W = torch.zeros(2, x.shape[1], V.shape[1], dtype=D64, device=DEVICE)
        f = torch.zeros(2, x.shape[1], dtype=torch.int32, device=DEVICE)
        _qmvc3d.qmvc3d_triton(X, tables, W, f, block=8)
        assert int((f == 1).sum()) > 0 and int((f == 0).sum()) > 0
        for b in range(2):
            one = _qmvc3d.batch_tables(V[b : b + 1], cage.quads, tol[b : b + 1], 2)
            Wr = torch.zeros(x.shape[1], V.shape[1], dtype=D64, device=DEVICE)
            fr = torch.zeros(x.shape[1], dtype=torch.int32, device=DEVICE)
            _qmvc3d.qmvc3d_triton(X[b if X.shape[0] > 1 else 0], one, Wr, fr, block=8)
            _assert_close(W[b], Wr)
            assert torch.equal(f[b], fr)
    with pytest.raises(ValueError, match="for tables of 2 cages"):
        _qmvc3d.qmvc3d_triton(torch.zeros(3, 5, 3, dtype=D64, device=DEVICE), tables, W, f)


def test_batched_quad_mean_value_thin_triangles_and_errors() -> None:
    """A batch of triangle-only cages (the sliver cube and a stretched copy) through quad mean value
    coordinates: the points that see the sliver from a few widths are redone by the torch kernel,
    per cage, as one cage; NaN points are refused naming the element."""
    cage, x = _sliver_batch()
    out = F.quad_mean_value_coordinates(x, cage, backend="triton")
    for b in range(2):
        ref = F.quad_mean_value_coordinates(x.cpu(), cage[b].to("cpu"), backend="torch")
        assert float(((out[b].cpu() - ref).abs() / ref.abs().clamp_min(1.0)).max()) < 1e-10
    bad = torch.stack([x, x]).clone()
    bad[1, 3, 0] = float("nan")
    with pytest.raises(torchcage.PointsError, match=r"batch element \(1,\)"):
        F.quad_mean_value_coordinates(bad, cage, backend="triton")


# ---------------------------------------------------------------------- 3D mean value derivatives
def _off_cage_points(V: torch.Tensor, tri: torch.Tensor, seed: int) -> torch.Tensor:
    """:func:`_points` off the cage (the derivatives refuse points on it), with an outside and a far
    point (the first-moment normaliser)."""
    x = _points(V, tri, seed)
    c = V.mean(0)
    return torch.cat([x[:8], x[23:], c + torch.tensor([[3.0, 0.5, 0.2], [2e4, 1e4, -3e4]], dtype=D64)])


@pytest.mark.parametrize("order", [1, 2])
def test_batched_3d_derivatives_in_one_launch_equal_the_loop(order: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Gradients and Hessians of 3D mean value coordinates of three cages (the last 1e3 from the
    origin), points one set per cage and shared (inside, near faces on both sides, outside, far):
    one launch per chunk for the batch (``mvcd3d_triton_batch``), element by element the
    single-cage Triton call, and linear precision near the cages."""
    from torchcage.families.mean_value.triton import mvcd3d as _mvcd3d

    V, tri = _cages(3, shift=1e3)
    cage = torchcage.Cage(V.to(DEVICE), tri.to(DEVICE))
    per = torch.stack([_off_cage_points(V[b], tri, seed=b) for b in range(3)]).to(DEVICE)
    launches = _Launches(monkeypatch, _mvcd3d, "mvcd3d_triton_batch")
    for pts in (per, per[0]):
        launches.batches.clear()
        out = F.mean_value_derivatives(pts, cage, order, backend="triton")
        assert launches.batches == [3]  # one launch for the whole batch
        refs = [F.mean_value_derivatives(pts if pts.ndim == 2 else pts[b], cage[b], order, backend="triton")
                for b in range(3)]  # fmt: skip
        for k in range(3 if order == 2 else 2):
            _assert_close(out[k], torch.stack([r[k] for r in refs]))
        X = (pts if pts.ndim == 3 else pts.expand(3, -1, -1)).cpu()
        near = (X - V.mean(1, keepdim=True)).norm(dim=-1) < 10
        Vc = V - V.mean(1, keepdim=True)
        G = torch.einsum("bnvc,bvd->bncd", out[1].cpu(), Vc)
        assert float((G - torch.eye(3, dtype=D64))[near].abs().max()) < 1e-8
        if order == 2:
            H = torch.einsum("bnvcd,bve->bncde", out[2].cpu(), Vc)
            assert float(H[near].abs().max()) < 1e-7


def test_batched_3d_derivative_kernel_blocks_point_batches_and_redo(monkeypatch: pytest.MonkeyPatch) -> None:
    """The 3D derivative kernel with small blocks against each cage's own tables, points one set per
    cage and shared; the sliver cube's batch: points the kernel flags (next to the thin face) are
    redone by the torch kernel's derivatives per cage, as one cage; a point batch that is neither 1
    nor the cages' is refused."""
    from torchcage.families.mean_value.triton import mvcd3d as _mvcd3d

    V, tri = _cages(2, shift=5.0)
    V, tri = V.to(DEVICE), tri.to(DEVICE)
    x = torch.stack([_off_cage_points(V[b].cpu(), tri.cpu(), seed=4 + b)[:13] for b in range(2)]).to(DEVICE)
    tol = torch.full((2,), 1e-13, dtype=D64)
    cages = [torchcage.Cage(V[b], tri) for b in range(2)]
    tables = _mvcd3d.batch_tables(V, tri, tol)
    for X in (x, x[:1]):
        out = _mvcd3d.mvcd3d_triton_batch(X, tables, 2, cages, block=8)
        for b in range(2):
            one = _mvcd3d.batch_tables(V[b : b + 1], tri, tol[b : b + 1])
            ref = _mvcd3d.mvcd3d_triton_batch(X[b if X.shape[0] > 1 else 0][None], one, 2, cages[b : b + 1], block=8)
            for k in range(3):
                _assert_close(out[k][b], ref[k][0])
            assert torch.equal(out[3][b], ref[3][0])
    with pytest.raises(ValueError, match="for tables of 2 cages"):
        _mvcd3d.mvcd3d_triton_batch(torch.zeros(3, 5, 3, dtype=D64, device=DEVICE), tables, 1, cages)
    sliver, xs = _sliver_batch()
    xs = xs[:20]  # (inside the box: off the cage)
    redone, real = [], _mvcd3d.torch_derivatives
    monkeypatch.setattr(_mvcd3d, "torch_derivatives", lambda y, c, o: redone.append(y.shape[0]) or real(y, c, o))
    out = F.mean_value_derivatives(xs, sliver, 2, backend="triton")
    assert len(redone) == 2 and min(redone) > 0  # (each cage redoes its points next to the sliver)
    for b in range(2):
        ref = F.mean_value_derivatives(xs.cpu(), sliver[b].to("cpu"), 2, backend="torch")
        for k in range(3):
            assert float(((out[k][b].cpu() - ref[k]).abs() / ref[k].abs().clamp_min(1.0)).max()) < 1e-7


def test_batched_3d_derivatives_name_the_element() -> None:
    V, tri = _cages(3)
    cage = torchcage.Cage(V.to(DEVICE), tri.to(DEVICE))
    pts = torch.stack([_off_cage_points(V[b], tri, seed=b)[:6] for b in range(3)]).to(DEVICE)
    on = pts.clone()
    on[2, 4] = V[2, 3].to(DEVICE)
    with pytest.raises(torchcage.PointsError, match=r"points \[4\] in batch element \(2,\) lie on the cage"):
        F.mean_value_derivatives(on, cage, backend="triton")
