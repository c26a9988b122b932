"""A batch of polygons with one topology in one native call: 2D mean value coordinates and their
analytic derivatives equal the loop over the polygons to rounding, equal the torch kernel, and keep
their properties (partition of unity, linear precision, zero-sum gradients)."""

from __future__ import annotations

import math

import pytest
import torch
from support import CountNativeCalls, assert_same_to_rounding

import torchcage
from torchcage import functional as F
from torchcage._core.batch import over_cage_batch
from torchcage.backends import native as _native
from torchcage.families.mean_value import derivatives_native as _mvcd_native
from torchcage.families.mean_value import native2d as _mvc2d_native

D64 = torch.float64
V_COUNT = 24


def _polygons(B: int, seed: int = 0, shift: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """``(B, 24, 2)`` jittered star-shaped polygons (float64, counter-clockwise) and their edges;
    ``shift`` moves the last one that far from the origin."""
    g = torch.Generator().manual_seed(seed)
    angle = torch.arange(V_COUNT, dtype=D64) * (2 * math.pi / V_COUNT)
    radius = 1 + 0.25 * torch.rand(B, V_COUNT, generator=g, dtype=D64)
    V = radius[..., None] * torch.stack([angle.cos(), angle.sin()], dim=-1)
    V[-1] += shift
    edges = torch.stack([torch.arange(V_COUNT), torch.arange(V_COUNT).roll(-1)], dim=1)
    return V, edges


def _points(V: torch.Tensor, seed: int = 1, on: bool = True) -> torch.Tensor:
    """``(N, 2)`` points for the polygon ``V`` ``(24, 2)``: inside, (with ``on``) on vertices and
    edges, just off the edges on both sides, outside, far and very far."""
    g = torch.Generator().manual_seed(seed)
    c = V.mean(0)
    a, b = V, V.roll(-1, 0)
    t = torch.rand(V_COUNT, 1, generator=g, dtype=D64)
    on_edge = a + t * (b - a)
    e = b - a
    normal = torch.stack([e[:, 1], -e[:, 0]], dim=1) / e.norm(dim=1, keepdim=True)  # (outward)
    d = torch.randn(40, 2, generator=g, dtype=D64)
    d = d / d.norm(dim=1, keepdim=True)
    parts = [c + 0.7 * torch.rand(50, 1, generator=g, dtype=D64) * torch.cat([d, d[:10]])]  # inside
    if on:
        parts += [V[:8], on_edge[:8]]
    parts += [
        on_edge[8:16] + 1e-9 * normal[8:16],  # just outside
        on_edge[16:] - 1e-7 * normal[16:],  # just inside
        c + (2 + 3 * torch.rand(20, 1, generator=g, dtype=D64)) * d[:20],  # outside
        c + 1e4 * d[20:30],  # far
        c + 1e7 * d[30:35],  # very far (the first-moment normaliser)
    ]
    return torch.cat(parts)


def _cases(B: int, shift: float, dtype: torch.dtype, on: bool = True):
    V, edges = _polygons(B, shift=shift)
    cage = torchcage.Cage(V.to(dtype), edges)
    per_cage = torch.stack([_points(V[b], seed=b, on=on) for b in range(B)]).to(dtype)  # (B, N, 2)
    return V, edges, cage, per_cage


@pytest.mark.native
@pytest.mark.parametrize("dtype", [torch.float32, D64])
@pytest.mark.parametrize("B", [1, 3])
@pytest.mark.parametrize("shift", [0.0, 1e3])
def test_batched_coordinates_equal_the_loop(dtype, B, shift, monkeypatch):
    V, edges, cage, per_cage = _cases(B, shift, dtype)
    count = CountNativeCalls(monkeypatch, "tc_mvc2d")
    for pts in (per_cage, per_cage[0]):  # one set per polygon; one set shared by all
        count.batches.clear()
        out = F.mean_value_coordinates(pts, cage)
        assert count.batches == [B]  # the whole batch in one native call
        ref = torch.stack([F.mean_value_coordinates(pts if pts.ndim == 2 else pts[b], cage[b]) for b in range(B)])
        assert_same_to_rounding(out, ref)
        assert_same_to_rounding(out, over_cage_batch(F.mean_value_coordinates, pts, cage))
    # the coordinates themselves: rows sum to one, reproduce the points, agree with the torch kernel
    W = F.mean_value_coordinates(per_cage.double(), torchcage.Cage(V, edges))
    near = (per_cage.double() - V.mean(1, keepdim=True)).norm(dim=-1) < 10
    assert (W.sum(-1) - 1).abs().max() < 1e-9
    assert ((W @ V - per_cage.double()).norm(dim=-1)[near]).max() < 1e-9 * (1 + shift)
    Wt = F.mean_value_coordinates(per_cage.double(), torchcage.Cage(V, edges), backend="torch")
    assert (W - Wt)[near].abs().max() < 1e-9


@pytest.mark.native
def test_two_batch_dimensions_chunks_and_broadcast_points(monkeypatch):
    V, edges = _polygons(6, seed=3)
    cage = torchcage.Cage(V.reshape(2, 3, V_COUNT, 2), edges)
    pts = torch.stack([_points(V[b], seed=b) for b in range(6)]).reshape(2, 3, -1, 2)
    N = pts.shape[-2]
    count = CountNativeCalls(monkeypatch, "tc_mvc2d")
    out = F.mean_value_coordinates(pts, cage, chunk_size=40)
    assert out.shape == (2, 3, N, V_COUNT) and count.batches == [6] * -(-N // 40)  # one call per chunk
    shared = F.mean_value_coordinates(pts[0], cage)  # points (3, N, 2) broadcast against polygons (2, 3)
    for i in range(2):
        for j in range(3):
            assert_same_to_rounding(out[i, j], F.mean_value_coordinates(pts[i, j], cage[i, j]))
            assert_same_to_rounding(shared[i, j], F.mean_value_coordinates(pts[0, j], cage[i, j]))


@pytest.mark.native
def test_points_on_the_polygon_interpolate():
    V, edges = _polygons(3)
    pts = torch.stack([0.3 * V[b, 4] + 0.7 * V[b, 5] for b in range(3)])[:, None]  # (3, 1, 2) on edge 4
    W = F.mean_value_coordinates(pts, torchcage.Cage(V, edges))
    expect = torch.zeros(V_COUNT, dtype=D64)
    expect[4], expect[5] = 0.3, 0.7
    assert (W[:, 0] - expect).abs().max() < 1e-12


@pytest.mark.native
def test_the_kernels_refuse_a_point_batch_that_is_neither_one_nor_the_polygons():
    V, edges = _polygons(3)
    tol = torch.full((3,), 1e-12, dtype=D64)
    X = torch.zeros(2, 5, 2, dtype=D64)
    with pytest.raises(ValueError, match="points for 2 polygons"):
        _mvc2d_native.native_chunk(X, _mvc2d_native.batch_tables(V, edges, tol), _native.library(),
                                   torch.empty(3, 5, V_COUNT, dtype=D64))  # fmt: skip
    out = [torch.empty(3, 5, V_COUNT, dtype=D64), torch.empty(3, 5, V_COUNT, 2, dtype=D64), None,
           torch.empty(3, 5, dtype=torch.uint8)]  # fmt: skip
    with pytest.raises(ValueError, match="points for 2 cages"):
        _mvcd_native.native_chunk(X, _mvcd_native.polygon_tables(V, edges, tol), _native.library(), 1, *out)


@pytest.mark.native
def test_the_kernel_flags_rows_that_are_not_finite():
    V, edges = _polygons(2)
    tables = _mvc2d_native.batch_tables(V, edges, torch.full((2,), 1e-12, dtype=D64))
    X = torch.stack([_points(V[b], seed=b)[:58] for b in range(2)])  # inside (50), then vertices
    X[1, 3] = float("nan")  # (no public path passes such a point: it only makes a row that is not finite)
    W = torch.empty(2, 58, V_COUNT, dtype=D64)
    flags = _mvc2d_native.native_chunk(X, tables, _native.library(), W)
    assert flags[1, 3] == 2 and (flags[0, :50] == 0).all() and (flags[0, 50:] == 1).all()
    assert torch.isfinite(W.sum(-1)).logical_xor(flags == 2).all()


@pytest.mark.native
def test_undefined_points_are_named_by_element(monkeypatch):
    V, edges = _polygons(3)
    real = _mvc2d_native.native_chunk

    def chunk(x, tables, lib, W):
        flags = real(x, tables, lib, W)
        flags[1, 4] = 2  # as the kernel marks a row whose total weight vanishes
        return flags

    monkeypatch.setattr(_mvc2d_native, "native_chunk", chunk)
    with pytest.raises(torchcage.PointsError, match=r"undefined at points \[4\] in batch element \(1,\)"):
        F.mean_value_coordinates(torch.zeros(5, 2, dtype=D64), torchcage.Cage(V, edges))


def test_points_with_nan_are_named_by_element():
    V, edges = _polygons(3)
    x = torch.zeros(3, 5, 2, dtype=D64)
    x[1, 4, 0] = float("nan")
    for fn in (F.mean_value_coordinates, F.mean_value_derivatives):
        with pytest.raises(torchcage.PointsError, match=r"indices \[4\].*batch element \(1,\)"):
            fn(x, torchcage.Cage(V, edges))


# ----------------------------------------------------------------------------------- derivatives


@pytest.mark.native
@pytest.mark.parametrize("dtype", [torch.float32, D64])
@pytest.mark.parametrize("B", [1, 3])
@pytest.mark.parametrize("shift", [0.0, 1e3])
@pytest.mark.parametrize("order", [1, 2])
def test_batched_derivatives_equal_the_loop(dtype, B, shift, order, monkeypatch):
    V, edges, cage, per_cage = _cases(B, shift, dtype, on=False)
    count = CountNativeCalls(monkeypatch, "tc_mvcd2d")
    for pts in (per_cage, per_cage[0]):
        count.batches.clear()
        out = F.mean_value_derivatives(pts, cage, order=order)
        assert count.batches == [B]  # the whole batch in one native call
        refs = [F.mean_value_derivatives(pts if pts.ndim == 2 else pts[b], cage[b], order=order) for b in range(B)]
        for k in range(2 if order == 1 else 3):
            assert_same_to_rounding(out[k], torch.stack([r[k] for r in refs]))
        assert (out[2] is None) == (order == 1)
    # the derivatives themselves: zero sum over the vertices, linear precision (sum_v grad_v V_v^T = I,
    # sum_v hess_v V_v = 0), and the torch kernel's autograd derivatives
    cage64 = torchcage.Cage(V, edges)
    _, grad, hess = F.mean_value_derivatives(per_cage.double(), cage64, order=order)
    near = (per_cage.double() - V.mean(1, keepdim=True)).norm(dim=-1) < 10
    eye = torch.einsum("bnvc,bvd->bncd", grad, V)[near]
    assert (eye - torch.eye(2, dtype=D64)).abs().max() < 1e-8 * (1 + shift)
    assert grad.sum(2)[near].abs().max() < 1e-10
    _, grad_t, hess_t = F.mean_value_derivatives(per_cage.double(), cage64, order=order, backend="torch")
    inside = (per_cage.double() - V.mean(1, keepdim=True)).norm(dim=-1) < 3
    scale = grad_t[inside].abs().amax(dim=(-1, -2), keepdim=True).clamp_min(1.0)
    assert ((grad - grad_t)[inside] / scale).abs().max() < 1e-7
    if order == 2:
        assert torch.einsum("bnvcd,bve->bnecd", hess, V)[near].abs().max() < 1e-6 * (1 + shift)
        scale = hess_t[inside].abs().amax(dim=(-1, -2, -3), keepdim=True).clamp_min(1.0)
        assert ((hess - hess_t)[inside] / scale).abs().max() < 1e-6


@pytest.mark.native
def test_batched_derivatives_two_batch_dimensions_and_chunks(monkeypatch):
    V, edges = _polygons(6, seed=3)
    cage = torchcage.Cage(V.reshape(2, 3, V_COUNT, 2), edges)
    pts = torch.stack([_points(V[b], seed=b, on=False) for b in range(6)]).reshape(2, 3, -1, 2)
    count = CountNativeCalls(monkeypatch, "tc_mvcd2d")
    lam, grad, hess = F.mean_value_derivatives(pts, cage, chunk_size=40)
    N = pts.shape[-2]
    assert hess.shape == (2, 3, N, V_COUNT, 2, 2) and count.batches == [6] * -(-N // 40)
    for i in range(2):
        for j in range(3):
            ref = F.mean_value_derivatives(pts[i, j], cage[i, j])
            for k in range(3):
                assert_same_to_rounding((lam, grad, hess)[k][i, j], ref[k])


@pytest.mark.native
def test_batched_derivatives_name_the_element_of_a_point_on_the_polygon():
    V, edges = _polygons(3)
    x = torch.zeros(3, 4, 2, dtype=D64)
    x[2, 1] = 0.5 * (V[2, 6] + V[2, 7])  # on an edge of polygon 2: not differentiable there
    with pytest.raises(torchcage.PointsError, match=r"points \[1\] in batch element \(2,\) lie on the cage"):
        F.mean_value_derivatives(x, torchcage.Cage(V, edges))


# ----------------------------------------------------------------------------------- Green


def _normals(V: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Outward unit normals ``(..., E, 2)`` of counter-clockwise polygons ``V`` ``(..., V, 2)``."""
    e = V[..., edges[:, 1], :] - V[..., edges[:, 0], :]
    return torch.stack([e[..., 1], -e[..., 0]], dim=-1) / e.norm(dim=-1, keepdim=True)


class CountGreenCalls:
    """Counts the calls of the batched 2D Green kernel, with their batch sizes."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        from torchcage.families.green import batch2d

        self.batches: list[int] = []
        real = batch2d.green2d_batch

        def kernel(points, vertices, edges, tol):
            self.batches.append(vertices.shape[0])
            return real(points, vertices, edges, tol)

        monkeypatch.setattr(batch2d, "green2d_batch", kernel)


@pytest.mark.parametrize("dtype", [torch.float32, D64])
@pytest.mark.parametrize("B", [1, 3])
@pytest.mark.parametrize("shift", [0.0, 1e3])
@pytest.mark.parametrize("exterior", ["extend", "none"])
def test_batched_green_equals_the_loop(dtype, B, shift, exterior, monkeypatch):
    V, edges, cage, per_cage = _cases(B, shift, dtype)
    count = CountGreenCalls(monkeypatch)
    for pts in (per_cage, per_cage[0]):
        count.batches.clear()
        phi, psi = F.green_coordinates(pts, cage, exterior=exterior)
        assert count.batches == [B]  # the whole batch in one kernel call
        refs = [F.green_coordinates(pts if pts.ndim == 2 else pts[b], cage[b], exterior=exterior) for b in range(B)]
        assert_same_to_rounding(phi, torch.stack([r[0] for r in refs]))
        assert_same_to_rounding(psi, torch.stack([r[1] for r in refs]))
    # the coordinates themselves: phi @ V + psi @ N reproduces the points inside (and outside, extended)
    phi, psi = F.green_coordinates(per_cage.double(), torchcage.Cage(V, edges), exterior=exterior)
    rebuilt = phi @ V + psi @ _normals(V, edges)
    dist = (per_cage.double() - V.mean(1, keepdim=True)).norm(dim=-1)
    keep = dist < (10 if exterior == "extend" else 0.7)
    assert (rebuilt - per_cage.double()).norm(dim=-1)[keep].max() < 1e-9 * (1 + shift)


def test_batched_green_two_batch_dimensions_chunks_and_broadcast_points(monkeypatch):
    V, edges = _polygons(6, seed=3)
    cage = torchcage.Cage(V.reshape(2, 3, V_COUNT, 2), edges)
    pts = torch.stack([_points(V[b], seed=b) for b in range(6)]).reshape(2, 3, -1, 2)
    N = pts.shape[-2]
    count = CountGreenCalls(monkeypatch)
    phi, psi = F.green_coordinates(pts, cage, chunk_size=40)
    assert phi.shape == (2, 3, N, V_COUNT) and psi.shape == (2, 3, N, V_COUNT)
    assert count.batches == [6] * -(-N // 40)  # one call per chunk
    shared = F.green_coordinates(pts[0], cage)  # points (3, N, 2) broadcast against polygons (2, 3)
    for i in range(2):
        for j in range(3):
            for k, ref in enumerate(F.green_coordinates(pts[i, j], cage[i, j])):
                assert_same_to_rounding((phi, psi)[k][i, j], ref)
            for k, ref in enumerate(F.green_coordinates(pts[0, j], cage[i, j])):
                assert_same_to_rounding(shared[k][i, j], ref)


def test_batched_green_with_a_graph_equals_the_loop():
    """With an autograd graph the batch goes element by element (the analytic Function): the same
    values and gradients as the loop."""
    V, edges = _polygons(3)
    pts = torch.stack([_points(V[b], seed=b, on=False)[:50] for b in range(3)])  # inside
    cot = torch.randn(3, 50, 2 * V_COUNT, generator=torch.Generator().manual_seed(5), dtype=D64)
    grads = []
    for batched in (True, False):
        VV, xx = V.clone().requires_grad_(), pts.clone().requires_grad_()
        cage = torchcage.Cage(VV, edges)
        out = F.green_coordinates(xx, cage) if batched else over_cage_batch(F.green_coordinates, xx, cage)
        (torch.cat(out, dim=-1) * cot).sum().backward()
        grads.append((xx.grad, VV.grad))
    for g, h in zip(*grads, strict=True):
        assert_same_to_rounding(g, h)


def test_batched_green_errors_are_those_of_the_loop():
    V, edges = _polygons(3)
    x = torch.zeros(3, 5, 2, dtype=D64)
    x[2, 1, 1] = float("inf")
    with pytest.raises(torchcage.PointsError, match=r"indices \[1\].*batch element \(2,\)"):
        F.green_coordinates(x, torchcage.Cage(V, edges))
    with pytest.raises(ValueError, match="backend='native' for Green coordinates serves 3D points"):
        F.green_coordinates(x[:, :0], torchcage.Cage(V, edges), backend="native")
