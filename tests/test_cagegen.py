"""The cage maker: enclosure, validity, no self-intersection, size and tightness on procedurally
made shapes (an open sphere with a second part, a point cloud), and clear errors on bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchcage
from torchcage import functional as F
from torchcage.cagegen import measure_cage, self_intersections, signed_clearance
from torchcage.errors import MeshError

pytest.importorskip("skimage")
pytest.importorskip("fast_simplification")


def _uv_sphere(n: int, radius: float, centre, hole: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere ``(n + 1) x 2n`` (poles duplicated per column, fine for the maker), optionally
    with faces removed (an open mesh)."""
    th = np.linspace(0, math.pi, n + 1)
    ph = np.linspace(0, 2 * math.pi, 2 * n, endpoint=False)
    t, p = np.meshgrid(th, ph, indexing="ij")
    v = radius * np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3) + centre
    idx = np.arange((n + 1) * 2 * n).reshape(n + 1, 2 * n)
    a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
    c, d = idx[1:], np.roll(idx[1:], -1, axis=1)
    f = np.concatenate([np.stack([a, c, d], -1).reshape(-1, 3), np.stack([a, d, b], -1).reshape(-1, 3)])
    if hole:
        f = f[np.arange(f.shape[0]) % 97 != 0]  # about 1% of the faces missing, scattered holes
    return v, f


def _two_parts() -> tuple[torch.Tensor, torch.Tensor]:
    v1, f1 = _uv_sphere(24, 1.0, np.zeros(3), hole=True)
    v2, f2 = _uv_sphere(12, 0.4, np.array([2.2, 0.0, 0.0]))
    v = np.concatenate([v1, v2])
    f = np.concatenate([f1, f2 + v1.shape[0]])
    keep = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1) > 1e-12
    return torch.from_numpy(v), torch.from_numpy(f[keep])


@pytest.mark.parametrize("kind", ["triangle", "quad"])
def test_made_cage_encloses_an_open_two_part_mesh(kind):
    v, f = _two_parts()
    target = 80
    cage = torchcage.make_cage(v, f, target_vertices=target, kind=kind)
    diag = float((v.amax(0) - v.amin(0)).norm())
    r = measure_cage(cage, v, f)
    assert abs(cage.num_vertices - target) <= 0.25 * target
    assert r.outside == 0 and r.self_intersections == 0 and r.invalid_quads == 0
    s, _ = signed_clearance(v, cage.vertices, cage.triangles, cage.quads)
    assert float(s.min()) >= 0.005 * diag * (1 - 1e-9)  # the default margin
    assert r.mean_distance < 0.05 and r.max_distance < 0.2
    if kind == "quad":
        assert r.quad_fraction >= 0.8
    lam = F.mean_value_coordinates(v, cage.triangulated())
    assert torch.isfinite(lam).all()
    assert torch.allclose(lam @ cage.vertices, v, atol=1e-10 * diag)


def test_made_cage_of_a_point_cloud():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(3000, 3, dtype=torch.float64, generator=g) * torch.tensor([2.0, 1.0, 0.5], dtype=torch.float64)
    cage = torchcage.make_cage(x, target_vertices=60, margin=0.05)
    s, _ = signed_clearance(x, cage.vertices, cage.triangles)
    assert float(s.min()) >= 0.05 * (1 - 1e-9)
    assert self_intersections(cage.vertices, cage.triangles) == 0
    assert abs(cage.num_vertices - 60) <= 15


def test_self_intersection_check_finds_two_interpenetrating_tetrahedra():
    t = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    tet = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    apart = torch.cat([tet, tet + 3])
    overlap = torch.cat([tet, tet + 0.2])
    faces = torch.cat([t, t + 4])
    assert self_intersections(apart, faces) == 0
    assert self_intersections(overlap, faces) > 0


@pytest.mark.parametrize(
    ("vertices", "faces", "match"),
    [
        (np.zeros((0, 3)), None, "empty"),
        (np.array([[0.0, 0, 0], [np.nan, 0, 0]]), None, "NaN"),
        (np.array([[1.0, 2, 3]]), None, "coincide"),
        (np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]), np.array([[0, 1, 2]]), "degenerate"),
        (np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 5]]), "outside"),
    ],
)
def test_make_cage_refuses_bad_input(vertices, faces, match):
    with pytest.raises(MeshError, match=match):
        torchcage.make_cage(vertices, faces)
