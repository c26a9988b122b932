"""The command line: demo and deform write meshes, cages and a picture."""

from __future__ import annotations

import torch

import torchcage
from torchcage.cli import main


def test_demo_writes_everything(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path)]) == 0
    names = {p.name for p in tmp_path.iterdir()}
    assert {"rest_mesh.obj", "deformed_mesh.obj", "rest_cage.obj", "deformed_cage.obj", "deformation.png"} <= names
    printed = capsys.readouterr().out
    assert "wrote:" in printed and "coordinates" in printed and " ms" in printed
    rest, f = torchcage.load_mesh(tmp_path / "rest_mesh.obj")
    moved, f2 = torchcage.load_mesh(tmp_path / "deformed_mesh.obj")
    assert torch.equal(f, f2) and rest.shape == moved.shape and not torch.allclose(rest, moved)
    # The written deformed mesh is what the module gives for the written deformed cage.
    cage = torchcage.load_cage(tmp_path / "rest_cage.obj")
    pose = torchcage.load_cage(tmp_path / "deformed_cage.obj")
    expect = torchcage.MeanValueCoordinates(cage.triangulated(), rest)(pose.vertices)
    assert torch.allclose(expect, moved, atol=1e-12)
    from PIL import Image

    assert Image.open(tmp_path / "deformation.png").size[0] > 400


def test_deform_user_files_and_errors(tmp_path, capsys):
    d = torchcage.data
    out = tmp_path / "o"
    args = ["deform", "--cage", str(d.path("bar_cage.obj")), "--deformed", str(d.path("bar_cage_deformed.obj"))]
    assert main([*args, "--mesh", str(d.path("bar.obj")), "--out", str(out), "--no-picture"]) == 0
    assert (out / "deformed_mesh.obj").exists() and not (out / "deformation.png").exists()
    bad = ["deform", "--cage", str(d.path("bar_cage.obj")), "--deformed", str(d.path("cube.obj"))]
    assert main([*bad, "--mesh", str(d.path("bar.obj")), "--out", str(out)]) == 2
    assert "deformed cage" in capsys.readouterr().err


def test_bench(capsys):
    assert main(["bench", "--points", "2000", "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    assert "torch" in out and "Mpts/s" in out


def test_demo_with_green_coordinates(tmp_path):
    assert main(["demo", "--out", str(tmp_path), "--method", "gc"]) == 0
    assert main(["demo", "--out", str(tmp_path / "q"), "--method", "qmvc"]) == 0
    assert (tmp_path / "q" / "deformed_mesh.obj").exists()
    assert main(["demo", "--out", str(tmp_path / "g"), "--method", "qgc"]) == 0
    assert (tmp_path / "g" / "deformed_mesh.obj").exists()
    rest, _ = torchcage.load_mesh(tmp_path / "rest_mesh.obj")
    moved, _ = torchcage.load_mesh(tmp_path / "deformed_mesh.obj")
    cage = torchcage.load_cage(tmp_path / "rest_cage.obj")
    pose = torchcage.load_cage(tmp_path / "deformed_cage.obj")
    expect = torchcage.GreenCoordinates(cage.triangulated(), rest)(pose.vertices)
    assert torch.allclose(expect, moved, atol=1e-12)
