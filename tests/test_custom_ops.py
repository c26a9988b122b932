"""torchcage's ``torch.library`` custom ops pass ``torch.library.opcheck`` (schema, autograd
registration, fake tensors, AOT dispatch), and modules compile with ``torch.compile``."""

from __future__ import annotations

import pytest
import torch

import torchcage
from torchcage import functional as F
from torchcage.backends import native as _native

needs_native = pytest.mark.skipif(not _native.available(), reason="needs the native kernel (the derivatives op)")


@pytest.fixture(scope="module")
def cube() -> torchcage.Cage:
    return torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()


def _points(n: int = 6) -> torch.Tensor:
    g = torch.Generator().manual_seed(3)
    return torch.rand(n, 3, generator=g, dtype=torch.float64) * 1.6 - 0.8


def test_opcheck_coordinates(cube: torchcage.Cage) -> None:
    op = torch.ops.torchcage.mean_value_coordinates.default
    for backend in ("auto", "torch"):  # (the backend in force: the op's schema has none)
        with torchcage.backends.use(backend):
            torch.library.opcheck(op, (_points(), cube.vertices, cube.triangles, 0))


@needs_native
@pytest.mark.parametrize("order", [1, 2])
def test_opcheck_derivatives(cube: torchcage.Cage, order: int) -> None:
    op = torch.ops.torchcage.mean_value_derivatives.default
    torch.library.opcheck(op, (_points(), cube.vertices, cube.triangles, order))


def test_compiled_module_matches_eager(cube: torchcage.Cage) -> None:
    m = torchcage.MeanValueCoordinates(cube, _points())
    pose = cube.vertices * 1.5 + 0.1
    compiled = torch.compile(m, fullgraph=True)
    torch.testing.assert_close(compiled(pose), m(pose), rtol=0, atol=1e-15)


@pytest.mark.slow
def test_compiled_functional_matches_eager(cube: torchcage.Cage) -> None:
    # The functional call keeps its checks (data-dependent: graph breaks) and its custom op.
    f = torch.compile(lambda y: F.mean_value_coordinates(y, cube))
    x = _points()
    torch.testing.assert_close(f(x), F.mean_value_coordinates(x, cube), rtol=0, atol=1e-15)
