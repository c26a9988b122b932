"""Cage geometry that cannot be computed with is refused on every path:
coincident vertices, flat cages, NaN/inf vertices given through paths that skip the constructor's
checks (``validate=False`` / ``"topology"``, ``with_vertices``), and unit normals at any scale."""

from __future__ import annotations

import math

import pytest
import torch
from support import cube_files

import torchcage
from torchcage import Cage
from torchcage import functional as F
from torchcage.errors import CageError, DegenerateFaceError
from torchcage.testing import icosphere

D64 = torch.float64


def _cube(scale: float = 1.0, shift: float = 0.0) -> Cage:
    c = torchcage.load_cage(torchcage.data.path("cube.obj")).to(D64)
    return Cage(c.vertices * scale + shift, c.faces)


def _rotation(seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=D64))
    return q * torch.sign(torch.det(q))


@pytest.mark.parametrize("seed", range(4))
def test_unit_normals_at_any_scale(seed: int) -> None:
    """|n| = 1 for random star cages scaled by 1e-150..1e40 and moved far away (no fixed clamp)."""
    g = torch.Generator().manual_seed(seed)
    if seed % 2:  # a random star-shaped cage: an icosphere with random radii
        ico = icosphere(1)
        base = Cage(ico.vertices * (0.5 + torch.rand(ico.vertices.shape[0], 1, generator=g, dtype=D64)), ico.faces)
    else:
        base = _cube()
    for exp in (-150, -30, -7, 0, 9, 40):
        s = 10.0**exp * (1 + float(torch.rand(1, generator=g)))
        shift = s * 1e3 * torch.randn(3, generator=g, dtype=D64)
        cage = Cage(base.vertices.to(D64) @ _rotation(seed).T * s + shift, base.faces)
        n = cage.triangle_normals()
        assert torch.allclose(n.norm(dim=-1), torch.ones_like(n[..., 0]), atol=1e-14, rtol=0)
        raw = cage.triangle_normals(unit=False)
        cos = (torch.nn.functional.normalize(raw / raw.abs().amax(), dim=-1) * n).sum(-1)
        assert bool((cos > 1 - 1e-12).all())


def test_edge_normals_at_any_scale() -> None:
    for s in (1e-300, 1e-7, 1.0, 1e40):
        sq = Cage(torch.tensor([[0.0, 0], [1, 0], [1, 1], [0, 1]], dtype=D64) * s)
        n = sq.edge_normals()
        assert torch.allclose(n.norm(dim=-1), torch.ones(4, dtype=D64), atol=1e-15, rtol=0)


def test_green_identity_holds_on_a_tiny_cage() -> None:
    """The documented ``phi @ V + psi @ normals == x`` on a cube of side 5e-7, far from the origin."""
    for s, shift in ((5e-7, 0.0), (5e-7, 3e-6), (1e-3, 0.2)):
        cage = _cube(s, shift).triangulated()
        g = torch.Generator().manual_seed(1)
        x = cage.vertices.mean(0) + (torch.rand(64, 3, generator=g, dtype=D64) - 0.5) * 1.6 * s
        phi, psi = F.green_coordinates(x, cage)
        rec = phi @ cage.vertices + psi @ cage.triangle_normals()
        assert float((rec - x).norm(dim=-1).max()) < 1e-11 * cage.scale


def test_coincident_neighbours_are_refused() -> None:
    """A quad cube with one vertex moved onto a neighbour keeps positive face areas: refused."""
    cube = _cube()
    for i, j in ((1, 0), (6, 2), (3, 7)):
        v = cube.vertices.clone()
        edges = cube.unique_edges().tolist()
        if [min(i, j), max(i, j)] not in edges:
            continue
        v[i] = v[j]
        with pytest.raises(DegenerateFaceError, match="coincide"):
            Cage(v, cube.faces)


def test_coincident_vertices_anywhere_and_in_a_batch() -> None:
    """Two equal vertices that share no edge, and a batch whose third element has two equal vertices."""
    cube = _cube()
    v = cube.vertices.clone()
    v[0] = v[6]  # opposite corners: no shared edge, the surface pinches
    with pytest.raises(DegenerateFaceError, match=r"same position|coincide"):
        Cage(v, cube.faces)
    w = cube.vertices.clone()
    w[1] = w[0]
    batch = torch.stack([cube.vertices, cube.vertices * 2, w])
    with pytest.raises(DegenerateFaceError, match=r"batch element \(2,\)"):
        Cage(batch, cube.faces)
    with pytest.raises(DegenerateFaceError, match=r"batch element \(2,\)"):
        F.mean_value_coordinates(torch.zeros(3, 3, dtype=D64), cube.triangulated().with_vertices(batch))


def test_flat_cages_are_refused() -> None:
    """A tetrahedron folded onto a plane (distinct vertices, positive face areas, zero volume) and a
    polygon folded onto a line: no inside; refused by the constructor and by the functional API."""
    v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.3, 0.3, 0]], dtype=D64)
    faces = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
    with pytest.raises(DegenerateFaceError, match="encloses no volume"):
        Cage(v, faces)
    loose = Cage(v, faces, validate=False)
    for fn in (F.mean_value_coordinates, F.green_coordinates):
        with pytest.raises(DegenerateFaceError, match="encloses no volume"):
            fn(torch.tensor([[0.2, 0.2, 0.1]], dtype=D64), loose)
    line = torch.tensor([[0.0, 0], [1, 0], [2, 0], [1, 1e-17]], dtype=D64)
    with pytest.raises(DegenerateFaceError, match="encloses no area"):
        Cage(line)


