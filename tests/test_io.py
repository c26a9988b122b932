"""OBJ reading and writing (polygons kept), mesh I/O through trimesh."""

from __future__ import annotations

import pytest
import torch
from support import box_cage

import torchcage


def test_obj_forms_negative_indices_and_comments(tmp_path):
    text = """# a cube, with every face form
v -1 -1 -1
v 1 -1 -1
v 1 1 -1
v -1 1 -1   # trailing comment
v -1 -1 1
v 1 -1 1
v 1 1 1
v -1 1 1
vt 0 0
vn 0 0 1
f 1/1 4/1 3/1 2/1
f 5//1 6//1 7//1 8//1
f 1/1/1 2/1/1 6/1/1 5/1/1
f -7 -6 -2 -3
f 3 4 8 7
f 4 1 5 8
"""
    p = tmp_path / "cube.obj"
    p.write_text(text)
    cage = torchcage.load_cage(p)
    ref = torchcage.load_cage(torchcage.data.path("cube.obj"))
    assert torch.equal(cage.vertices, ref.vertices) and torch.equal(cage.quads, ref.quads)


def test_large_polygon_and_bad_lines(tmp_path):
    p = tmp_path / "bad.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0.5 1.5 0\nf 1 2 3 4 5\n")
    with pytest.raises(torchcage.CageError, match="more than four corners"):
        torchcage.load_cage(p)
    p.write_text("v 0 0 0\nv 1 0\n")
    with pytest.raises(torchcage.CageError, match=r"bad.obj:2"):
        torchcage.load_cage(p)
    p.write_text("v 0 0 0\nf 1 2 3\n")
    with pytest.raises(torchcage.CageError, match="out of range"):
        torchcage.load_cage(p)


def test_cage_round_trip_keeps_quads(tmp_path):
    cage = box_cage(2, 1, 3)
    out = tmp_path / "c.obj"
    torchcage.save_cage(out, cage)
    back = torchcage.load_cage(out)
    assert torch.equal(back.quads, cage.quads) and torch.equal(back.vertices, cage.vertices)
    moved = cage.vertices * 2
    torchcage.save_cage(out, cage, moved)
    assert torch.equal(torchcage.load_cage(out).vertices, moved)


def test_2d_cage_round_trip(tmp_path):
    cage = torchcage.Cage([[0.0, 0], [2, 0], [2, 1], [0, 1.5]])
    out = tmp_path / "p.obj"
    torchcage.save_cage(out, cage)
    back = torchcage.load_cage(out)
    assert back.dim == 2 and torch.equal(back.vertices, cage.vertices)


def test_mesh_io_obj_and_trimesh_formats(tmp_path):
    pytest.importorskip("trimesh")
    v, f = torchcage.load_mesh(torchcage.data.path("bar.obj"))
    for ext in ("obj", "ply", "stl", "off"):
        out = tmp_path / f"m.{ext}"
        torchcage.save_mesh(out, v, f)
        v2, f2 = torchcage.load_mesh(out)
        if ext != "stl":  # STL stores unindexed triangles
            assert torch.allclose(v2, v, atol=1e-6) and torch.equal(f2, f)
        assert f2.shape == f.shape
