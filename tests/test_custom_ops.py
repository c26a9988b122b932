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


# ------------------------------------------------------------------ the derivatives' ops
def _square() -> torchcage.Cage:
    return torchcage.Cage(
        torch.tensor([[0.0, 0], [1, 0], [1.2, 1], [0, 0.9]], dtype=torch.float64),
        torch.tensor([[0, 1], [1, 2], [2, 3], [3, 0]]),
    )


def _derivative_cases(cube: torchcage.Cage) -> list[tuple[str, object, torchcage.Cage, torch.Tensor, dict]]:
    """(label, function, cage, points, options): both derivative functions, 3D and 2D, both orders,
    Green's two exteriors and a lower output dtype, and a batch of mean value cages (two poses)."""
    x3 = torch.cat([_points(5) * 0.9, torch.tensor([[2.0, 0.3, -0.2]], dtype=torch.float64)])
    x2 = torch.tensor([[0.3, 0.4], [0.6, 0.2], [2.0, 1.5]], dtype=torch.float64)
    two = torchcage.Cage(torch.stack([cube.vertices, 1.3 * cube.vertices]), cube.triangles)
    mvd, gd = F.mean_value_derivatives, F.green_derivatives
    return [
        ("mvc 3D order 1", mvd, cube, x3, {"order": 1}),
        ("mvc 3D order 2", mvd, cube, x3, {"order": 2, "chunk_size": 2}),
        ("mvc 2D order 2", mvd, _square(), x2, {"order": 2}),
        ("mvc batch of two", mvd, two, torch.stack([x3[:5], 1.2 * x3[:5]]), {"order": 2}),
        ("green 3D order 1", gd, cube, x3, {"order": 1}),
        ("green 3D, order 2, none, float32", gd, cube, x3, {"order": 2, "exterior": "none", "dtype": torch.float32}),
        ("green 2D order 2", gd, _square(), x2, {"order": 2}),
    ]


@pytest.mark.filterwarnings("ignore:Dynamo does not know how to trace")
def test_derivatives_compile_with_fullgraph(cube: torchcage.Cage) -> None:
    """``torch.compile(fullgraph=True)`` takes ``mean_value_derivatives`` and ``green_derivatives``
    (each one opaque op, ``torchcage::mvc_derivatives`` / ``::green_derivatives``): the outputs equal
    the eager ones, ``None`` where the eager call gives ``None``, plain values (no graph) as eager's,
    and the points' requiring grad does not change that."""
    for label, fn, cage, x, opts in _derivative_cases(cube):
        torch._dynamo.reset()
        want = fn(x, cage, **opts)
        compiled = torch.compile(lambda y, fn=fn, cage=cage, opts=opts: fn(y, cage, **opts), fullgraph=True,
                                 backend="eager")  # fmt: skip
        got = compiled(x.clone().requires_grad_())
        assert len(got) == len(want), label
        for a, b in zip(got, want, strict=True):
            if b is None:
                assert a is None, label
                continue
            assert a.dtype == b.dtype and not a.requires_grad, label
            torch.testing.assert_close(a, b, rtol=0, atol=0, msg=label)
    torch._dynamo.reset()


@needs_native  # (without it the ops differentiate the torch kernel by autograd, which opcheck's modes do not run)
def test_derivative_ops_pass_opcheck(cube: torchcage.Cage) -> None:
    """The derivatives' ops pass ``torch.library.opcheck`` (schema, fake tensors, dispatch), and
    carry no backend in their schemas."""
    x = _points()
    c = cube
    args = (x, c.vertices, c.triangles, c.quads, c.edges)
    for order in (1, 2):
        torch.library.opcheck(torch.ops.torchcage.mvc_derivatives.default, (*args, order, 0, True))
        torch.library.opcheck(torch.ops.torchcage.green_derivatives.default, (*args, order, 0, False))
    for name in ("mvc_derivatives", "green_derivatives"):
        schema = getattr(torch.ops.torchcage, name).default._schema
        assert not any(a.name == "backend" or str(a.type) == "str" for a in schema.arguments), schema
