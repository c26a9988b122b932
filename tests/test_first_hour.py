"""What a newcomer meets in the first hour: empty point sets give empty results, and a batch of
point sets given to a module is refused with a message saying what to do."""

from __future__ import annotations

import functools
import warnings
from pathlib import Path

import pytest
import torch

import torchcage
from torchcage import functional as F
from torchcage.errors import PointsError

f64 = torch.float64


@pytest.fixture(scope="module")
def cubes() -> tuple[torchcage.Cage, torchcage.Cage]:
    quads = torchcage.load_cage(torchcage.data.path("cube.obj"))
    return quads, quads.triangulated()


MODULES = {
    "mvc": (torchcage.MeanValueCoordinates, 1),
    "gc": (torchcage.GreenCoordinates, 1),
    "qmvc": (torchcage.QuadMeanValueCoordinates, 0),
    "qgc": (torchcage.QuadGreenCoordinates, 0),
    # a coarse interior mesh: these tests check shapes and errors, not the solve
    "lbc": (functools.partial(torchcage.LocalBarycentricCoordinates, target_cells=300), 1),
}


@pytest.mark.parametrize("name", sorted(MODULES))
def test_modules_accept_an_empty_point_set(cubes, name: str) -> None:
    cls, triangulated = MODULES[name]
    cage = cubes[triangulated]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = cls(cage, torch.zeros(0, 3, dtype=f64))
    assert m(cage.vertices).shape == (0, 3)
    assert m(torch.stack([cage.vertices, 2 * cage.vertices])).shape == (2, 0, 3)


def test_functions_return_empty_results(cubes) -> None:
    quads, tri = cubes
    e = torch.zeros(0, 3, dtype=f64)
    assert F.mean_value_coordinates(e, tri).shape == (0, 8)
    assert [t.shape for t in F.green_coordinates(e, tri)] == [(0, 8), (0, 12)]
    assert [t.shape for t in F.quad_green_coordinates(e, quads)] == [(0, 8), (0, 24)]
    assert F.quad_mean_value_coordinates(e, quads).shape == (0, 8)
    assert F.mean_value_derivatives(e, tri)[2].shape == (0, 8, 3, 3)
    # leading shapes are kept, empty or not
    assert [t.shape for t in F.green_coordinates(torch.zeros(2, 0, 3, dtype=f64), tri)] == [(2, 0, 8), (2, 0, 12)]


@pytest.mark.parametrize("name", sorted(MODULES))
def test_modules_refuse_a_batch_of_point_sets(cubes, name: str) -> None:
    cls, triangulated = MODULES[name]
    with pytest.raises(PointsError, match=r"one point set of shape \(N, 3\), got \(2, 5, 3\).*batched cage"):
        cls(cubes[triangulated], torch.zeros(2, 5, 3, dtype=f64))


def test_load_mesh_refuses_garbage_and_missing_files(tmp_path) -> None:
    garbage = tmp_path / "garbage.obj"
    garbage.write_text("this is not a mesh\n")
    with pytest.raises(ValueError, match=r"garbage\.obj: no vertices found"):
        torchcage.load_mesh(garbage)
    with pytest.raises(FileNotFoundError, match=r"missing\.ply"):
        torchcage.load_mesh(tmp_path / "missing.ply")
    with pytest.raises(FileNotFoundError, match=r"missing\.obj"):
        torchcage.load_mesh(tmp_path / "missing.obj")


def test_save_mesh_validates_faces(tmp_path) -> None:
    v = torch.rand(4, 3, dtype=f64)
    with pytest.raises(TypeError, match="integer vertex indices"):
        torchcage.save_mesh(tmp_path / "a.obj", v, torch.tensor([[0, 2, 3.7]]))
    with pytest.raises(ValueError, match=r"must lie in \[0, 4\)"):
        torchcage.save_mesh(tmp_path / "a.obj", v, torch.tensor([[0, 2, 4]]))
    with pytest.raises(ValueError, match=r"\(F, 3\) or \(F, 4\)"):
        torchcage.save_mesh(tmp_path / "a.obj", v, torch.tensor([0, 1, 2]))
    torchcage.save_mesh(tmp_path / "ok.obj", v, torch.tensor([[0, 1, 2], [0, 2, 3]]))
    v2, f2 = torchcage.load_mesh(tmp_path / "ok.obj")
    assert torch.equal(f2, torch.tensor([[0, 1, 2], [0, 2, 3]])) and torch.allclose(v2, v)


def test_cli_deform_fails_on_a_garbage_mesh(tmp_path, capsys) -> None:
    from torchcage.cli import main

    garbage = tmp_path / "garbage.obj"
    garbage.write_text("nothing here\n")
    cage, deformed = torchcage.data.path("bar_cage.obj"), torchcage.data.path("bar_cage_deformed.obj")
    argv = ["deform", "--cage", str(cage), "--deformed", str(deformed), "--mesh", str(garbage), "--out", str(tmp_path)]
    assert main([*argv, "--no-picture"]) == 2
    assert "no vertices found" in capsys.readouterr().err
    assert not list(tmp_path.glob("*deformed*"))


