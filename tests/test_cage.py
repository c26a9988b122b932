"""Cage construction, validation errors, orientation, derived geometry."""

from __future__ import annotations

import warnings

import pytest
import torch
from support import QMVC_MODELS, box_cage, data_path

import torchcage
from torchcage import Cage

TET_V = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
TET_F = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]


def test_tetrahedron_geometry():
    cage = Cage(TET_V, TET_F)
    assert cage.dim == 3 and cage.num_vertices == 4 and not cage.has_quads
    assert torch.isclose(cage.signed_volume(), torch.tensor(1 / 6, dtype=torch.float64))
    n = cage.triangle_normals()
    centroid = TET_V[torch.tensor(TET_F)].mean(1)
    assert ((centroid - TET_V.mean(0)) * n).sum(-1).gt(0).all()  # outward
    assert torch.allclose(n.norm(dim=-1), torch.ones(4, dtype=torch.float64))


def test_quads_and_triangulation():
    cage = box_cage(2, 1, 1)
    assert cage.has_quads and cage.quads.shape == (10, 4) and cage.triangles.shape == (0, 3)
    tri = cage.triangulated()
    assert tri.triangles.shape == (20, 3) and not tri.has_quads
    q = cage.quads[0]
    assert tri.triangles[0].tolist() == [q[0], q[1], q[2]] and tri.triangles[1].tolist() == [q[0], q[2], q[3]]
    assert torch.isclose(tri.signed_volume(), torch.tensor(8.0, dtype=torch.float64))
    corner = cage.quad_corner_normals()
    assert corner.shape == (10, 4, 3)
    # For planar quads the corner normals are parallel to the face normal.
    tn = tri.triangle_normals()[0::2]
    assert torch.allclose(torch.nn.functional.normalize(corner[:, 0], dim=-1), tn)


def test_unique_edges():
    cage = box_cage(2, 1, 1)
    e = cage.unique_edges()
    assert e.shape == (20, 2) and bool((e[:, 0] < e[:, 1]).all())  # 12 vertices, 10 quads: E = V + F - 2
    assert cage.triangulated().unique_edges().shape == (30, 2)  # the q0-q2 diagonals join in


def test_triquad_list_faces():
    v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1]], dtype=torch.float64)
    faces = [[0, 3, 2, 1], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]]  # a square pyramid
    cage = Cage(v, faces)
    assert cage.triangles.shape == (4, 3) and cage.quads.shape == (1, 4)
    assert isinstance(cage.faces, list) and len(cage.faces) == 5
    assert cage.signed_volume() > 0


def test_inward_cage_is_flipped_with_warning():
    flipped = [f[::-1] for f in TET_F]
    with pytest.warns(UserWarning, match="oriented inward"):
        cage = Cage(TET_V, flipped)
    assert cage.signed_volume() > 0
    box = box_cage()
    with pytest.warns(UserWarning, match="oriented inward"):
        inv = Cage(box.vertices, box.quads.flip(1))
    assert inv.quads[:, 0].tolist() == box.quads.flip(1)[:, 0].tolist()  # q0 kept: same diagonal


@pytest.mark.parametrize(
    ("vertices", "faces", "error", "match"),
    [
        (TET_V.clone().index_fill_(0, torch.tensor([2]), float("nan")), TET_F, torchcage.CageError, "NaN or inf"),
        (TET_V, [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 7]], torchcage.CageError, "outside"),
        (TET_V, [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 2]], torchcage.CageError, "repeat a vertex"),
        (TET_V, [[0, 2, 1], [0, 1, 3], [0, 3, 2]], torchcage.CageTopologyError, "open"),
        (TET_V, [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 3, 2]], torchcage.CageOrientationError, "inconsistently"),
        (TET_V, [[0, 2, 1, 3, 1]], torchcage.CageError, "5 corners"),
        (TET_V[:, :1], None, torchcage.CageError, "shape"),
        (TET_V[0], None, torchcage.CageError, "shape"),
    ],
)
def test_validation_errors(vertices, faces, error, match):
    with pytest.raises(error, match=match):
        Cage(vertices, faces)


def test_degenerate_and_non_manifold():
    v = torch.cat([TET_V, torch.tensor([[0.5, 0.5, 0.0]], dtype=torch.float64)])
    # Vertex 4 lies on the edge (1, 2): the face (1, 2, 4) has zero area.
    with pytest.raises(torchcage.DegenerateFaceError, match="zero area"):
        Cage(v, [*TET_F, [1, 2, 4]])
    # Two tetrahedra sharing one face's edge three times: non-manifold.
    v2 = torch.cat([TET_V, torch.tensor([[1.0, 1.0, 1.0]], dtype=torch.float64)])
    faces = [*TET_F, [1, 4, 2], [1, 3, 4], [2, 4, 3]]
    with pytest.raises(torchcage.CageTopologyError, match=r"\(1, 2\)"):
        Cage(v2, faces)
    assert issubclass(torchcage.CageTopologyError, ValueError)
    # Two tetrahedra touching at vertex 0 only (a "bowtie"): every edge is fine, the vertex is not.
    v3 = torch.cat([TET_V, -TET_V[1:]])
    second = [[0, 4, 5], [0, 6, 4], [0, 5, 6], [4, 6, 5]]
    with pytest.raises(torchcage.CageTopologyError, match="non-manifold at vertex 0"):
        Cage(v3, [*TET_F, *second])


