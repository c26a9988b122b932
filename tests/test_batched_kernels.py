"""Batched rest cages as one native kernel call: mean value and Green coordinates of a batch of 3D
triangle cages with one topology, and the mean value derivatives, agree with the loop of single-cage
calls (the same tables, the same kernel), for points inside, outside, on faces, edges and vertices
and far away, and the batch's errors name the element."""

from __future__ import annotations

import pytest
import torch
from support import CountNativeCalls, assert_same_to_rounding, cube

import torchcage
from torchcage import functional as F
from torchcage._core.batch import over_cage_batch
from torchcage.backends import native as _native
from torchcage.families.mean_value import native3d as _mvc3d_native
from torchcage.testing import icosphere

D64 = torch.float64


def _cages(B: int, seed: int = 0, shift: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """``(B, 42, 3)`` jittered, scaled icospheres (float64) and their triangles; ``shift`` moves
    the last cage that far from the origin (its coordinates are then computed relative to its
    centre)."""
    ico = icosphere()
    g = torch.Generator().manual_seed(seed)
    V = ico.vertices * (1 + 0.3 * torch.rand(B, 1, 1, generator=g, dtype=D64))
    V = V + 0.03 * torch.randn(B, 42, 3, generator=g, dtype=D64)
    V[-1] += shift
    return V, ico.triangles


def _points(V: torch.Tensor, tri: torch.Tensor, seed: int = 1) -> torch.Tensor:
    """``(N, 3)`` points of every kind for the cage ``V`` ``(42, 3)``: inside, on vertices, on edge
    midpoints, on faces (barycentric), just off faces on both sides, outside, and far away."""
    g = torch.Generator().manual_seed(seed)
    c = V.mean(0)
    p = V[tri]
    bary = torch.rand(tri.shape[0], 3, generator=g, dtype=D64)
    bary = bary / bary.sum(1, keepdim=True)
    on_face = (bary[:, :, None] * p).sum(1)
    nrm = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    nrm = nrm / nrm.norm(dim=-1, keepdim=True)
    d = torch.randn(60, 3, generator=g, dtype=D64)
    d = d / d.norm(dim=1, keepdim=True)
    return torch.cat(
        [
            c + 0.8 * torch.rand(60, 1, generator=g, dtype=D64) * d,  # inside
            V[:12],  # on vertices
            0.5 * (p[:12, 0] + p[:12, 1]),  # on edges
            on_face[:20],  # on faces
            on_face[20:40] + 1e-9 * nrm[20:40],  # just outside the faces
            on_face[40:60] - 1e-7 * nrm[40:60],  # just inside
            c + (2 + 3 * torch.rand(30, 1, generator=g, dtype=D64)) * d[:30],  # outside
            c + 1e4 * d[30:40],  # far
            c + 1e7 * d[40:45],  # very far (first-moment normaliser)
        ]
    )


@pytest.mark.native
@pytest.mark.parametrize("dtype", [torch.float32, D64])
@pytest.mark.parametrize("B", [1, 3])
@pytest.mark.parametrize("shift", [0.0, 1e3])
def test_batched_call_equals_the_loop(dtype, B, shift, monkeypatch):
    V, tri = _cages(B, shift=shift)
    cage = torchcage.Cage(V.to(dtype), tri)
    per_cage = torch.stack([_points(V[b], tri, seed=b) for b in range(B)]).to(dtype)  # (B, N, 3)
    shared = per_cage[0]  # (N, 3): on cage 0's faces, near the others'
    count = CountNativeCalls(monkeypatch)
    for pts in (per_cage, shared):
        count.batches.clear()
        out = F.mean_value_coordinates(pts, cage)
        assert count.batches == [B]  # the whole batch in one native call
        ref = torch.stack([F.mean_value_coordinates(pts if pts.ndim == 2 else pts[b], cage[b]) for b in range(B)])
        assert_same_to_rounding(out, ref)
        assert_same_to_rounding(out, over_cage_batch(F.mean_value_coordinates, pts, cage))
    # rows sum to one and reproduce the points (the coordinates themselves, not only their agreement)
    W = F.mean_value_coordinates(per_cage.double(), torchcage.Cage(V, tri))
    near = (per_cage.double() - V.mean(1, keepdim=True)).norm(dim=-1) < 10
    assert (W.sum(-1) - 1).abs().max() < 1e-9
    assert ((W @ V - per_cage.double()).norm(dim=-1)[near]).max() < 1e-9 * (1 + shift)


@pytest.mark.native
def test_two_batch_dimensions_and_chunks(monkeypatch):
    V, tri = _cages(6, seed=3)
    cage = torchcage.Cage(V.reshape(2, 3, 42, 3), tri)
    pts = torch.stack([_points(V[b], tri, seed=b) for b in range(6)]).reshape(2, 3, -1, 3)
    count = CountNativeCalls(monkeypatch)
    out = F.mean_value_coordinates(pts, cage, chunk_size=100)
    N = pts.shape[-2]
    assert out.shape == (2, 3, N, 42) and count.batches == [6] * -(-N // 100)  # one call per chunk
    for i in range(2):
        for j in range(3):
            assert_same_to_rounding(out[i, j], F.mean_value_coordinates(pts[i, j], cage[i, j]))
    # points broadcast over the first batch axis: (3, N, 3) against cages (2, 3)
    out = F.mean_value_coordinates(pts[0], cage)
    for i in range(2):
        for j in range(3):
            assert_same_to_rounding(out[i, j], F.mean_value_coordinates(pts[0, j], cage[i, j]))


def test_no_points():
    V, tri = _cages(2)
    cage = torchcage.Cage(V, tri)
    for pts in (torch.zeros(0, 3, dtype=D64), torch.zeros(2, 0, 3, dtype=D64)):
        assert F.mean_value_coordinates(pts, cage).shape == (2, 0, 42)
        assert F.mean_value_coordinates(pts, cage, backend="torch").shape == (2, 0, 42)


def test_a_degenerate_element_is_named():
    V, tri = _cages(4)
    t = tri[7]
    V[2, t[2]] = 0.5 * (V[2, t[0]] + V[2, t[1]])  # triangle 7 of element 2 collapses to a segment
    x = torch.zeros(5, 3, dtype=D64)
    with pytest.raises(torchcage.DegenerateFaceError, match=r"triangles \[7\] in batch element \(2,\)"):
        F.mean_value_coordinates(x, torchcage.Cage(V, tri, validate="topology"))
    with pytest.raises(torchcage.DegenerateFaceError, match=r"in batch element \(1, 0\)"):
        F.mean_value_coordinates(x, torchcage.Cage(V.reshape(2, 2, 42, 3), tri, validate="topology"))


def test_points_with_nan_are_named_by_element():
    V, tri = _cages(3)
    x = torch.zeros(3, 5, 3, dtype=D64)
    x[1, 4, 2] = float("nan")
    with pytest.raises(torchcage.PointsError, match=r"indices \[4\].*batch element \(1,\)"):
        F.mean_value_coordinates(x, torchcage.Cage(V, tri))


@pytest.mark.native
def test_the_kernel_refuses_a_point_batch_that_is_neither_one_nor_the_cages():
    V, tri = _cages(3)
    tables = _mvc3d_native.batch_tables(V, tri, torch.full((3,), 1e-12, dtype=D64))
    W = torch.empty(3, 5, 42, dtype=D64)
    with pytest.raises(ValueError, match="points for 2 cages"):
        _mvc3d_native.native_chunk(torch.zeros(2, 5, 3, dtype=D64), tables, _native.library(), W)


@pytest.mark.native
def test_the_kernel_flags_rows_that_are_not_finite():
    V, tri = _cages(2)
    tables = _mvc3d_native.batch_tables(V, tri, torch.full((2,), 1e-12, dtype=D64))
    X = torch.stack([_points(V[b], tri, seed=b)[:70] for b in range(2)])  # inside (60), then vertices
    X[1, 3] = float("nan")  # (no public path passes such a point: it only makes a row that is not finite)
    W = torch.empty(2, 70, 42, dtype=D64)
    flags = _mvc3d_native.native_chunk(X, tables, _native.library(), W)
    assert flags[1, 3] == 2 and (flags[0, :60] == 0).all() and (flags[0, 60:] == 1).all()
    assert torch.isfinite(W.sum(-1)).logical_xor(flags == 2).all()


@pytest.mark.native
def test_undefined_points_are_named_by_element(monkeypatch):
    V, tri = _cages(3)
    real = _mvc3d_native.native_chunk

    def chunk(x, tables, lib, W, normalize=True):
        flags = real(x, tables, lib, W, normalize)
        flags[1, 4] = 2  # as the kernel marks a row whose total weight vanishes
        return flags

    monkeypatch.setattr(_mvc3d_native, "native_chunk", chunk)
    with pytest.raises(torchcage.PointsError, match=r"undefined at points \[4\] in batch element \(1,\)"):
        F.mean_value_coordinates(torch.zeros(5, 3, dtype=D64), torchcage.Cage(V, tri))


@pytest.mark.native
def test_undefined_points_of_one_cage_are_named_from_the_kernel_flags(monkeypatch):
    """One cage: the rows the native kernel marks not finite (flag 2) are refused by index, with no
    pass of its own over the output."""
    V, tri = _cages(1)
    real = _mvc3d_native.native_chunk

    def chunk(x, tables, lib, W, normalize=True):
        flags = real(x, tables, lib, W, normalize)
        flags[4] = 2  # as the kernel marks a row whose total weight vanishes
        return flags

    monkeypatch.setattr(_mvc3d_native, "native_chunk", chunk)
    with pytest.raises(torchcage.PointsError, match=r"undefined at points \[4\] \(the total weight"):
        F.mean_value_coordinates(torch.zeros(6, 3, dtype=D64), torchcage.Cage(V[0], tri), backend="native")


# ----------------------------------------------------------------------------------- Green


def _near_vertices(V: torch.Tensor, seed: int) -> torch.Tensor:
    """Points a few rounding steps from the first vertices of ``V`` ``(42, 3)``: inside the vertex
    snap's radius (64 on-cage tolerances, about 2.3e-13 of the size) and just outside it."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(16, 3, generator=g, dtype=D64)
    d = d / d.norm(dim=1, keepdim=True)
    scale = float((V.amax(0) - V.amin(0)).norm())
    r = torch.tensor([1e-15, 1e-14, 1e-13, 2e-13, 5e-13, 1e-12, 1e-11, 1e-10] * 2, dtype=D64)[:, None] * scale
    return V[:16] + r * d


@pytest.mark.native
@pytest.mark.parametrize("dtype", [torch.float32, D64])
@pytest.mark.parametrize("B", [1, 3])
@pytest.mark.parametrize("shift", [0.0, 1e3])
@pytest.mark.parametrize("exterior", ["extend", "none"])
def test_batched_green_equals_the_loop(dtype, B, shift, exterior, monkeypatch):
    V, tri = _cages(B, shift=shift)
    cage = torchcage.Cage(V.to(dtype), tri)
    per_cage = torch.stack([torch.cat([_points(V[b], tri, seed=b), _near_vertices(V[b], b)]) for b in range(B)]).to(
        dtype
    )  # (B, N, 3)
    shared = per_cage[0]  # (N, 3): on cage 0's faces, near the others'
    count = CountNativeCalls(monkeypatch, "tc_gc3d_batch")
    for pts in (per_cage, shared):
        count.batches.clear()
        phi, psi = F.green_coordinates(pts, cage, exterior=exterior)
        assert count.batches == [B]  # the whole batch in one native call
        refs = [F.green_coordinates(pts if pts.ndim == 2 else pts[b], cage[b], exterior=exterior) for b in range(B)]
        assert_same_to_rounding(phi, torch.stack([r[0] for r in refs]))
        assert_same_to_rounding(psi, torch.stack([r[1] for r in refs]))
    # the coordinates themselves: phi @ V + psi @ n reproduces the points inside (and, extended,
    # outside), and phi sums to one there
    phi, psi = F.green_coordinates(per_cage.double(), torchcage.Cage(V, tri), exterior=exterior)
    n = torch.stack([torchcage.Cage(V[b], tri).triangle_normals() for b in range(B)])
    inside = torch.zeros(per_cage.shape[:2], dtype=torch.bool)
    inside[:, :60] = True  # (the inside points of _points)
    keep = inside | (exterior == "extend") & ((per_cage.double() - V.mean(1, keepdim=True)).norm(dim=-1) < 10)
    err = (phi @ V + psi @ n - per_cage.double()).norm(dim=-1)
    assert float(err[keep].max()) < 1e-9 * (1 + shift)
    assert float((phi.sum(-1) - 1).abs()[keep].max()) < 1e-9


@pytest.mark.native
def test_batched_green_two_batch_dimensions_and_chunks(monkeypatch):
    V, tri = _cages(6, seed=3)
    cage = torchcage.Cage(V.reshape(2, 3, 42, 3), tri)
    pts = torch.stack([_points(V[b], tri, seed=b) for b in range(6)]).reshape(2, 3, -1, 3)
    count = CountNativeCalls(monkeypatch, "tc_gc3d_batch")
    seen = []
    phi, psi = F.green_coordinates(pts, cage, chunk_size=100, progress=lambda done, total: seen.append(done))
    N = pts.shape[-2]
    assert phi.shape == (2, 3, N, 42) and psi.shape == (2, 3, N, 80)
    assert count.batches == [6] * -(-N // 100) and seen[-1] == N  # one call per chunk, progress to the end
    for i in range(2):
        for j in range(3):
            ref = F.green_coordinates(pts[i, j], cage[i, j])
            assert_same_to_rounding(phi[i, j], ref[0])
            assert_same_to_rounding(psi[i, j], ref[1])
    # points broadcast over the first batch axis: (3, N, 3) against cages (2, 3)
    phi, psi = F.green_coordinates(pts[0], cage)
    for i in range(2):
        for j in range(3):
            assert_same_to_rounding(phi[i, j], F.green_coordinates(pts[0, j], cage[i, j])[0])


def test_batched_green_edge_cases():
    V, tri = _cages(3)
    cage = torchcage.Cage(V, tri)
    # an element without outside points next to ones with them (the exterior continuation skips it)
    pts = torch.stack([_points(V[b], tri, seed=b) for b in range(3)])
    d = pts[1] - V[1].mean(0)
    pts[1] = V[1].mean(0) + 0.5 * d / d.norm(dim=-1, keepdim=True).clamp_min(1)  # (all within half the radius)
    phi, psi = F.green_coordinates(pts, cage)
    for b in range(3):
        ref = F.green_coordinates(pts[b], cage[b])
        assert_same_to_rounding(phi[b], ref[0])
        assert_same_to_rounding(psi[b], ref[1])
    for pts in (torch.zeros(0, 3, dtype=D64), torch.zeros(3, 0, 3, dtype=D64)):
        phi, psi = F.green_coordinates(pts, cage)
        assert phi.shape == (3, 0, 42) and psi.shape == (3, 0, 80)
    x = torch.zeros(3, 5, 3, dtype=D64)
    x[2, 1, 0] = float("inf")
    with pytest.raises(torchcage.PointsError, match=r"indices \[1\].*batch element \(2,\)"):
        F.green_coordinates(x, cage)
    # the torch kernel and a graph keep the loop; the same numbers up to the kernels' agreement
    x = torch.stack([_points(V[b], tri, seed=b)[:60] for b in range(3)])
    phi = F.green_coordinates(x, cage)[0]
    assert torch.allclose(F.green_coordinates(x, cage, backend="torch")[0], phi, atol=1e-10)
    Vg = V.clone().requires_grad_(True)
    phig = F.green_coordinates(x, torchcage.Cage(Vg, tri))[0]
    assert phig.requires_grad and torch.allclose(phig.detach(), phi, atol=1e-10)


def test_snap_of_a_batch_equals_the_snap_of_each_element():
    from torchcage._core.common import snap_to_vertices, snap_to_vertices_batch

    V, _ = _cages(4, seed=5)
    g = torch.Generator().manual_seed(7)
    x = torch.stack(
        [torch.cat([_near_vertices(V[b], b), 0.5 * torch.randn(50, 3, generator=g, dtype=D64)]) for b in range(4)]
    )
    x[1, 3] = V[2, 3]  # another element's vertex: not snapped in element 1
    x[3, 5, 1] = V[3, 9, 1]  # one coordinate of a vertex: passes the first screens only
    radius = torch.tensor([1e-13, 3e-13, 0.0, 1e-12], dtype=D64)
    out = snap_to_vertices_batch(x, V, radius)
    for b in range(4):
        assert torch.equal(out[b], snap_to_vertices(x[b], V[b], float(radius[b])))
    # and against the definition: a point moves iff a vertex is within the radius, onto the nearest
    d = (x[:, :, None] - V[:, None]).norm(dim=-1)  # (B, N, V)
    moved = (out != x).any(-1)
    assert torch.equal(moved, (d.amin(-1) <= radius[:, None]) & (d.amin(-1) > 0))
    assert torch.equal(out[moved], V[torch.nonzero(moved)[:, 0], d.argmin(-1)[moved]])
    assert snap_to_vertices_batch(x, V, torch.zeros(4, dtype=D64)) is x  # nothing snaps: no copy


def test_the_batched_snap_works_in_chunks(monkeypatch):
    from torchcage._core import common
    from torchcage._core.common import snap_to_vertices_batch

    V, _ = _cages(3, seed=8)
    g = torch.Generator().manual_seed(9)
    far = torch.randn(3, 40, 3, generator=g, dtype=D64)
    x = torch.cat([torch.stack([_near_vertices(V[b], b) for b in range(3)]), far], dim=1)
    x[:, 16:, 0] = V[:, :1, 0]  # the random rows share a first coordinate with a vertex: all pass the first screen
    radius = torch.full((3,), 1e-12, dtype=D64)
    whole = snap_to_vertices_batch(x, V, radius)
    monkeypatch.setattr(common, "SNAP_ENTRIES", 100)  # (pairs of about two rows at a time)
    assert torch.equal(snap_to_vertices_batch(x, V, radius), whole)
    assert int((whole != x).any(-1).sum()) >= 6  # (some points snap)


# ------------------------------------------------------------------------- with autograd


def _loss_grads(fn, pts: torch.Tensor, V: torch.Tensor, tri: torch.Tensor, cot: torch.Tensor, wrt: str):
    """The coordinates and the gradients of ``sum(cot * lam)`` with respect to ``wrt`` ("points",
    "vertices" or both, "all")."""
    x = pts.clone().requires_grad_(wrt in ("points", "all"))
    P = V.clone().requires_grad_(wrt in ("vertices", "all"))
    lam = fn(x, torchcage.Cage(P, tri))
    (lam * cot).sum().backward()
    return lam.detach(), x.grad, P.grad


@pytest.mark.native
@pytest.mark.parametrize("dtype", [torch.float32, D64])
@pytest.mark.parametrize("shift", [0.0, 1e3])
@pytest.mark.parametrize("wrt", ["all", "vertices", "points"])
def test_batched_call_with_a_graph_equals_the_loop(dtype, shift, wrt, monkeypatch):
    B = 3
    V, tri = _cages(B, shift=shift)
    per_cage = torch.stack([_points(V[b], tri, seed=b) for b in range(B)])  # on faces, edges, vertices ...
    count = CountNativeCalls(monkeypatch)
    vjp = CountNativeCalls(monkeypatch, "tc_mvc3d_vjp_batch")
    for pts in (per_cage, per_cage[0]):
        cot = torch.randn(B, pts.shape[-2], 42, generator=torch.Generator().manual_seed(2), dtype=D64).to(dtype)
        count.batches.clear(), vjp.batches.clear()
        lam, gx, gP = _loss_grads(F.mean_value_coordinates, pts.to(dtype), V.to(dtype), tri, cot, wrt)
        # the values of the whole batch in one native call, and their products in one more (the
        # points alone: element by element, the analytic point gradients)
        assert count.batches == [B]
        assert vjp.batches == ([B] if wrt != "points" else [])
        ref = _loss_grads(
            lambda x, c: over_cage_batch(F.mean_value_coordinates, x, c), pts.to(dtype), V.to(dtype), tri, cot, wrt
        )
        assert_same_to_rounding(lam, ref[0])
        for got, want in zip((gx, gP), ref[1:], strict=True):
            assert (got is None) == (want is None)
            if got is not None:  # (vertex gradients summed in another order: rounding apart)
                assert got.dtype == dtype and bool(torch.isfinite(got).all())
                err = float((got - want).abs().max()) / max(1.0, float(want.abs().max()))
                assert err <= 8 * torch.finfo(dtype).eps, err


@pytest.mark.native
@pytest.mark.parametrize("mixed", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_batched_call_with_a_graph_checks_its_derivatives(mixed):
    ico = cube().triangulated()  # a small cage: gradcheck perturbs every coordinate
    g = torch.Generator().manual_seed(4)
    V = (ico.vertices[None] * (1 + 0.1 * torch.rand(2, 1, 1, generator=g, dtype=D64))).requires_grad_()
    x = (0.4 * (torch.rand(2, 2, 3, generator=g, dtype=D64) - 0.5)).requires_grad_()

    def mvc(points, rest):
        return F.mean_value_coordinates(points, torchcage.Cage(rest, ico.triangles, validate=False))

    assert torch.autograd.gradcheck(mvc, (x, V))
    # double backward (second derivatives with respect to the points) through the batched call
    assert torch.autograd.gradgradcheck(lambda p: mvc(p, V.detach()), (x,))
    if mixed:  # and the mixed ones, with the rest vertices (7 s: the slow tier)
        assert torch.autograd.gradgradcheck(mvc, (x, V))


@pytest.mark.native
def test_batched_call_in_forward_mode_equals_the_loop():
    import torch.autograd.forward_ad as fwAD

    V, tri = _cages(3)
    x = torch.stack([_points(V[b], tri, seed=b)[:60] for b in range(3)])  # (inside points)
    tangent = torch.randn(x.shape, generator=torch.Generator().manual_seed(3), dtype=D64)
    rest = V.clone().requires_grad_()  # (a graph as well: the batched Function, not the values-only call)
    outs = []
    for fn in (F.mean_value_coordinates, lambda p, c: over_cage_batch(F.mean_value_coordinates, p, c)):
        with fwAD.dual_level():
            lam = fn(fwAD.make_dual(x, tangent), torchcage.Cage(rest, tri))
            outs.append(fwAD.unpack_dual(lam).tangent.detach().clone())
    assert_same_to_rounding(outs[0], outs[1])
    # and against finite differences of the coordinates themselves
    h = 1e-6
    fd = (
        F.mean_value_coordinates(x + h * tangent, torchcage.Cage(V, tri))
        - F.mean_value_coordinates(x - h * tangent, torchcage.Cage(V, tri))
    ) / (2 * h)
    assert float((outs[0] - fd).abs().max()) < 1e-7


def _green_loss_grads(fn, pts, V, tri, cots, wrt: str, exterior: str):
    """Green coordinates and the gradients of ``sum(cot_phi * phi) + sum(cot_psi * psi)`` with
    respect to ``wrt`` ("points", "vertices" or both, "all")."""
    x = pts.clone().requires_grad_(wrt in ("points", "all"))
    P = V.clone().requires_grad_(wrt in ("vertices", "all"))
    phi, psi = fn(x, torchcage.Cage(P, tri), exterior=exterior)
    ((phi * cots[0]).sum() + (psi * cots[1]).sum()).backward()
    return phi.detach(), psi.detach(), x.grad, P.grad


@pytest.mark.native
@pytest.mark.parametrize("dtype", [torch.float32, D64])
@pytest.mark.parametrize("shift", [0.0, 1e3])
@pytest.mark.parametrize("wrt", ["all", "vertices", "points"])
@pytest.mark.parametrize("exterior", ["extend", "none"])
def test_batched_green_with_a_graph_equals_the_loop(dtype, shift, wrt, exterior, monkeypatch):
    B = 3
    V, tri = _cages(B, shift=shift)
    per_cage = torch.stack([torch.cat([_points(V[b], tri, seed=b), _near_vertices(V[b], b)]) for b in range(B)])
    values = CountNativeCalls(monkeypatch, "tc_gc3d_batch")
    vjp = CountNativeCalls(monkeypatch, "tc_gc3d_vjp_batch")
    g = torch.Generator().manual_seed(2)
    for pts in (per_cage, per_cage[0]):
        N = pts.shape[-2]
        cots = (
            torch.randn(B, N, 42, generator=g, dtype=D64).to(dtype),
            torch.randn(B, N, 80, generator=g, dtype=D64).to(dtype),
        )
        values.batches.clear(), vjp.batches.clear()
        phi, psi, gx, gP = _green_loss_grads(F.green_coordinates, pts.to(dtype), V.to(dtype), tri, cots, wrt, exterior)
        # the values of the whole batch in one native call, and their products in one more (the
        # points alone: element by element, the closed-form point gradients)
        assert values.batches == [B]
        assert vjp.batches == ([B] if wrt != "points" else [])
        ref = _green_loss_grads(
            lambda x, c, **kw: over_cage_batch(F.green_coordinates, x, c, **kw),
            pts.to(dtype), V.to(dtype), tri, cots, wrt, exterior,
        )  # fmt: skip
        assert_same_to_rounding(phi, ref[0])
        assert_same_to_rounding(psi, ref[1])
        for got, want in zip((gx, gP), ref[2:], strict=True):
            assert (got is None) == (want is None)
            if got is not None:  # (sums over the points in another order: rounding apart)
                assert got.dtype == dtype and bool(torch.isfinite(got).all())
                err = float((got - want).abs().max()) / max(1.0, float(want.abs().max()))
                assert err <= 64 * torch.finfo(dtype).eps, err


@pytest.mark.native
def test_batched_green_with_a_graph_checks_its_derivatives():
    box = cube().triangulated()  # a small cage: gradcheck perturbs every coordinate
    g = torch.Generator().manual_seed(5)
    V = (box.vertices[None] * (1 + 0.1 * torch.rand(2, 1, 1, generator=g, dtype=D64))).requires_grad_()
    x = torch.cat([0.4 * (torch.rand(2, 1, 3, generator=g, dtype=D64) - 0.5), torch.full((2, 1, 3), 3.0, dtype=D64)], 1)
    x.requires_grad_()  # a point inside each cage, one outside (the extension)

    def green(points, rest):
        return F.green_coordinates(points, torchcage.Cage(rest, box.triangles, validate=False))

    assert torch.autograd.gradcheck(green, (x, V))
    # double backward (second derivatives with respect to the points) through the batched call
    assert torch.autograd.gradgradcheck(lambda p: green(p, V.detach()), (x,))


@pytest.mark.native
@pytest.mark.parametrize("rest_grad", [False, True])
def test_batched_green_in_forward_mode_equals_the_loop(rest_grad):
    import torch.autograd.forward_ad as fwAD

    V, tri = _cages(3)
    x = torch.stack([_points(V[b], tri, seed=b)[:60] for b in range(3)])  # (inside points)
    tangent = torch.randn(x.shape, generator=torch.Generator().manual_seed(3), dtype=D64)
    rest = V.clone().requires_grad_(rest_grad)  # (with a graph too: the batched Function's jvp)
    outs = []
    for fn in (F.green_coordinates, lambda p, c: over_cage_batch(F.green_coordinates, p, c)):
        with fwAD.dual_level():
            phi, psi = fn(fwAD.make_dual(x, tangent), torchcage.Cage(rest, tri))
            outs.append([fwAD.unpack_dual(o).tangent.detach().clone() for o in (phi, psi)])
    for a, b in zip(*outs, strict=True):
        assert_same_to_rounding(a, b)
    # and against central differences of the coordinates themselves
    h = 1e-6
    plus = F.green_coordinates(x + h * tangent, torchcage.Cage(V, tri))
    minus = F.green_coordinates(x - h * tangent, torchcage.Cage(V, tri))
    for tan, p, m in zip(outs[0], plus, minus, strict=True):
        assert float((tan - (p - m) / (2 * h)).abs().max()) < 1e-7


# ----------------------------------------------------------------------- mean value derivatives


def _off_cage(V: torch.Tensor, tri: torch.Tensor, seed: int) -> torch.Tensor:
    """:func:`_points` without those on the cage (vertices, edges, faces): where the coordinates
    are differentiable."""
    p = _points(V, tri, seed)
    return torch.cat([p[:60], p[104:]])


@pytest.mark.native
@pytest.mark.parametrize("dtype", [torch.float32, D64])
@pytest.mark.parametrize("B", [1, 3])
@pytest.mark.parametrize("shift", [0.0, 1e3])
@pytest.mark.parametrize("order", [1, 2])
def test_batched_derivatives_equal_the_loop(dtype, B, shift, order, monkeypatch):
    V, tri = _cages(B, shift=shift)
    cage = torchcage.Cage(V.to(dtype), tri)
    per_cage = torch.stack([_off_cage(V[b], tri, seed=b) for b in range(B)]).to(dtype)
    count = CountNativeCalls(monkeypatch, "tc_mvcd3d")
    for pts in (per_cage, per_cage[0]):  # one set per cage; one set shared (off cage 0, near the others')
        count.batches.clear()
        out = F.mean_value_derivatives(pts, cage, order=order)
        assert count.batches == [B]  # the whole batch in one native call
        refs = [F.mean_value_derivatives(pts if pts.ndim == 2 else pts[b], cage[b], order=order) for b in range(B)]
        for k in range(2 if order == 1 else 3):
            assert_same_to_rounding(out[k], torch.stack([r[k] for r in refs]))
        assert (out[2] is None) == (order == 1)
    # the derivatives themselves: they sum to zero over the vertices and reproduce the identity
    # (gradients of linear precision, sum_v grad_v V_v^T = I) on the points near the cages
    _, grad, hess = F.mean_value_derivatives(per_cage.double(), torchcage.Cage(V, tri), order=order)
    near = (per_cage.double() - V.mean(1, keepdim=True)).norm(dim=-1) < 10
    eye = torch.einsum("bnvc,bvd->bncd", grad, V)[near]
    assert (eye - torch.eye(3, dtype=D64)).abs().max() < 1e-8 * (1 + shift)
    assert grad.sum(2)[near].abs().max() < 1e-10
    if order == 2:
        assert torch.einsum("bnvcd,bve->bnecd", hess, V)[near].abs().max() < 1e-7 * (1 + shift)


@pytest.mark.native
def test_batched_derivatives_two_batch_dimensions_and_chunks(monkeypatch):
    V, tri = _cages(6, seed=3)
    cage = torchcage.Cage(V.reshape(2, 3, 42, 3), tri)
    pts = torch.stack([_off_cage(V[b], tri, seed=b) for b in range(6)]).reshape(2, 3, -1, 3)
    count = CountNativeCalls(monkeypatch, "tc_mvcd3d")
    lam, grad, hess = F.mean_value_derivatives(pts, cage, chunk_size=40)
    N = pts.shape[-2]
    assert hess.shape == (2, 3, N, 42, 3, 3) and count.batches == [6] * -(-N // 40)
    for i in range(2):
        for j in range(3):
            ref = F.mean_value_derivatives(pts[i, j], cage[i, j])
            for k in range(3):
                assert_same_to_rounding((lam, grad, hess)[k][i, j], ref[k])


@pytest.mark.native
def test_batched_derivatives_name_the_element():
    V, tri = _cages(3)
    cage = torchcage.Cage(V, tri)
    x = torch.zeros(3, 4, 3, dtype=D64)
    x[2, 1] = V[2, 5]  # on a vertex of cage 2: not differentiable there
    with pytest.raises(torchcage.PointsError, match=r"points \[1\] in batch element \(2,\) lie on the cage"):
        F.mean_value_derivatives(x, cage)
    x[2, 1] = 0.0
    x[1, 3, 0] = float("inf")
    with pytest.raises(torchcage.PointsError, match=r"indices \[3\].*batch element \(1,\)"):
        F.mean_value_derivatives(x, cage)


@pytest.mark.native
def test_batched_derivatives_undefined_points_are_named_by_element(monkeypatch):
    from torchcage.families.mean_value import derivatives_native

    real = derivatives_native.native_chunk

    def chunk(x, tables, lib, order, lam, grad, hess, on):
        real(x, tables, lib, order, lam, grad, hess, on)
        on[1, 2] = 2  # as the kernel marks a row whose total weight vanishes

    monkeypatch.setattr(derivatives_native, "native_chunk", chunk)
    V, tri = _cages(3)
    with pytest.raises(torchcage.PointsError, match=r"undefined at points \[2\] in batch element \(1,\)"):
        F.mean_value_derivatives(torch.zeros(4, 3, dtype=D64), torchcage.Cage(V, tri))
