"""Batched rest cages of the quad families as one native kernel call per chunk of points: quad mean
value and quad Green coordinates of a batch of quad and triquad cages with one topology equal the
single-cage calls (the same tables, the same kernel) on quads, edges and corners, near them,
outside and far away, for the Riemann sum and the tolerance form, and reproduce the points (linear
precision); the batch's errors name the element."""

from __future__ import annotations

import pytest
import torch
from support import (
    CountNativeCalls,
    assert_same_to_rounding,
    bent_box,
    box_points,
    quad_adversarial_points,
    triquad,
)

import torchcage
from torchcage import functional as F
from torchcage.backends import native as _native

D64 = torch.float64


def _batch(base: torchcage.Cage, B: int, seed: int = 0, shift: float = 0.0) -> torchcage.Cage:
    """``B`` scaled and jittered copies of ``base`` (float64; quads stay valid); ``shift`` moves the
    last one that far from the origin."""
    g = torch.Generator().manual_seed(seed)
    V = base.vertices * (1 + 0.3 * torch.rand(B, 1, 1, generator=g, dtype=D64))
    V = V + 0.02 * torch.randn(B, *base.vertices.shape, generator=g, dtype=D64)
    V[-1] += shift
    return base._like(V)


def _points(cage: torchcage.Cage, seed: int) -> torch.Tensor:
    """``(N, 3)`` points of every kind for one cage: near and on its quads, edges and corners
    (1e-15..1e-3 of the size, both sides), inside its box, and far away (1e4 and 1e7 sizes)."""
    g = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(6, 3, generator=g, dtype=D64), dim=-1)
    c = cage.vertices.mean(0)
    far = torch.cat([c + 1e4 * cage.scale * d[:3], c + 1e7 * cage.scale * d[3:]])
    return torch.cat([quad_adversarial_points(cage, seed), box_points(cage, 40, seed=seed), far])


QMVC_CASES = [("quads", None), ("triquad", None), ("triquad", 1e-8)]


@pytest.mark.native
@pytest.mark.parametrize("dtype", [torch.float32, D64])
@pytest.mark.parametrize("B", [1, 3])
@pytest.mark.parametrize("shift", [0.0, 1e3])
@pytest.mark.parametrize("faces, tol", QMVC_CASES)
def test_batched_qmvc_equals_the_loop(dtype, B, shift, faces, tol, monkeypatch):
    base = bent_box() if faces == "quads" else triquad()
    cage64 = _batch(base, B, shift=shift)
    cage = cage64._like(cage64.vertices.to(dtype))
    per_cage = torch.stack([_points(cage64[b], seed=b) for b in range(B)]).to(dtype)  # (B, N, 3)
    count = CountNativeCalls(monkeypatch, "tc_qmvc3d")
    for pts in (per_cage, per_cage[0]):  # one set per cage; one set shared by every cage
        count.batches.clear()
        out = F.quad_mean_value_coordinates(pts, cage, n=2, tol=tol)
        assert count.batches == [B]  # the whole batch in one native call
        ref = torch.stack(
            [F.quad_mean_value_coordinates(pts if pts.ndim == 2 else pts[b], cage[b], n=2, tol=tol) for b in range(B)]
        )
        assert_same_to_rounding(out, ref)
    # the coordinates themselves: rows sum to one and reproduce the points (linear precision)
    W = F.quad_mean_value_coordinates(per_cage.double(), cage64, n=2, tol=tol)
    near = (per_cage.double() - cage64.vertices.mean(1, keepdim=True)).norm(dim=-1) < 10
    assert ((W.sum(-1) - 1).abs()[near]).max() < 1e-9  # (far rows extrapolate: weights of 1e6 and more)
    assert ((W @ cage64.vertices - per_cage.double()).norm(dim=-1)[near]).max() < 1e-9 * (1 + shift)


