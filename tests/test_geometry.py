"""The distance helpers of torchcage.geometry against the tests' brute-force reference."""

from __future__ import annotations

import pytest
import torch
from reference import distance_to_triangles
from support import l_shape, triquad

import torchcage as tc
from torchcage.geometry import distance_to_cage, near_cage, winding_number

D64 = torch.float64


def _probe(cage: tc.Cage, n: int = 400) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    v = cage.vertices.to(D64)
    lo, hi = v.min(0).values - 0.3, v.max(0).values + 0.3
    x = lo + (hi - lo) * torch.rand(n, cage.dim, generator=g, dtype=D64)
    if cage.dim == 3:  # and points on and just off the faces
        tri = cage.triangulated().triangles if cage.has_quads else cage.triangles
        c = v[tri].mean(1)
        x = torch.cat([x, c, c + 1e-9, c - 1e-4])
    return x


def test_distance_to_cage_matches_the_reference() -> None:
    for cage in (l_shape(), triquad()):
        x = _probe(cage)
        tri = cage.triangulated().triangles if cage.has_quads else cage.triangles
        ref = distance_to_triangles(x, cage.vertices, tri)
        assert torch.allclose(distance_to_cage(x, cage), ref, atol=1e-14, rtol=0)


def test_near_cage_agrees_with_the_distances() -> None:
    star = tc.Cage(torch.tensor([[1.0, 0.0], [0.2, 0.2], [0.0, 1.0], [-0.2, 0.2], [-1, 0], [0, -1]], dtype=D64))
    for cage in (l_shape(), triquad(), star):
        x = _probe(cage)
        d = distance_to_cage(x, cage)
        for r in (1e-12, 1e-6, 1e-3, 0.05):
            assert torch.equal(near_cage(x, cage, r), d <= r)


def test_native_winding_number_matches_torch() -> None:
    if not tc.backends.native.available():
        pytest.skip("no C compiler")
    for cage in (l_shape(), triquad()):
        x = _probe(cage)
        tri = cage.triangulated().triangles if cage.has_quads else cage.triangles
        x = x[distance_to_cage(x, cage) > 1e-12]  # (on a face the solid angle's sign is rounding)
        a = winding_number(x, cage.vertices, tri, backend="native")
        b = winding_number(x, cage.vertices, tri, backend="torch")
        assert torch.allclose(a, b, atol=1e-12, rtol=0)
        assert bool(((a - 1).abs() < 1e-9).sum() > 0) and bool((a.abs() < 1e-9).sum() > 0)  # inside and outside


def test_nearest_triangle_native_torch_and_reference_agree() -> None:
    """Both backends against the tests' reference, with a per-triangle slack and degenerate
    triangles (a segment and a point: their distance is to their edges, never to a 'plane')."""
    from torchcage.geometry import nearest_triangle

    cage = l_shape()
    x = _probe(cage)
    v = torch.cat([cage.vertices.to(D64), torch.tensor([[0.3, 0.3, 3.0], [0.3, 0.3, 3.0]], dtype=D64)])
    n = cage.num_vertices
    tri = torch.cat([cage.triangles, torch.tensor([[n, n + 1, 0], [n, n, n]])])
    slack = torch.rand(tri.shape[0], dtype=D64, generator=torch.Generator().manual_seed(1)) * 0.05
    per_face = torch.stack([distance_to_triangles(x, v, tri[k : k + 1]) for k in range(tri.shape[0] - 2)], dim=1)
    ab = v[0] - v[n]  # the segment v[n] -> v[0], and the point v[n]
    t = ((x - v[n]) @ ab / (ab @ ab)).clamp(0, 1)
    segment = (x - v[n] - t[:, None] * ab).norm(dim=1)
    per_face = torch.cat([per_face, segment[:, None], (x - v[n]).norm(dim=1)[:, None]], dim=1)
    ref = (per_face - slack).min(dim=1)
    backends = ("torch", "native") if tc.backends.native.available() else ("torch",)
    for backend in backends:
        d, i = nearest_triangle(x, v, tri, slack=slack, backend=backend)
        assert torch.allclose(d, ref.values, atol=1e-14, rtol=0)
        picked = per_face.gather(1, i[:, None])[:, 0] - slack[i]
        assert torch.allclose(picked, ref.values, atol=1e-14, rtol=0)
    d0, _ = nearest_triangle(x, v, tri)
    assert torch.allclose(d0, per_face.min(dim=1).values, atol=1e-14, rtol=0)


def test_nearest_triangle_gives_nan_for_nan_input_on_both_backends() -> None:
    """A NaN point, or a NaN corner of any triangle, gives a NaN distance (never a finite distance
    to the remaining triangles), natively as in torch; bad slack shapes raise."""
    from torchcage.geometry import nearest_triangle

    v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5], [6, 5, 5], [5, 6, 5]], dtype=D64)
    t = torch.tensor([[0, 1, 2], [3, 4, 5]])
    x = torch.tensor([[0.2, 0.2, 1.0], [float("nan"), 0, 0]], dtype=D64)
    bad = v.clone()
    bad[4, 0] = float("nan")
    backends = ("torch", "native") if tc.backends.native.available() else ("torch",)
    for backend in backends:
        d, _ = nearest_triangle(x, v, t, backend=backend)
        assert d[0] == 1.0 and torch.isnan(d[1])
        assert torch.isnan(nearest_triangle(x[:1], bad, t, backend=backend)[0]).all()
        with pytest.raises(ValueError, match="one value per triangle"):
            nearest_triangle(x, v, t, slack=torch.zeros(3, dtype=D64), backend=backend)
