"""The cheap screens over points agree with the exact tests they stand in front of: the vertex
snap (torchcage._core.common.snap_to_vertices: points within the snap radius of a cage vertex are
moved onto it) against a brute-force search over every pair, including points that share one or
two coordinates with a vertex and points just inside and just outside the radius; the far-region
bound (may_be_far) against far_region; the cached edge table (unique_face_edges) against its computation."""

from __future__ import annotations

import torch

from torchcage._core.common import snap_to_vertices


def _brute(x: torch.Tensor, V: torch.Tensor, radius: float) -> torch.Tensor:
    d2 = ((x[:, None, :] - V[None, :, :]) ** 2).sum(-1)
    m, j = d2.min(dim=1)
    return torch.where((m <= radius * radius)[:, None], V[j], x)


def test_snap_agrees_with_brute_force() -> None:
    g = torch.Generator().manual_seed(3)
    V = torch.rand(40, 3, generator=g, dtype=torch.float64)
    radius = 1e-9
    x = [torch.rand(2000, 3, generator=g, dtype=torch.float64)]
    pick = torch.randint(0, 40, (300,), generator=g)
    direction = torch.nn.functional.normalize(torch.randn(300, 3, generator=g, dtype=torch.float64), dim=1)
    scale = torch.rand(300, 1, generator=g, dtype=torch.float64) * 2  # 0 .. 2 radii from a vertex
    x.append(V[pick] + direction * scale * radius)
    one_axis = torch.rand(300, 3, generator=g, dtype=torch.float64)
    one_axis[:, 0] = V[pick, 0]  # the same x as a vertex, elsewhere otherwise
    two_axes = V[pick].clone()
    two_axes[:, 2] += 10 * radius  # two coordinates of a vertex, the third a little off
    x += [one_axis, two_axes, V.clone()]
    pts = torch.cat(x)
    out = snap_to_vertices(pts, V, radius)
    assert torch.equal(out, _brute(pts, V, radius))
    moved = (out != pts).any(dim=1)
    assert 100 < int(moved.sum()) < 300 + 1  # (about half of the points within 2 radii, none of the others)


def test_snap_in_float32_keeps_the_rows_at_the_radius() -> None:
    """float32 points just inside the radius along one axis (the screen's slack covers float32's
    rounding of the squares): snapped as the brute-force search snaps them."""
    g = torch.Generator().manual_seed(7)
    V = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    for _ in range(200):
        r = float(torch.rand(1, generator=g)) * 1e-3 + 1e-6
        edge = torch.tensor(r, dtype=torch.float32)
        for k in range(-3, 4):  # a few float32 steps either side of the radius
            c = edge
            step = torch.tensor(1.0 if k > 0 else 0.0)
            for _ in range(abs(k)):
                c = torch.nextafter(c, step)
            x = torch.stack([c, torch.tensor(0.0), torch.tensor(0.0)])[None]
            assert torch.equal(snap_to_vertices(x, V, r), _brute(x, V, r))


def test_snap_with_one_vertex_and_in_2d() -> None:
    V = torch.tensor([[0.5, 0.25]], dtype=torch.float64)
    pts = torch.tensor([[0.5, 0.25 + 1e-10], [0.5, 0.3], [0.7, 0.25]], dtype=torch.float64)
    assert torch.equal(snap_to_vertices(pts, V, 1e-9), _brute(pts, V, 1e-9))
    V2 = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]], dtype=torch.float64)
    pts2 = torch.tensor([[1.0, 1e-12], [1.0, 0.5], [1e-12, 1e-12]], dtype=torch.float64)
    assert torch.equal(snap_to_vertices(pts2, V2, 1e-9), _brute(pts2, V2, 1e-9))


def test_far_screen_never_misses_a_far_point() -> None:
    """may_be_far (a bounding-box bound) is True wherever far_region finds a far point, for single
    cages and batches, points just inside and just outside the far radius included."""
    from torchcage._core.common import FAR_MOMENT, far_region, may_be_far

    g = torch.Generator().manual_seed(5)
    for trial in range(200):
        B = 1 + trial % 3
        V = torch.rand(B, 8, 3, generator=g, dtype=torch.float64) * (1 + 10 * trial)
        c = (V.amax(dim=1) + V.amin(dim=1)) / 2
        r = ((V - c[:, None]) ** 2).sum(-1).amax(-1).sqrt()
        direction = torch.nn.functional.normalize(torch.randn(B, 5, 3, generator=g, dtype=torch.float64), dim=-1)
        dist = FAR_MOMENT * r[:, None, None] * (0.99 + 0.02 * torch.rand(B, 5, 1, generator=g, dtype=torch.float64))
        x = c[:, None] + direction * dist * (trial % 2)  # (every other trial: all points at the centre)
        _, far = far_region(V, x)
        if bool(far.any()):
            assert may_be_far(V, x)
        if trial % 2 == 0:
            assert not may_be_far(V, x)
        assert may_be_far(V[0], x[0]) or not bool(far_region(V[0], x[0])[1].any())
        # the bound itself: one point at 0.49 of the far radius is within it, at 0.51 beyond
        one = c[0] + direction[0, :1] * FAR_MOMENT * r[0]
        assert not may_be_far(V[0], c[0] + (one - c[0]) * 0.49)
        assert may_be_far(V[0], c[0] + (one - c[0]) * 0.51)


def test_unique_face_edges_cached_per_topology_is_the_computed_table() -> None:
    """The cached edge table (plain CPU tables, keyed by the table's content) equals a direct
    computation and the definition, for int64 and int32 tables; changing the returned tensors or
    editing the table in place never serves a stale result."""
    from torchcage._core.common import _unique_face_edges, unique_face_edges

    g = torch.Generator().manual_seed(5)
    for dtype in (torch.int64, torch.int32):
        tri = torch.stack([torch.randperm(30, generator=g)[:3] for _ in range(50)]).to(dtype)
        for _ in range(2):  # (the second call is served from the cache)
            edges, face_edge, sign = unique_face_edges(tri)
            ref = _unique_face_edges(tri)
            got = (edges, face_edge, sign)
            assert all(torch.equal(a, b) and a.dtype == b.dtype for a, b in zip(got, ref, strict=True))
            for i in range(3):  # the definition: edge opposite corner i, stored (t[i+1], t[i+2]) when sign = +1
                j, k = tri[:, (i + 1) % 3], tri[:, (i + 2) % 3]
                e = edges[face_edge[:, i]]
                fwd = sign[:, i] > 0
                assert torch.equal(torch.where(fwd, e[:, 0], e[:, 1]), j)
                assert torch.equal(torch.where(fwd, e[:, 1], e[:, 0]), k)
            edges.zero_(), face_edge.zero_(), sign.zero_()  # a caller's changes stay its own
        tri[0] = torch.tensor([27, 28, 29], dtype=dtype)  # edited in place: a new key
        assert all(torch.equal(a, b) for a, b in zip(unique_face_edges(tri), _unique_face_edges(tri), strict=True))
