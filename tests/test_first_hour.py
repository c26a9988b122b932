"""What a newcomer meets in the first hour: empty point sets give empty results, and a batch of
point sets given to a module is refused with a message saying what to do."""

from __future__ import annotations

import warnings

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
    "lbc": (torchcage.LocalBarycentricCoordinates, 1),
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
    with pytest.raises(PointsError, match=r"one point set of shape \(N, 3\), got \(2, 5, 3\).*one module per set"):
        cls(cubes[triangulated], torch.zeros(2, 5, 3, dtype=f64))
