"""Static check of the public API as a user's code sees it: run by mypy in CI
(``mypy``, configured in pyproject.toml), never called at run time. Each ``assert_type`` fails
the check when torchcage's annotations are lost (no ``py.typed``: every name is ``Any``) or
wrong; the functions are not called, so importing this module (pytest's doctest collection
does) runs nothing."""

from __future__ import annotations

import torch
from typing_extensions import assert_type

import torchcage
from torchcage import functional as F
from torchcage.functional.deform import Outside, find_outside


def _cages_and_io(path: str) -> None:
    cage = torchcage.load_cage(path)
    assert_type(cage, torchcage.Cage)
    assert_type(cage.triangulated(), torchcage.Cage)
    assert_type(cage.vertices, torch.Tensor)
    assert_type(cage.num_vertices, int)
    assert_type(cage.scale, float)
    assert_type(cage.triangle_normals(), torch.Tensor)
    vertices, faces = torchcage.load_mesh(path)
    assert_type(vertices, torch.Tensor)
    assert_type(faces, torch.Tensor)
    assert_type(torchcage.save_mesh(path, vertices, faces), None)
    assert_type(torchcage.make_cage(vertices, faces, target_vertices=100), torchcage.Cage)


def _functional(points: torch.Tensor, cage: torchcage.Cage) -> None:
    assert_type(F.mean_value_coordinates(points, cage), torch.Tensor)
    assert_type(F.quad_mean_value_coordinates(points, cage), torch.Tensor)
    assert_type(F.green_coordinates(points, cage), tuple[torch.Tensor, torch.Tensor])
    assert_type(F.local_barycentric_coordinates(points, cage), torch.Tensor)
    lam, grad, hess = F.mean_value_derivatives(points, cage, order=2)
    assert_type(lam, torch.Tensor)
    assert_type(grad, torch.Tensor)
    assert_type(hess, torch.Tensor | None)
    assert_type(torchcage.deform(points, cage, cage.vertices, "gc"), torch.Tensor)
    found = find_outside(points, cage)
    assert_type(found, Outside)
    assert_type(found.count, int)
    assert_type(found.message(), str)


def _modules(points: torch.Tensor, cage: torchcage.Cage) -> None:
    mvc = torchcage.MeanValueCoordinates(cage, points)
    assert_type(mvc.forward(cage.vertices), torch.Tensor)
    assert_type(mvc.jacobian(cage.vertices), torch.Tensor)
    gc = torchcage.GreenCoordinates(cage, points)
    assert_type(gc.forward(cage.vertices), torch.Tensor)
    assert_type(gc.jacobian(cage.vertices), torch.Tensor)


def _errors() -> None:
    try:
        pass
    except torchcage.PointsError as err:
        assert_type(err, torchcage.PointsError)
        _: ValueError = err  # the documented hierarchy: catchable as ValueError
    warning: type[UserWarning] = torchcage.OutsideCageWarning
    del warning
