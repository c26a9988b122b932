"""The native 3D mean value kernel's blocked path (8 points at a time, ``mvc3d_block`` in
``torchcage/backends/native/mvc3d.c``) against its per-point path (``mvc3d_point``, which serves a
call of fewer than 8 points) and against the torch kernel, on points that mix every case in the
same blocks: ordinary points, points on faces, edges and vertices, near support planes (the stable
split form), beside thin faces (the swept form) and far away (the far-field rule, the moment)."""

from __future__ import annotations

import pytest
import torch
from random_cages import needle_cage, plane_points, star_cage

import torchcage
from torchcage import functional as F
from torchcage.backends import native as _native

D64 = torch.float64


def _mixed_points(cage: torchcage.Cage, g: torch.Generator) -> torch.Tensor:
    """``8 k + 5`` points, the special ones shuffled among ordinary ones (so that blocks mix them)."""
    v, tri = cage.vertices, cage.triangles
    p = v[tri]
    nrm = torch.nn.functional.normalize(torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1), dim=-1)
    lo, hi = v.min(0).values, v.max(0).values
    centre, scale = (lo + hi) / 2, cage.scale
    inside = centre + (torch.rand(40, 3, generator=g, dtype=D64) - 0.5) * (hi - lo) * 0.6
    f = torch.randint(0, tri.shape[0], (12,), generator=g)
    bary = torch.rand(12, 3, generator=g, dtype=D64)
    bary = bary / bary.sum(1, keepdim=True)
    on_face = (bary[:, :, None] * p[f]).sum(1)
    on_edge = 0.3 * p[f, 0] + 0.7 * p[f, 1]
    on_vertex = p[f, 2]
    off = (torch.tensor([1e-13, -1e-9, 1e-6, -1e-4] * 3, dtype=D64) * scale)[:, None] * nrm[f]
    near_face = on_face + off  # (just off the face: the split form, or on the cage within tol)
    in_plane, pf = plane_points(cage, g, 12)  # on support planes outside their faces
    near_plane = in_plane + (torch.tensor([1e-14, -1e-8, 1e-5] * 4, dtype=D64) * scale)[:, None] * nrm[pf]
    dirs = torch.nn.functional.normalize(torch.randn(9, 3, generator=g, dtype=D64), dim=-1)
    far = centre + dirs * (scale * torch.tensor([3.0, 30.0, 1e3, 1e4, 1e5, 2.0, 5.0, 1e2, 1e6], dtype=D64))[:, None]
    x = torch.cat([inside, on_face, on_edge, on_vertex, near_face, in_plane, near_plane, far])
    x = x[torch.randperm(x.shape[0], generator=g)]
    n = 8 * (x.shape[0] // 8) + 5
    return x[:n] if n <= x.shape[0] else torch.cat([x, inside[: n - x.shape[0]]])


def _rows_close(a: torch.Tensor, b: torch.Tensor) -> float:
    """The largest difference of rows of ``a`` and ``b`` relative to the row's largest entry (at least 1)."""
    row = b.abs().amax(dim=1, keepdim=True).clamp_min(1.0)
    return float(((a - b).abs() / row).max())


@pytest.mark.parametrize("kind", ["star", "needle"])
def test_blocked_path_equals_the_per_point_path_and_torch(kind):
    if not _native.available():
        pytest.skip("native kernel unavailable")
    g = torch.Generator().manual_seed(7)
    cage = star_cage(g) if kind == "star" else needle_cage(g, aspect=300.0)
    x = _mixed_points(cage, g)
    assert x.shape[0] % 8 == 5
    blocked = F.mean_value_coordinates(x, cage, backend="native")
    alone = torch.cat([F.mean_value_coordinates(x[i : i + 1], cage, backend="native") for i in range(x.shape[0])])
    assert torch.isfinite(blocked).all()
    # The two paths evaluate the same formulas in the same order; only libmvec's vector atan (the
    # per-point path calls libm's for its edge loop's remainder) may differ in the last bits.
    assert _rows_close(blocked, alone) < 1e-14
    # (the torch kernel's swept form of thin faces differs from the native one by ~2e-11 here, as
    # the per-point kernel did before the blocks; elsewhere by ~1e-13)
    ref = F.mean_value_coordinates(x, cage, backend="torch")
    assert _rows_close(blocked, ref) < (1e-12 if kind == "star" else 1e-10)
    # A point's values do not depend on its neighbours in the block: the same points reversed.
    rev = F.mean_value_coordinates(x.flip(0), cage, backend="native").flip(0)
    assert _rows_close(rev, blocked) < 1e-14


def test_blocked_path_in_a_batch_of_cages():
    """Blocks per (cage, block) work item: a batch of three cages, shared points and one set per cage,
    against each cage alone (whose blocks the test above ties to the per-point path)."""
    if not _native.available():
        pytest.skip("native kernel unavailable")
    g = torch.Generator().manual_seed(3)
    base = star_cage(g)
    verts = torch.stack([base.vertices * s for s in (1.0, 1.1, 0.9)])
    batch = torchcage.Cage(verts, base.triangles)
    x = _mixed_points(base, g)
    W = F.mean_value_coordinates(x, batch, backend="native")
    for b in range(3):
        one = torchcage.Cage(verts[b], base.triangles)
        assert _rows_close(W[b], F.mean_value_coordinates(x, one, backend="native")) < 1e-14
        alone = F.mean_value_coordinates(x[-5:], one, backend="native")  # (the remainder rows of each cage)
        assert _rows_close(W[b, -5:], alone) < 1e-14
    xs = torch.stack([x, x.flip(0), x * 0.5])
    Wp = F.mean_value_coordinates(xs, batch, backend="native")
    for b in range(3):
        one = torchcage.Cage(verts[b], base.triangles)
        assert _rows_close(Wp[b], F.mean_value_coordinates(xs[b], one, backend="native")) < 1e-14