def test_plain_python_inputs(cubes) -> None:
    """Item 11: lists as points; a (vertices, faces) pair as a cage is refused with what to pass."""
    quads, tri = cubes
    pts = [[0.1, 0.2, 0.3], [-0.5, 0.0, 0.25]]
    x = torch.tensor(pts, dtype=f64)
    assert torch.equal(F.mean_value_coordinates(pts, tri), F.mean_value_coordinates(x, tri))
    assert torch.equal(F.green_coordinates(pts, tri)[1], F.green_coordinates(x, tri)[1])
    assert torch.equal(F.quad_mean_value_coordinates(pts, quads), F.quad_mean_value_coordinates(x, quads))
    assert torch.equal(F.quad_green_coordinates(pts, quads)[0], F.quad_green_coordinates(x, quads)[0])
    assert torch.equal(F.mean_value_derivatives(pts, tri)[1], F.mean_value_derivatives(x, tri)[1])
    for fn in (F.mean_value_coordinates, F.green_coordinates, F.quad_mean_value_coordinates):
        with pytest.raises(TypeError, match=r"torchcage.Cage\(vertices, faces\)"):
            fn(pts, (tri.vertices, tri.triangles))


@pytest.mark.parametrize("name", sorted(MODULES))
def test_meta_device_is_refused_clearly(cubes, name: str) -> None:
    """Item 12: no coordinates on the meta device: a clear error instead of one from deep in torch."""
    cls, triangulated = MODULES[name]
    cage = cubes[triangulated].to("meta")
    with pytest.raises(PointsError, match="meta device"):
        cls(cage, torch.zeros(4, 3, dtype=f64, device="meta"))


def test_cage_owns_its_vertices() -> None:
    """Item 13: editing the caller's tensor after validation does not change the cage; gradients
    still reach the caller's tensor."""
    v = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated().vertices.clone().requires_grad_()
    cage = torchcage.Cage(v, torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated().triangles)
    with torch.no_grad():
        v[0] = float("nan")
    assert torch.isfinite(cage.vertices).all()
    arr = cage.vertices.detach().numpy().copy()
    from_array = torchcage.Cage(arr, cage.triangles)
    arr[:] = 0.0
    assert from_array.vertices.abs().max() > 0
    v2 = cage.vertices.detach().clone().requires_grad_()
    c2 = torchcage.Cage(v2, cage.triangles)
    F.mean_value_coordinates(torch.zeros(1, 3, dtype=f64), c2).square().sum().backward()
    assert v2.grad is not None and torch.isfinite(v2.grad).all()


@pytest.mark.parametrize("name", sorted(MODULES))
def test_nan_pose_is_refused(cubes, name: str) -> None:
    """Item 9: NaN in a deformed pose raises, unless the check is switched off for a hot loop."""
    cls, triangulated = MODULES[name]
    cage = cubes[triangulated]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = cls(cage, torch.tensor([[0.1, 0.2, 0.3]], dtype=f64))
    pose = cage.vertices.clone()
    pose[3, 1] = float("nan")
    with pytest.raises(ValueError, match=r"NaN or inf \(indices \[\[3\]\]\).*check_inputs = False"):
        m(pose)
    m.check_inputs = False
    assert m(pose).shape == (1, 3)


def test_messages_say_what_is_wrong(tmp_path) -> None:
    """Item 10: an empty OBJ, a 2D cage given to quad Green coordinates, huge coordinates."""
    (tmp_path / "empty.obj").write_text("# nothing here\n")
    with pytest.raises(torchcage.CageError, match="no vertices"):
        torchcage.load_cage(tmp_path / "empty.obj")
    square = torchcage.Cage([[0.0, 0], [1, 0], [1, 1], [0, 1]])
    with pytest.raises(torchcage.CageError, match="quad Green coordinates need a 3D cage; use green_coordinates"):
        torchcage.QuadGreenCoordinates(square, torch.zeros(1, 2, dtype=f64))
    cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
    with pytest.raises(torchcage.CageError, match="overflow"):
        torchcage.Cage(cube.vertices * 1e200, cube.faces)
    torchcage.Cage(cube.vertices * 1e40, cube.faces)  # large but safe: accepted