@pytest.mark.native
def test_batched_qmvc_two_batch_dimensions_and_chunks(monkeypatch):
    cage = _batch(triquad(), 6, seed=3)
    cage = cage._like(cage.vertices.reshape(2, 3, *cage.vertices.shape[1:]))
    pts = torch.stack([_points(cage[i, j], seed=3 * i + j) for i in range(2) for j in range(3)])
    pts = pts.reshape(2, 3, -1, 3)
    count = CountNativeCalls(monkeypatch, "tc_qmvc3d")
    out = F.quad_mean_value_coordinates(pts, cage, n=2, chunk_size=50)
    N = pts.shape[-2]
    assert out.shape == (2, 3, N, cage.num_vertices) and count.batches == [6] * -(-N // 50)
    for i in range(2):
        for j in range(3):
            assert_same_to_rounding(out[i, j], F.quad_mean_value_coordinates(pts[i, j], cage[i, j], n=2))
    out = F.quad_mean_value_coordinates(pts[0], cage, n=2)  # (3, N, 3) broadcast against cages (2, 3)
    for i in range(2):
        for j in range(3):
            assert_same_to_rounding(out[i, j], F.quad_mean_value_coordinates(pts[0, j], cage[i, j], n=2))


@pytest.mark.native
def test_batched_qmvc_edge_cases():
    cage = _batch(triquad(), 2)
    assert F.quad_mean_value_coordinates(torch.zeros(0, 3, dtype=D64), cage).shape == (2, 0, cage.num_vertices)
    x = torch.zeros(2, 4, 3, dtype=D64)
    x[1, 2, 0] = float("nan")
    with pytest.raises(torchcage.PointsError, match=r"indices \[2\].*batch element \(1,\)"):
        F.quad_mean_value_coordinates(x, cage)
    with pytest.raises(ValueError, match="n must be a positive integer"):
        F.quad_mean_value_coordinates(x[0], cage, n=0)
    # an invalid quad in one element: refused for the batch, or computed with a warning when allowed
    V = cage.vertices.clone()
    q = cage.quads[0]
    V[1, q[2]] = V[1, q[0]] + 0.1 * (V[1, q[0]] - V[1, q[2]])  # the quad folds over
    bad = cage._like(V)
    with pytest.raises(torchcage.CageError, match="not valid"):
        F.quad_mean_value_coordinates(x[0], bad)


@pytest.mark.native
def test_batched_qmvc_undefined_points_are_named_by_element(monkeypatch):
    from torchcage.families.quad_mean_value import api

    real = api.native_coordinates

    def kernel(*args, **kwargs):
        out = real(*args, **kwargs)
        out[1, 3] = float("inf")  # as a row whose total weight vanishes
        return out

    monkeypatch.setattr(api, "native_coordinates", kernel)
    cage = _batch(triquad(), 3)
    with pytest.raises(torchcage.PointsError, match=r"undefined at points \[3\] in batch element \(1,\)"):
        F.quad_mean_value_coordinates(torch.zeros(5, 3, dtype=D64), cage)


def test_batched_qmvc_with_a_graph_still_loops():
    """A batch that records a graph (the torch kernel, differentiable) equals the loop too."""
    cage = _batch(triquad(), 2)
    V = cage.vertices.clone().requires_grad_()
    x = torch.stack([box_points(cage[b], 20, spread=0.5, seed=b) for b in range(2)])
    out = F.quad_mean_value_coordinates(x, cage._like(V), n=2)
    ref = torch.stack([F.quad_mean_value_coordinates(x[b], cage[b], n=2, backend="torch") for b in range(2)])
    assert out.requires_grad and torch.allclose(out.detach(), ref, atol=1e-12, rtol=0)


@pytest.mark.native
def test_qmvc_undefined_points_of_one_cage_are_refused(monkeypatch):
    """One cage on the native kernel: rows that are not finite are refused by index."""
    from torchcage.families.quad_mean_value import api

    real = api.native_coordinates

    def kernel(*args, **kwargs):
        out = real(*args, **kwargs)
        out[0, 2] = float("inf")  # as a row whose total weight vanishes
        return out

    monkeypatch.setattr(api, "native_coordinates", kernel)
    with pytest.raises(torchcage.PointsError, match=r"undefined at points \[2\] \(the total weight"):
        F.quad_mean_value_coordinates(torch.zeros(4, 3, dtype=D64), triquad(), backend="native")


@pytest.mark.native
def test_the_batched_kernels_refuse_a_point_batch_that_is_neither_one_nor_the_cages():
    from torchcage.families.mean_value import derivatives_native
    from torchcage.families.quad_mean_value.native import native_coordinates

    cage = _batch(triquad(), 3)
    v, lib = cage.vertices, _native.library()
    with pytest.raises(ValueError, match="points for 2 cages"):
        native_coordinates(
            lib, torch.zeros(2, 5, 3, dtype=D64), v, cage.triangles, cage.quads, torch.ones(3) * 1e-12, 2
        )
    tri = cage.triangulated()
    tables = derivatives_native.batch_tables(v, tri.triangles, torch.full((3,), 1e-12, dtype=D64))
    V = v.shape[1]
    outs = [
        torch.empty(3, 5, V, dtype=D64),
        torch.empty(3, 5, V, 3, dtype=D64),
        None,
        torch.empty(3, 5, dtype=torch.uint8),
    ]
    with pytest.raises(ValueError, match="points for 2 cages"):
        derivatives_native.native_chunk(torch.zeros(2, 5, 3, dtype=D64), tables, lib, 1, *outs)


# ------------------------------------------------------------------------- quad Green coordinates


@pytest.mark.native
@pytest.mark.filterwarnings("ignore::torchcage.errors.OutsideCageWarning")
@pytest.mark.parametrize("dtype", [torch.float32, D64])
@pytest.mark.parametrize("B", [1, 3])
@pytest.mark.parametrize("shift", [0.0, 1e3])
@pytest.mark.parametrize("faces, tol", QMVC_CASES)
def test_batched_qgc_equals_the_loop(dtype, B, shift, faces, tol, monkeypatch):
    base = bent_box() if faces == "quads" else triquad()
    cage64 = _batch(base, B, shift=shift)
    cage = cage64._like(cage64.vertices.to(dtype))
    per_cage = torch.stack([_points(cage64[b], seed=b) for b in range(B)]).to(dtype)  # (B, N, 3)
    count = CountNativeCalls(monkeypatch, "tc_qgc3d")
    for pts in (per_cage, per_cage[0]):  # one set per cage; one set shared by every cage
        count.batches.clear()
        phi, psi = F.quad_green_coordinates(pts, cage, n=1, tol=tol)
        assert count.batches == [B]  # the whole batch in one native call
        refs = [F.quad_green_coordinates(pts if pts.ndim == 2 else pts[b], cage[b], n=1, tol=tol) for b in range(B)]
        assert_same_to_rounding(phi, torch.stack([r[0] for r in refs]))
        assert_same_to_rounding(psi, torch.stack([r[1] for r in refs]))
    if faces == "quads":  # the coordinates themselves: inside, phi @ V + psi @ N = x (linear precision)
        x = torch.stack([box_points(cage64[b], 30, spread=0.5, seed=b) for b in range(B)])
        phi, psi = F.quad_green_coordinates(x, cage64, n=1, tol=tol)
        N = torch.stack([cage64[b].quad_corner_normals().reshape(-1, 3) for b in range(B)])
        rebuilt = phi @ cage64.vertices + psi @ N
        assert (rebuilt - x).abs().max() < 1e-9 * (1 + shift)


@pytest.mark.native
@pytest.mark.filterwarnings("ignore::torchcage.errors.OutsideCageWarning")
def test_batched_qgc_two_batch_dimensions_and_chunks(monkeypatch):
    cage = _batch(triquad(), 4, seed=5)
    cage = cage._like(cage.vertices.reshape(2, 2, *cage.vertices.shape[1:]))
    pts = torch.stack([box_points(cage[i, j], 90, spread=0.9, seed=2 * i + j) for i in range(2) for j in range(2)])
    pts = pts.reshape(2, 2, -1, 3)
    count = CountNativeCalls(monkeypatch, "tc_qgc3d")
    phi, psi = F.quad_green_coordinates(pts, cage, n=1, chunk_size=40)
    assert phi.shape == (2, 2, 90, cage.num_vertices) and count.batches == [4] * 3
    for i in range(2):
        for j in range(2):
            ref = F.quad_green_coordinates(pts[i, j], cage[i, j], n=1)
            assert_same_to_rounding(phi[i, j], ref[0])
            assert_same_to_rounding(psi[i, j], ref[1])


@pytest.mark.native
def test_batched_qgc_edge_cases():
    cage = _batch(triquad(), 2)
    T4 = cage.triangles.shape[0] + 4 * cage.quads.shape[0]
    phi, psi = F.quad_green_coordinates(torch.zeros(0, 3, dtype=D64), cage)
    assert phi.shape == (2, 0, cage.num_vertices) and psi.shape == (2, 0, T4)
    x = torch.zeros(2, 4, 3, dtype=D64)
    x[1, 2, 1] = float("nan")
    with pytest.raises(torchcage.PointsError, match=r"indices \[2\].*batch element \(1,\)"):
        F.quad_green_coordinates(x, cage)
    far = torch.full((2, 3, 3), 50.0, dtype=D64)
    with pytest.warns(torchcage.errors.OutsideCageWarning, match="6 of 6 points"):
        F.quad_green_coordinates(far, cage)


@pytest.mark.native
@pytest.mark.filterwarnings("ignore::torchcage.errors.OutsideCageWarning")
@pytest.mark.parametrize("dtype", [torch.float32, D64])
def test_batched_quad_families_broadcast_the_points_batch(dtype):
    """Points whose batch shape adds to the cages' (cages ``(2, 1)``, points ``(3, N, 3)``: the
    broadcast batch ``(2, 3)``) equal the calls on each pair."""
    cage = _batch(triquad(), 2, seed=7)
    cage = cage._like(cage.vertices[:, None].to(dtype))
    pts = torch.stack([box_points(cage[0, 0], 25, spread=0.9, seed=s) for s in range(3)]).to(dtype)
    for f in (F.quad_green_coordinates, F.quad_mean_value_coordinates):
        out = f(pts, cage, n=1)
        out = out if isinstance(out, tuple) else (out,)
        for i in range(2):
            for j in range(3):
                ref = f(pts[j], cage[i, 0], n=1)
                ref = ref if isinstance(ref, tuple) else (ref,)
                for o, r in zip(out, ref, strict=True):
                    assert_same_to_rounding(o[i, j], r)


def _folded(cage: torchcage.Cage, elements: tuple[int, ...]) -> torch.Tensor:
    """The vertices of ``cage`` with its first quad folded over in ``elements``."""
    q = cage.quads[0]
    V = cage.vertices.clone()
    for b in elements:
        V[b, q[2]] = V[b, q[0]] + 0.1 * (V[b, q[0]] - V[b, q[2]])
    return V


@pytest.mark.native
def test_allowed_invalid_quads_warn_naming_the_batch_element():
    """With ``allow_invalid=True`` the batched native call warns once, naming the first element
    that holds invalid quads (the per-element paths warn once per element)."""
    cage = _batch(triquad(), 4)
    V = _folded(cage, (2, 3))
    x = torch.zeros(3, 3, dtype=D64)
    with pytest.warns(UserWarning, match=r"in batch element \(1, 0\) \(and some in 1 other"):
        F.quad_mean_value_coordinates(x, cage._like(V.reshape(2, 2, *V.shape[1:])), allow_invalid=True)


def test_invalid_quads_name_the_batch_element():
    """A quad that folds over in some elements of a batch: the error names the first such element,
    with its own quads, and counts the others, for both quad families and every path."""
    cage = _batch(triquad(), 4)
    q = cage.quads[0]
    V = cage.vertices.clone()
    V[2, q[2]] = V[2, q[0]] + 0.1 * (V[2, q[0]] - V[2, q[2]])  # the quad folds over in element 2
    x = torch.zeros(3, 3, dtype=D64)
    for fn in (F.quad_mean_value_coordinates, F.quad_green_coordinates):
        with pytest.raises(torchcage.CageError, match=r"not valid in batch element \(2,\) \(Thiery"):
            fn(x, cage._like(V))
    V[3] = V[2]
    V[3, q[3]] = V[3, q[1]] + 0.1 * (V[3, q[1]] - V[3, q[3]])  # (element 3: two quads fold)
    with pytest.raises(torchcage.CageError, match=r"not valid in batch element \(2,\) \(and some in 1 other") as err:
        F.quad_mean_value_coordinates(x, cage._like(V))
    own = cage[2]._like(V[2]).invalid_quads().tolist()  # (the count and the examples are element 2's own)
    assert str(err.value).startswith(f"{len(own)} quad(s)") and f"e.g. quads {own}" in str(err.value)
    for backend in ("torch", "auto"):  # the per-element paths too (the torch kernel; a graph)
        pts = x if backend == "torch" else x.clone().requires_grad_()
        for fn in (F.quad_mean_value_coordinates, F.quad_green_coordinates):
            with pytest.raises(torchcage.CageError, match=r"not valid in batch element \(2,\)"):
                fn(pts, cage._like(V), backend=backend)
    with pytest.raises(torchcage.CageError, match=r"quad\(s\) of the cage are not valid \(Thiery"):
        F.quad_mean_value_coordinates(x, cage[2]._like(V[2]))  # (one cage: no element to name)