def test_2d_polygon_and_orientation():
    sq = [[0.0, 0], [1, 0], [1, 1], [0, 1]]
    cage = Cage(sq)
    assert cage.dim == 2 and cage.edges.tolist() == [[0, 1], [1, 2], [2, 3], [3, 0]]
    assert float(cage.signed_volume()) == pytest.approx(1.0)
    n = cage.edge_normals()
    assert torch.allclose(n[0], torch.tensor([0.0, -1.0], dtype=torch.float64))  # outward (down) for the bottom edge
    with pytest.warns(UserWarning, match="clockwise"):
        cw = Cage(sq[::-1])
    assert torch.equal(cw.vertices, torch.tensor(sq[::-1], dtype=torch.float64))
    assert float(cw.signed_volume()) == pytest.approx(1.0)
    with pytest.raises(torchcage.CageTopologyError, match="open"):
        Cage(sq, torch.tensor([[0, 1], [1, 2], [2, 3]]))
    with pytest.raises(torchcage.CageOrientationError, match="inconsistent directions"):
        Cage(sq, torch.tensor([[0, 1], [2, 1], [2, 3], [3, 0]]))
    with pytest.raises(torchcage.DegenerateFaceError):
        Cage([[0.0, 0], [1, 0], [1, 0], [0, 1]])


def test_to_dtype_and_input_untouched(device):
    v = TET_V.clone()
    cage = Cage(v, TET_F)
    c32 = cage.to(torch.float32)
    assert c32.dtype == torch.float32 and c32.triangles.dtype == torch.int64
    c = cage.to(device=device)
    assert c.vertices.device.type == device and c.triangles.device.type == device
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        Cage(v, [f[::-1] for f in TET_F])
    assert torch.equal(v, TET_V)
    with pytest.raises(TypeError):
        cage.to(torch.int32)
    assert "Cage(dim=3" in repr(cage)


def test_integer_vertices_become_float64():
    cage = Cage([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], TET_F)
    assert cage.dtype == torch.float64


def _valid_by_projection(q: torch.Tensor) -> bool:
    """Definition 1 checked literally: project the quad onto each corner triangle's plane, build
    2D coordinates in that plane, and require a convex, counter-clockwise (w.r.t. the plane's
    normal) polygon."""
    for i in range(4):
        a, b, c = q[(i - 1) % 4], q[i], q[(i + 1) % 4]
        n = torch.linalg.cross(b - a, c - b, dim=0)
        n = n / n.norm()
        u = (c - b) - ((c - b) @ n) * n
        u = u / u.norm()
        w = torch.linalg.cross(n, u, dim=0)
        xy = torch.stack([(q - b) @ u, (q - b) @ w], dim=1)
        for k in range(4):
            p0, p1, p2 = xy[k], xy[(k + 1) % 4], xy[(k + 2) % 4]
            turn = (p1[0] - p0[0]) * (p2[1] - p1[1]) - (p1[1] - p0[1]) * (p2[0] - p1[0])
            if turn <= 0:
                return False
    return True


def test_invalid_quads_against_the_definition():
    g = torch.Generator().manual_seed(3)
    square = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=torch.float64)
    agree, invalid = 0, 0
    for _ in range(300):
        q = square + 0.45 * torch.randn(4, 3, generator=g, dtype=torch.float64)
        cage = Cage._trusted(q, torch.zeros(0, 3, dtype=torch.long), torch.arange(4)[None], torch.zeros(0, 2))
        got = cage.invalid_quads().numel() == 0
        assert got == _valid_by_projection(q)
        agree += 1
        invalid += not got
    assert agree == 300 and 30 < invalid < 270  # both outcomes are exercised
    dart = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0.3, 0.3, 0], [0, 1, 0]], dtype=torch.float64)
    cage = Cage._trusted(dart, torch.zeros(0, 3, dtype=torch.long), torch.arange(4)[None], torch.zeros(0, 2))
    assert cage.invalid_quads().tolist() == [0]
    assert box_cage(2, 2, 3).invalid_quads().numel() == 0


@pytest.mark.parametrize("model", QMVC_MODELS)
def test_paper_cages_have_valid_quads(model):
    cage = torchcage.load_cage(data_path("qmvc", f"{model}_Cage.obj"))
    assert cage.has_quads and cage.invalid_quads().numel() == 0
