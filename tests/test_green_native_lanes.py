"""The native Green kernel computes blocks of points at once (gc3d.c, gc_block: vectorised across the
points, the careful forms per pair where a pair needs them). Each point's result must not depend on
its neighbours in the block: one call on points of every kind (ordinary, on faces, edges and
vertices, near the support planes of faces, far away, thin faces seen from a few widths) equals the
points computed one by one and in odd chunks, bit for bit, and agrees with the torch kernel."""

from __future__ import annotations

import pytest
import torch
from support import box_cage, notched

from torchcage import functional as F
from torchcage.backends import native as _native


def mixed_points(cage, seed: int = 0) -> torch.Tensor:
    """Points of every kind the kernel tells apart, 8k + 3 of them (not a multiple of a block)."""
    g = torch.Generator().manual_seed(seed)
    p, tri = cage.vertices, cage.triangles
    lo, hi = p.min(0).values, p.max(0).values
    pick = torch.randperm(tri.shape[0], generator=g)[:12]  # a few faces (the test stays fast)
    tri, nrm = tri[pick], cage.triangle_normals()[pick]
    size = (hi - lo).norm()
    corners = p[tri]  # (T, 3, 3)
    bary = torch.rand(tri.shape[0], 3, generator=g, dtype=torch.float64)
    bary = bary / bary.sum(1, keepdim=True)
    on_face = torch.einsum("tk,tkc->tc", bary, corners)
    on_edge = 0.3 * corners[:, 0] + 0.7 * corners[:, 1]
    # next to the support planes: just off faces, and in the plane of a face outside it
    near = torch.cat([on_face + 1e-13 * size * nrm, on_face - 1e-9 * size * nrm, on_face + 1e-3 * size * nrm])
    in_plane = corners[:, 0] + 1.5 * (corners[:, 0] - on_face)
    ordinary = lo + (hi - lo) * torch.rand(24, 3, generator=g, dtype=torch.float64)
    direction = torch.nn.functional.normalize(torch.randn(8, 3, generator=g, dtype=torch.float64), dim=1)
    far = (lo + hi) / 2 + size * torch.cat([30 * direction[:4], 1e4 * direction[4:]])
    vertices = p[torch.randperm(p.shape[0], generator=g)[:12]]
    x = torch.cat([ordinary, on_face, on_edge, vertices, near, in_plane, far])
    x = x[torch.randperm(x.shape[0], generator=g)]  # every kind in every lane
    return x[: 8 * ((x.shape[0] - 3) // 8) + 3]


def thin_box():
    """A flat box: its side triangles are 200 times longer than wide (thin faces)."""
    return box_cage(2, 2, 1, size=(2.0, 2.0, 0.005)).triangulated()


@pytest.mark.parametrize("make", [notched, thin_box], ids=["notched", "thin_box"])
def test_blocks_equal_points_alone_and_the_torch_kernel(make):
    if not _native.available():
        pytest.skip("native kernel unavailable")
    cage = make()
    x = mixed_points(cage)
    assert x.shape[0] % 8 == 3
    phi, psi = F.green_coordinates(x, cage, backend="native", exterior="none")
    assert torch.isfinite(phi).all() and torch.isfinite(psi).all()
    alone = [F.green_coordinates(x[i : i + 1], cage, backend="native", exterior="none") for i in range(x.shape[0])]
    assert torch.equal(phi, torch.cat([a[0] for a in alone])) and torch.equal(psi, torch.cat([a[1] for a in alone]))
    for size in (3, 13):  # odd chunks: every point in another lane of another block
        c = F.green_coordinates(x, cage, backend="native", exterior="none", chunk_size=size)
        assert torch.equal(phi, c[0]) and torch.equal(psi, c[1])
    ref = F.green_coordinates(x, cage, backend="torch", exterior="none")
    assert (phi - ref[0]).abs().max() < 1e-12 and (psi - ref[1]).abs().max() < 1e-12
    # and the default exterior (the jump on the cage, the extension outside) on the same points
    a = F.green_coordinates(x, cage, backend="native")
    b = F.green_coordinates(x, cage, backend="torch")
    assert (a[0] - b[0]).abs().max() < 1e-12 and (a[1] - b[1]).abs().max() < 1e-12


def test_large_outputs_streamed_equal_chunks():
    """Past 32 MiB of output the kernel writes with non-temporal stores: the same values as in
    chunks written the ordinary way."""
    if not _native.available():
        pytest.skip("native kernel unavailable")
    cage = box_cage().triangulated()  # 8 vertices + 12 triangles: 20 values per point
    g = torch.Generator().manual_seed(3)
    x = 2.4 * torch.rand(220_003, 3, generator=g, dtype=torch.float64) - 1.2  # 4.4e6 values > 2**22
    phi, psi = F.green_coordinates(x, cage, backend="native", exterior="none")
    c = F.green_coordinates(x, cage, backend="native", exterior="none", chunk_size=50_000)
    assert torch.equal(phi, c[0]) and torch.equal(psi, c[1])
