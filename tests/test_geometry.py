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
    if not tc._native.available():
        pytest.skip("no C compiler")
    for cage in (l_shape(), triquad()):
        x = _probe(cage)
        tri = cage.triangulated().triangles if cage.has_quads else cage.triangles
        x = x[distance_to_cage(x, cage) > 1e-12]  # (on a face the solid angle's sign is rounding)
        a = winding_number(x, cage.vertices, tri, backend="native")
        b = winding_number(x, cage.vertices, tri, backend="torch")
        assert torch.allclose(a, b, atol=1e-12, rtol=0)
        assert bool(((a - 1).abs() < 1e-9).sum() > 0) and bool((a.abs() < 1e-9).sum() > 0)  # inside and outside
