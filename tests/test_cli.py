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
    assert image.size[0] == 1600  # two 800-pixel panels, titles above, a legend below
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
    """--method lbc, --format, --up / camera, --strict."""
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
    err = capsys.readouterr().err  # continued through the nearest faces, and said (every point out)
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


def test_bench_prints_as_it_goes_and_names_the_kernel_library(capsys, monkeypatch):
    """The header and the kernel library are out before the first measurement
    ends, and each row as it is measured; every option has help."""
    import pytest

    import torchcage._timing
    from torchcage.backends import native as _native
    from torchcage.cli import kernel_library

    seen = []
    real = torchcage._timing.best_of

    def spy(fn, repeat):
        seen.append(capsys.readouterr().out)  # what was printed before this measurement
        return real(fn, repeat)

    monkeypatch.setattr(torchcage._timing, "best_of", spy)
    assert main(["bench", "--points", "500", "--repeat", "1"]) == 0
    rest = capsys.readouterr().out
    backends = (["native"] if _native.available() else []) + ["torch"]
    assert len(seen) == len(backends)
    assert "mean value coordinates: 500 points" in seen[0] and f"kernels: {kernel_library()}" in seen[0]
    assert "Mpts/s" in seen[0] and not any(line.startswith(backends[0]) for line in seen[0].splitlines())
    if len(backends) == 2:  # the native row is out before the torch measurement starts
        assert seen[1].startswith("native") and "torch" not in seen[1]
    assert rest.startswith("torch")
    library = kernel_library()
    assert library.startswith("native (") if _native.available() else library.startswith("torch (native kernels")
    with pytest.raises(SystemExit):
        main(["bench", "--help"])
    text = capsys.readouterr().out
    assert "--points POINTS  random points" in text and "--repeat REPEAT  timed runs" in text


def test_version_and_extras_in_help(capsys):
    from importlib.metadata import version

    import pytest

    from torchcage.methods import METHOD_EXTRAS

    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0 and capsys.readouterr().out.strip() == f"torchcage {version('torchcage')}"
    with pytest.raises(SystemExit):
        main(["--help"])
    top = " ".join(capsys.readouterr().out.split())
    assert "--method lbc, hc, bbw need pip install 'torchcage[lbc]'" in top and "'torchcage[cage]'" in top
    with pytest.raises(SystemExit):
        main(["deform", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for method, extra in METHOD_EXTRAS.items():
        assert f"needs torchcage[{extra}]" in text.split(f"{method} (")[1].split(")")[0]
    assert "mvc (mean value, any closed cage, quads split)" in text  # no extra named for the others


def test_extras_named_in_help_are_the_ones_pyproject_declares():
    """The methods solved on a mesh of the interior import scipy; the extra the help names brings it."""
    from pathlib import Path

    import pytest

    from torchcage.methods import METHOD_EXTRAS

    tomllib = pytest.importorskip("tomllib")  # (Python >= 3.11)

    extras = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    for extra in set(METHOD_EXTRAS.values()):
        assert any(dep.startswith("scipy") for dep in extras[extra])
    assert any(dep.startswith("matplotlib") for dep in extras["examples"])  # examples/green_jacobian.py's message


def test_warnings_print_as_one_clean_line(tmp_path, capsys):
    """An inverted cage flips with a warning: on the command line it is one line, no Python frame."""
    args = cube_files(tmp_path)
    for name in ("cage.obj", "pose.obj"):  # both files turned inside out (faces reversed)
        p = tmp_path / name
        p.write_text(
            "".join(
                " ".join(["f", *line.split()[1:][::-1]]) + "\n" if line.startswith("f ") else line + "\n"
                for line in p.read_text().splitlines()
            )
        )
    assert main([*args, "--out", str(tmp_path / "o"), "--no-picture"]) == 0
    err = capsys.readouterr().err.splitlines()
    flips = [line for line in err if "oriented inward" in line]
    assert flips and all(line.startswith("torchcage: warning: the cage is oriented inward") for line in flips)
    assert not any("UserWarning" in line or "warnings.warn" in line or ".py:" in line for line in err), err


def test_ply_without_trimesh_says_writing(tmp_path, capsys, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "trimesh", None)  # import trimesh raises ImportError
    args = cube_files(tmp_path)
    assert main([*args, "--out", str(tmp_path / "o"), "--format", "ply", "--no-picture"]) == 2
    err = capsys.readouterr().err
    assert "writing this mesh format needs trimesh: pip install 'torchcage[mesh]'" in err and "reading" not in err


def test_up_axis_default_and_auto_rule(capsys):
    """--up defaults to auto: y (the OBJ convention) unless the mesh stands
    along z; models of the data set's kind (y-up, long along x, thin along z) are not laid down."""
    import pytest

    from torchcage.cli import UP_Z_RATIO, up_axis

    def box(x, y, z):
        return torch.tensor([[0.0, 0.0, 0.0], [x, y, z]])

    assert up_axis("auto", box(1, 1, 3)) == "z"  # the bundled bar stands along z
    assert up_axis("auto", box(2.0, 0.51, 0.45)) == "y"  # a bench: longest along x
    assert up_axis("auto", box(1.0, 0.92, 0.42)) == "y"  # an animal: thinnest along z, yet z is not up
    assert up_axis("auto", box(1.24, 1.84, 1.71)) == "y"  # a head, y-up
    assert up_axis("auto", box(1, 1, 0.99 * UP_Z_RATIO)) == "y" and up_axis("auto", box(1, 1, UP_Z_RATIO)) == "z"
    assert all(up_axis(a, box(1, 1, 3)) == a for a in "xyz")
    with pytest.raises(ValueError, match="up must be one of"):
        up_axis("w", box(1, 1, 1))
    for command in ("make-cage", "deform", "view"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert "{auto,x,y,z}" in text and "auto (default)" in text and "else y (the OBJ convention" in text


def test_view_resolves_up_auto(tmp_path, monkeypatch):
    """`torchcage view` hands the editor the axis that --up auto chose (z for the standing bar, y
    for a mesh longest along x); an explicit axis passes through."""
    import torchcage.viewer as viewer_module

    seen = []

    def fake_view(mesh, cage, **options):
        seen.append(options["up"])
        raise ValueError("stop here")  # (the CLI turns it into exit code 2)

    monkeypatch.setattr(viewer_module, "view", fake_view)
    d = torchcage.data
    bar = ["view", "--mesh", str(d.path("bar.obj")), "--cage", str(d.path("bar_cage.obj")), "--no-browser"]
    assert main(bar) == 2 and seen[-1] == "z"
    v, f = torchcage.load_mesh(d.path("bar.obj"))
    torchcage.save_mesh(tmp_path / "lying.obj", v[:, [2, 0, 1]], f)  # the bar laid along x
    cage = torchcage.load_cage(d.path("bar_cage.obj"))
    torchcage.save_cage(tmp_path / "lying_cage.obj", cage, cage.vertices[:, [2, 0, 1]])
    lying = ["view", "--mesh", str(tmp_path / "lying.obj"), "--cage", str(tmp_path / "lying_cage.obj"), "--no-browser"]
    assert main(lying) == 2 and seen[-1] == "y"
    assert main([*lying, "--up", "x"]) == 2 and seen[-1] == "x"