def test_self_intersecting_cages_are_refused() -> None:
    """Item 10: a bow-tie polygon and a 3D cage pushed through itself name the crossing pair; an
    independent check: the crossing point lies on both the edge and the face."""
    with pytest.raises(torchcage.CageTopologyError, match=r"edges 0 \[0, 1\] and 2 \[2, 3\] cross"):
        # (an uneven bow-tie: a symmetric one encloses no net area and is refused as flat first)
        torchcage.Cage([[0.0, 0], [1, 1], [1, 0], [0, 2]])
    cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
    v = cube.vertices.clone()
    v[0] = -1.5 * v[0]  # corner 0 pushed through the opposite corner's faces
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(torchcage.CageTopologyError, match=r"intersects itself: edge \[\d+, \d+\] passes through"):
            torchcage.Cage(v, cube.triangles)
        torchcage.Cage(v, cube.triangles, check_intersections=False)  # the big-cage escape hatch
    from torchcage._intersections import edge_triangle_crossings

    edges = cube.unique_edges()
    for e, t in edge_triangle_crossings(v, edges, cube.triangles).tolist():
        p, q = v[edges[e]]
        a, b, c = v[cube.triangles[t]]
        n = torch.linalg.cross(b - a, c - a)
        s = ((a - p) @ n) / ((q - p) @ n)
        y = p + s * (q - p)  # the segment meets the plane here: inside the triangle
        bary = torch.linalg.solve(torch.stack([b - a, c - a, n], 1), y - a)
        assert 0 < s < 1 and bary[0] > 0 and bary[1] > 0 and bary[0] + bary[1] < 1
    # one batch element is named
    from torchcage.testing import icosphere

    ico = icosphere()
    V = torch.stack([ico.vertices, ico.vertices.clone()])
    V[1, 0] = -1.3 * V[1, 0]  # a vertex pulled through the far side of element 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(torchcage.CageError, match=r"batch element \(1,\)"):
            torchcage.Cage(V, ico.triangles)


def test_data_set_deformed_pose_that_folds() -> None:
    """The data set's deformed Beast cage passes through itself (found by the check above; the
    crossings persist with either quad diagonal): refused as a cage, read as a pose."""
    from support import data_path

    path = data_path("qmvc", "Beast_Cage_Deformed.obj")
    with pytest.raises(torchcage.CageTopologyError, match="intersects itself"):
        torchcage.load_cage(path)
    assert torchcage.load_cage(path, check_intersections=False).num_vertices == 152


def test_native_library_built_at_install_is_preferred(monkeypatch) -> None:
    """Item 1: where an install built the kernels (pip install -e . in CI), they load without any
    compilation; a build from other sources (stale) is never loaded."""
    from torchcage.backends import native as _native

    if not _native.available():
        pytest.skip(f"no native library: {_native.failure_reason()}")
    built = list((_native.Path(_native.__file__).parent).glob("_kernels*"))
    if not built:
        pytest.skip("no library built at install time here (the run-time build serves)")
    assert _native.variant().startswith("prebuilt"), _native.variant()
    assert _native._load_prebuilt() is not None
    monkeypatch.setattr(_native.build_spec, "source_digest", lambda folder: "0" * 16)
    assert _native._load_prebuilt() is None  # a digest mismatch: stale, refused


EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_green_jacobian_example_names_the_extra_when_matplotlib_is_missing() -> None:
    """No raw ModuleNotFoundError; the message names the extra (pyproject's
    `examples` extra brings matplotlib)."""
    import subprocess
    import sys

    script = (
        "import sys, runpy; sys.modules['matplotlib'] = None; sys.argv = ['x', 'unused.png']; "
        f"runpy.run_path({str(EXAMPLES / 'green_jacobian.py')!r}, run_name='__main__')"
    )
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert run.returncode != 0
    assert "pip install 'torchcage[examples]'" in run.stderr and "matplotlib" in run.stderr
    assert "Traceback" not in run.stderr and "ModuleNotFoundError" not in run.stderr


def test_coordinate_field_picture_has_a_title_and_a_colour_scale(tmp_path) -> None:
    """The 2D field picture has a title strip and a colour scale whose colours
    are render_field_2d's own: red at +1 (top), white at 0, blue at -1 (bottom)."""
    import importlib.util

    from PIL import Image

    spec = importlib.util.spec_from_file_location("coordinate_field_2d", EXAMPLES / "coordinate_field_2d.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    out = tmp_path / "field.png"
    example.main(str(out), size=120)
    image = Image.open(out).convert("RGB")
    assert image.size == (120 + example.SCALE_WIDTH, 120 + example.TITLE_HEIGHT)
    title = [image.getpixel((x, y)) for x in range(image.size[0]) for y in range(example.TITLE_HEIGHT)]
    assert sum(max(p) < 100 for p in title) > 50  # dark text on the white strip
    x = 120 + 12 + example.BAR_WIDTH // 2
    top, middle, bottom = (image.getpixel((x, example.TITLE_HEIGHT + y)) for y in (2, 60, 117))
    assert top[0] > 200 and top[1] < 60 and top[2] < 60  # red: +1
    assert min(middle) > 200  # white: 0
    assert bottom[2] > 200 and bottom[0] < 60 and bottom[1] < 60  # blue: -1
    labels = [image.getpixel((px, y)) for px in range(x + 14, image.size[0]) for y in range(40, 150)]
    assert sum(max(p) < 100 for p in labels) > 30  # the scale's numbers