def test_thin_but_valid_cages_stay_accepted() -> None:
    """The checks are relative: a slab 1e-5 thick, at any scale and far away, is a valid cage."""
    cube = _cube()
    for s, shift in ((1.0, 0.0), (1e-6, 1e-3), (1e6, 1e9)):
        v = cube.vertices * torch.tensor([1.0, 1.0, 1e-5], dtype=D64) * s + shift
        Cage(v, cube.faces)


@pytest.mark.parametrize("bad", [math.inf, -math.inf, math.nan])
def test_paths_that_skip_checks_do_not_answer_silently(bad: float) -> None:
    """NaN/inf vertices given through with_vertices, validate=False or validate="topology" raise a
    CageError naming the cage (not the points) in every closed-form family, batched or not."""
    cube = _cube()
    tri = cube.triangulated()
    v = cube.vertices.clone()
    v[3, 1] = bad
    x = torch.full((4, 3), 0.1, dtype=D64)
    cases = [
        (F.mean_value_coordinates, tri.with_vertices(v)),
        (F.green_coordinates, tri.with_vertices(v)),
        (F.mean_value_derivatives, tri.with_vertices(v)),
        (F.quad_mean_value_coordinates, cube.with_vertices(v)),
        (F.quad_green_coordinates, cube.with_vertices(v)),
        (F.mean_value_coordinates, Cage(v, tri.faces, validate=False)),
        (F.green_coordinates, Cage(torch.stack([tri.vertices, v]), tri.faces, validate="topology")),
    ]
    for fn, cage in cases:
        with pytest.raises(CageError, match="cage vertices contain NaN or inf"):
            fn(x, cage)


def test_a_flat_batch_element_given_without_checks_is_named() -> None:
    """A batch validated with ``validate="topology"`` whose element is folded flat raises, naming it."""
    tri = _cube().triangulated()
    flat = tri.vertices.clone()
    flat[:, 2] = flat[:, 2] * 1e-15  # folded onto z = 0: coincident to the relative tolerance
    cage = Cage(torch.stack([tri.vertices, tri.vertices * 3, flat]), tri.faces, validate="topology")
    with pytest.raises(DegenerateFaceError, match=r"batch element \(2,\)"):
        F.green_coordinates(torch.zeros(5, 3, dtype=D64), cage)


def test_checked_cages_are_checked_once() -> None:
    """A validated cage, its batch elements, triangulation and same-dtype copies are not checked again;
    a lower precision is (its rounding can merge vertices)."""
    cube = _cube()
    batch = Cage(torch.stack([cube.vertices, 2 * cube.vertices]), cube.faces)
    for c in (cube, cube.triangulated(), batch[1], batch.unbind()[0], cube.to(D64)):
        assert c._geometry_checked
    assert not cube.to(torch.float32)._geometry_checked
    assert not cube._like(cube.vertices.float())._geometry_checked
    loose = cube.with_vertices(cube.vertices * 2)
    assert not loose._geometry_checked
    assert loose.check_geometry()._geometry_checked


def test_cli_refuses_a_cage_with_coincident_vertices(tmp_path, capsys) -> None:
    """`torchcage deform` on a cube OBJ with one vertex moved onto its neighbour fails, naming the
    coincident vertices, for every method (it wrote NaN meshes, or blamed the points)."""
    from torchcage.cli import main

    args = cube_files(tmp_path)
    cube = torchcage.load_cage(tmp_path / "cage.obj")
    v = cube.vertices.clone()
    e = cube.unique_edges()[0].tolist()
    v[e[1]] = v[e[0]]
    lines = (tmp_path / "cage.obj").read_text().splitlines()
    vi = [k for k, line in enumerate(lines) if line.startswith("v ")]
    lines[vi[e[1]]] = "v " + " ".join(repr(float(t)) for t in v[e[1]])
    (tmp_path / "cage.obj").write_text("\n".join(lines) + "\n")
    for method in ("gc", "mvc"):
        out = tmp_path / method
        message = ""
        try:
            code = main([*args, "--out", str(out), "--method", method, "--no-picture"])
        except SystemExit as err:
            code = err.code
        except DegenerateFaceError as err:
            code, message = 2, str(err)
        text = capsys.readouterr()
        assert code not in (0, None)
        assert "coincide" in text.err + text.out + message
        written = list(out.glob("*.obj")) if out.exists() else []
        assert not written, f"{method}: wrote {written} for an invalid cage"


def test_topology_checked_once_never_hides_an_error() -> None:
    """Faces whose topology passed are not checked again (a training step builds a Cage on the same
    faces every call), yet faces that differ in any index, or in the vertex count, still are; the
    unique edges served from the check equal a fresh computation and a caller's change to them
    changes nothing."""
    from torchcage.cage import _TOPOLOGY_SEEN
    from torchcage.errors import CageOrientationError, CageTopologyError

    ico = icosphere()
    V, faces = ico.vertices.to(D64), ico.triangles.clone()
    first = Cage(V, faces, validate="topology")
    assert any(k[0] == V.shape[0] and k[1] == faces.numpy().tobytes() for k in _TOPOLOGY_SEEN)
    edges = first.unique_edges()
    assert torch.equal(edges, first._unique_edges())
    edges[0] = -1  # (a caller changing the returned edges)
    assert torch.equal(Cage(V, faces, validate="topology").unique_edges(), first._unique_edges())
    flipped = faces.clone()
    flipped[3] = flipped[3, [0, 2, 1]]  # one face reversed: inconsistent orientation
    with pytest.raises(CageOrientationError):
        Cage(V, flipped, validate="topology")
    dropped = faces[1:]  # an open surface
    with pytest.raises(CageTopologyError):
        Cage(V, dropped, validate="topology")
    with pytest.raises(CageError):  # the same faces over one vertex fewer: an index out of range
        Cage(V[:-1], faces, validate="topology")
