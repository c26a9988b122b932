"""The native QMVC kernel takes eight points per quad side by side (qmvc3d.c, quad_pair_lanes and
riemann_lanes), leaving the lanes on corners, flat quads' planes and hull faces' planes to the
one-point code: a point's coordinates must not depend on the points that share its block, and
must agree with the torch kernel whatever the number of points."""

from __future__ import annotations

import pytest
import torch
from support import bent_box, box_points, quad_adversarial_points, triquad

from torchcage import functional as F


@pytest.fixture(autouse=True)
def _need_native():
    from torchcage.backends import native as _native

    if not _native.available():
        pytest.skip("no C compiler")


def _mixed_points(cage) -> torch.Tensor:
    """Generic points interleaved with points on and near quads, edges and corners (the blocks of
    eight mix the lane path and the one-point path)."""
    a = box_points(cage, 40, seed=3)
    b = quad_adversarial_points(cage, seed=4, distances=(0.0, 1e-12, 1e-6, 1e-3))
    b = torch.cat([b, cage.vertices.to(torch.float64)[:7]])
    m = min(a.shape[0], b.shape[0])
    inter = torch.stack([a[:m], b[:m]], 1).reshape(-1, 3)
    return torch.cat([inter, a[m:], b[m:]])


@pytest.mark.parametrize("make", [bent_box, triquad])
def test_rows_do_not_depend_on_block_neighbours(make):
    cage = make()
    x = _mixed_points(cage)
    w = F.quad_mean_value_coordinates(x, cage, backend="native")
    perm = torch.randperm(x.shape[0], generator=torch.Generator().manual_seed(0))
    wp = F.quad_mean_value_coordinates(x[perm], cage, backend="native")
    assert torch.equal(wp, w[perm])
    # the same points in calls of 1..11 points (blocks cut at other places, partial blocks)
    for size in (1, 3, 5, 7, 11):
        for s in range(0, 35, size):
            ws = F.quad_mean_value_coordinates(x[s : s + size], cage, backend="native")
            assert torch.equal(ws, w[s : s + size]), (size, s)


@pytest.mark.parametrize("n", [1, 2, 4])
def test_partial_blocks_agree_with_torch(n):
    cage = bent_box()
    x = _mixed_points(cage)
    for count in (1, 2, 3, 7, 8, 9, 17):
        a = F.quad_mean_value_coordinates(x[:count], cage, n, backend="native")
        b = F.quad_mean_value_coordinates(x[:count], cage, n, backend="torch")
        torch.testing.assert_close(a, b, atol=1e-10, rtol=0)
    a = F.quad_mean_value_coordinates(x, cage, n, backend="native")
    b = F.quad_mean_value_coordinates(x, cage, n, backend="torch")
    assert torch.isfinite(a).all()
    torch.testing.assert_close(a, b, atol=1e-10, rtol=0)
