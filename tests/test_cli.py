"""The command line: demo and deform write meshes, cages and a picture."""

from __future__ import annotations

import torch
from support import cube_files

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

    image = Image.open(tmp_path / "deformation.png").convert("RGB")
    assert image.size[0] == 1600  # two 800-pixel panels, titles above, a legend below (issue 22 item 15)
    strip = {image.getpixel((x, y)) for x in range(0, 600, 2) for y in range(image.size[1] - 40, image.size[1])}

    def near(rgb):
        return any(max(abs(a - b) for a, b in zip(c, rgb, strict=True)) <= 2 for c in strip)

    assert near((115, 158, 217)) and near((230, 120, 20))  # the legend's mesh and cage swatches


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


def test_deform_lbc_formats_camera_and_strict(tmp_path, capsys):
    """Issue 22 items 4 and 14: --method lbc, --format, --up / camera, --strict."""
    args = cube_files(tmp_path)
    assert main([*args, "--out", str(tmp_path / "lbc"), "--method", "lbc", "--no-picture"]) == 0
    rest, _ = torchcage.load_mesh(tmp_path / "lbc" / "rest_mesh.obj")
    moved, _ = torchcage.load_mesh(tmp_path / "lbc" / "deformed_mesh.obj")
    assert torch.allclose(moved, rest * torch.tensor([1.5, 1.0, 1.0], dtype=rest.dtype), atol=1e-6)  # linear precision
    for method in ("hc", "mec"):  # (the volumetric and the positive coordinates: the same stretch)
        assert main([*args, "--out", str(tmp_path / method), "--method", method, "--no-picture"]) == 0
        moved, _ = torchcage.load_mesh(tmp_path / method / "deformed_mesh.obj")
        assert torch.allclose(moved, rest * torch.tensor([1.5, 1.0, 1.0], dtype=rest.dtype), atol=1e-6)
    assert main([*args, "--out", str(tmp_path / "up"), "--up", "y", "--azimuth", "60", "--elevation", "10"]) == 0
    assert (tmp_path / "up" / "deformation.png").exists()
    try:
        import trimesh  # noqa: F401
    except ImportError:
        pass
    else:
        assert main([*args, "--out", str(tmp_path / "ply"), "--format", "ply", "--no-picture"]) == 0
        v, f = torchcage.load_mesh(tmp_path / "ply" / "deformed_mesh.ply")
        assert v.shape == (42, 3) and f.shape == (80, 3)
    (tmp_path / "poke").mkdir()
    poke = cube_files(tmp_path / "poke", scale=1.4)  # the sphere pokes out of the cube a little
    capsys.readouterr()
    assert main([*poke, "--out", str(tmp_path / "gc0"), "--method", "gc", "--no-picture"]) == 0
    err = capsys.readouterr().err  # continued through the nearest faces, and said (issue 43 item 4: every point out)
    assert "points lie outside the cage" in err and "nearest faces" in err and err.count("outside the cage") == 1
    v0, _ = torchcage.load_mesh(tmp_path / "gc0" / "rest_mesh.obj")
    v1, _ = torchcage.load_mesh(tmp_path / "gc0" / "deformed_mesh.obj")
    assert (v1 - v0).norm(dim=1).max() < 1.0  # no point sent to the origin
    (tmp_path / "big").mkdir()
    outside = cube_files(tmp_path / "big", scale=3.0)  # far outside the cube
    capsys.readouterr()
    assert main([*outside, "--out", str(tmp_path / "gc"), "--method", "gc", "--no-picture"]) == 0
    assert "points lie outside the cage" in capsys.readouterr().err
    assert main([*outside, "--out", str(tmp_path / "gc2"), "--method", "gc", "--strict"]) == 2
    assert "--strict" in capsys.readouterr().err


def test_bench_validates_arguments(capsys):
    import pytest

    with pytest.raises(SystemExit) as info:
        main(["bench", "--points", "-5"])
    assert info.value.code == 2 and "positive integer" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["deform", "--help"])
    assert "qgc (quad Green" in capsys.readouterr().out
