"""Points outside the cage: `deform` and `torchcage deform` say so for every
family, with the count and how far; `outside="error"` / `--strict` refuse them; points inside
(or on the cage, rounded to float32) say nothing. Independent check: for the axis-aligned cube
[-1, 1]^3 a point lies outside iff some |x_i| > 1, at distance |max(|x| - 1, 0)|."""

from __future__ import annotations

import warnings

import pytest
import torch
from support import cube_files

import torchcage
from torchcage.cli import main
from torchcage.errors import OutsideCageWarning, PointsError
from torchcage.functional.deform import OUTSIDE_TOLERANCE, find_outside
from torchcage.methods import METHODS

f64 = torch.float64
CUBE = torchcage.load_cage(torchcage.data.path("cube.obj")).to(f64)  # [-1, 1]^3, quads
SIZE = 12**0.5


def _cube_truth(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mask of the points outside the cube and their distances to it (closed form)."""
    excess = (x.abs() - 1).clamp_min(0)
    d = excess.norm(dim=-1)
    return d > 0, d


def _points(n: int, spread: float, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g, dtype=f64) * 2 - 1) * spread


def test_find_outside_agrees_with_the_closed_form() -> None:
    x = _points(3000, 2.0)
    truth, d = _cube_truth(x)
    for cage in (CUBE, CUBE.triangulated()):
        r = find_outside(x, cage)
        assert torch.equal(r.mask, truth) and r.count == int(truth.sum()) and r.total == 3000
        assert r.max_distance == pytest.approx(float(d.max()) / SIZE, rel=1e-12)
    # batched: one cage of the batch scaled by 3 holds every point; the other does not
    batch = torchcage.Cage(torch.stack([CUBE.vertices, 3 * CUBE.vertices]), CUBE.faces)
    r = find_outside(x, batch)
    assert r.mask.shape == (2, 3000) and torch.equal(r.mask[0], truth) and not bool(r.mask[1].any())
    assert r.total == 6000 and r.count == int(truth.sum())
    # 2D: the unit square, crossing rule then distance
    square = torchcage.Cage(torch.tensor([[0.0, 0], [1, 0], [1, 1], [0, 1]], dtype=f64))
    y = torch.tensor([[0.5, 0.5], [1.5, 0.5], [0.5, -2.0], [1.0, 0.5]], dtype=f64)
    r = find_outside(y, square)
    assert r.mask.tolist() == [False, True, True, False] and r.max_distance == pytest.approx(2.0 / 2**0.5)


def test_points_on_the_cage_are_not_outside() -> None:
    """Cage vertices, face centres and points within the tolerance: none reported; float32 copies
    (rounded off the cage) neither."""
    faces = CUBE.triangulated().vertices[CUBE.triangulated().triangles].mean(1)
    on = torch.cat([CUBE.vertices, faces, faces * (1 + 0.5 * OUTSIDE_TOLERANCE * SIZE)])
    assert find_outside(on, CUBE).count == 0
    moved = CUBE.vertices * 1e3 + 1e4  # far from the origin: the float32 rounding is larger than the tolerance
    cage32 = torchcage.Cage(moved.float(), CUBE.faces)
    pts32 = (torch.cat([moved, moved[CUBE.triangulated().triangles].mean(1)]) * (1 + 1e-7)).float()
    assert find_outside(pts32, cage32).count == 0
    assert find_outside(on * (1 + 10 * OUTSIDE_TOLERANCE * SIZE), CUBE).count == on.shape[0]


@pytest.mark.parametrize("method", ["mvc", "qmvc", "gc", "qgc"])
def test_deform_warns_for_every_family_with_count_and_distance(method: str) -> None:
    cage = CUBE.triangulated() if method in ("mvc", "gc") else CUBE
    x = _points(200, 30.0, seed=1)  # a mesh 30 times the cage
    truth, d = _cube_truth(x)
    with pytest.warns(OutsideCageWarning) as caught:
        torchcage.deform(x, cage, 2 * cage.vertices, method)
    (w,) = [w for w in caught if issubclass(w.category, OutsideCageWarning)]
    text = str(w.message)
    assert f"{int(truth.sum())} of 200 points lie outside the cage" in text
    assert f"up to {float(d.max()) / SIZE:.3g} of its size" in text
    with pytest.raises(PointsError, match="lie outside the cage"):
        torchcage.deform(x, cage, cage.vertices, method, outside="error")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        torchcage.deform(x, cage, cage.vertices, method, outside="ignore")
        inside = _points(200, 0.99, seed=2)
        torchcage.deform(inside, cage, 2 * cage.vertices, method)  # inside: nothing said
    with pytest.raises(ValueError, match="outside must be one of"):
        torchcage.deform(inside, cage, cage.vertices, method, outside="maybe")


def test_deform_batch_shapes_are_checked() -> None:
    """Two rest cages and three deformed cages is a clear error, not a torch
    broadcasting failure; the shapes that do broadcast agree with one call per cage."""
    tri = CUBE.triangulated()
    rest = torch.stack([tri.vertices, 1.5 * tri.vertices])
    batch = torchcage.Cage(rest, tri.triangles)
    x = _points(20, 0.9, seed=3)
    for method in ("mvc", "gc"):
        with pytest.raises(ValueError, match=r"batched rest cage of batch shape \(2,\).*must end with \(2,\)"):
            torchcage.deform(x, batch, tri.vertices.expand(3, -1, -1), method)
        poses = torch.stack([rest + k for k in range(3)])  # (3, 2, V, 3): three poses of each
        y = torchcage.deform(x, batch, poses, method)
        assert y.shape == (3, 2, 20, 3)
        for b in range(2):
            one = torchcage.deform(x, torchcage.Cage(rest[b], tri.triangles), poses[:, b], method)
            torch.testing.assert_close(y[:, b], one, rtol=1e-12, atol=1e-12)
        shared = torchcage.deform(x, batch, 2 * tri.vertices, method)  # one pose for both rest cages
        assert shared.shape == (2, 20, 3)


def _cli(tmp_path, scale: float) -> list[str]:
    tmp_path.mkdir(exist_ok=True)
    return cube_files(tmp_path, scale=scale)


@pytest.mark.parametrize("method", METHODS)
def test_cli_strict_refuses_a_mesh_outside_for_every_method(tmp_path, capsys, method: str) -> None:
    args = _cli(tmp_path / "big", 30.0)  # the sphere's 42 vertices, all 30 times outside the cube
    assert main([*args, "--out", str(tmp_path / "o"), "--method", method, "--strict", "--no-picture"]) == 2
    err = capsys.readouterr().err
    assert "42 of 42 points lie outside the cage" in err and "--strict" in err
    assert not (tmp_path / "o" / "deformed_mesh.obj").exists()


@pytest.mark.parametrize("method", ["mvc", "qmvc", "gc", "qgc", "hc"])
def test_cli_warns_for_a_mesh_outside_and_not_for_one_inside(tmp_path, capsys, method: str) -> None:
    args = _cli(tmp_path / "big", 30.0)
    assert main([*args, "--out", str(tmp_path / "o"), "--method", method, "--no-picture"]) == 0
    err = capsys.readouterr().err
    assert err.count("torchcage: warning: 42 of 42 points lie outside the cage, up to") == 1, err
    assert "Warning:" not in err and "warnings.warn" not in err  # one clean line each, no raw Python warning
    args = _cli(tmp_path / "small", 0.5)
    assert main([*args, "--out", str(tmp_path / "i"), "--method", method, "--strict", "--no-picture"]) == 0
    assert "outside" not in capsys.readouterr().err


def test_deform_checks_the_cage_before_the_outside_test_and_keeps_no_graph() -> None:
    """A damaged predicted cage is refused by the coordinate function's own check (not by the
    outside test); a rest cage that requires grad is tested without a graph and without torch's
    'requires_grad to a scalar' warning, and its gradient is what it is without the test."""
    tri = CUBE.triangulated()
    bad = tri.vertices.clone()
    bad[3] = float("nan")
    with pytest.raises(torchcage.CageError):
        torchcage.deform(_points(5, 0.5), tri.with_vertices(bad), tri.vertices)
    rest = tri.vertices.clone().requires_grad_()
    x = torch.cat([_points(30, 0.9, seed=4), torch.tensor([[3.0, 0.0, 0.0]], dtype=f64)])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        y = torchcage.deform(x, tri.with_vertices(rest), 2 * rest.detach())
    assert [str(w.message).split(":")[0] for w in caught] == [
        "1 of 31 points lie outside the cage, up to 0.577 of its size (bounding-box diagonal) away from it"
    ]
    (g,) = torch.autograd.grad(y.sum(), rest)
    rest2 = tri.vertices.clone().requires_grad_()
    y2 = torchcage.deform(x, tri.with_vertices(rest2), 2 * rest2.detach(), outside="ignore")
    (g2,) = torch.autograd.grad(y2.sum(), rest2)
    assert torch.equal(y, y2) and torch.equal(g, g2)
