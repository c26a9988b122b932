"""Mean value coordinates inside ``torch.compile(fullgraph=True)``: two opaque custom ops.

Dynamo cannot trace the public function's checks (data-dependent branches, ``.item()``), its
native calls or the analytic backward. Under compilation the public function therefore calls
``torchcage::mean_value`` (the whole eager function: checks, centring, the kernel chosen by
:func:`torchcage.backends.select`, the far field) and differentiates it through
``torchcage::mean_value_vjp`` (the eager backward: the analytic point gradients and the fused
vertex pass of :class:`~torchcage.families.mean_value.ops.MeanValueFunction`). Both have fake
implementations, so the compiled graph knows their shapes; neither is traced into.

What compiles: values and first derivatives with respect to the points and the cage's vertices,
batched cages included. Not under compilation: double backward (the Hessians), ``torch.func``
transforms (eager calls have both).

Examples:
    >>> import torch, torchcage
    >>> from torchcage import functional as F
    >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
    >>> x = torch.tensor([[0.1, 0.2, -0.3]], dtype=torch.float64)
    >>> f = torch.compile(lambda y: F.mean_value_coordinates(y, cube), fullgraph=True, backend="eager")
    >>> torch.allclose(f(x), F.mean_value_coordinates(x, cube))
    True
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import torch
from torch import Tensor

from torchcage.cage import Cage

__all__ = ["compiled_mean_value"]


def _shape(points: Tensor, vertices: Tensor) -> list[int]:
    """The result's shape: ``(*, V)`` for one cage, ``(*B', N, V)`` for a batch of cages."""
    V = vertices.shape[-2]
    if vertices.dim() == 2:
        return [*points.shape[:-1], V]
    batch = torch.broadcast_shapes(points.shape[:-2], vertices.shape[:-2])
    return [*batch, points.shape[-2], V]


def _eager(points: Tensor, vertices: Tensor, faces: Tensor, chunk_size: int, backend: str) -> Tensor:
    from torchcage.families.mean_value.api import mean_value_coordinates

    cage = Cage._from_faces(vertices, faces)
    return mean_value_coordinates(points, cage, chunk_size=chunk_size or None, backend=backend)


@torch.library.custom_op("torchcage::mean_value", mutates_args=())
def _values_op(points: Tensor, vertices: Tensor, faces: Tensor, chunk_size: int, backend: str) -> Tensor:
    with torch.no_grad():
        return _eager(points, vertices, faces, chunk_size, backend).clone()


@_values_op.register_fake
def _(points, vertices, faces, chunk_size, backend):
    return points.new_empty(_shape(points, vertices), dtype=torch.promote_types(points.dtype, vertices.dtype))


@torch.library.custom_op("torchcage::mean_value_vjp", mutates_args=())
def _vjp_op(
    points: Tensor, vertices: Tensor, faces: Tensor, grad: Tensor, chunk_size: int, backend: str
) -> tuple[Tensor, Tensor]:
    def vjp() -> tuple[Tensor | None, Tensor | None]:
        x = points.detach().requires_grad_()
        P = vertices.detach().requires_grad_()
        lam = _eager(x, P, faces, chunk_size, backend)
        return torch.autograd.grad(lam, (x, P), grad.to(lam.dtype), allow_unused=True)

    # A custom op's body runs below the autograd dispatch key (nothing it computes records a
    # graph), and the eager backward differentiates parts of the torch kernel by autograd: it runs
    # on a thread of its own, whose dispatch state is the default one.
    with ThreadPoolExecutor(max_workers=1) as pool:
        gx, gP = pool.submit(vjp).result()
    gx = torch.zeros_like(points) if gx is None else gx.to(points.dtype)
    gP = torch.zeros_like(vertices) if gP is None else gP.to(vertices.dtype)
    return gx, gP


@_vjp_op.register_fake
def _(points, vertices, faces, grad, chunk_size, backend):
    return torch.empty_like(points), torch.empty_like(vertices)


def _setup(ctx, inputs, output) -> None:
    points, vertices, faces, chunk_size, backend = inputs
    ctx.save_for_backward(points, vertices, faces)
    ctx.options = (chunk_size, backend)


def _backward(ctx, grad: Tensor):
    points, vertices, faces = ctx.saved_tensors
    if torch.is_grad_enabled():
        raise RuntimeError(
            "double backward of mean value coordinates is not available under torch.compile; call the function "
            "eagerly for Hessians (it has them: torchcage.functional.mean_value_derivatives)"
        )
    gx, gP = _vjp_op(points, vertices, faces, grad, *ctx.options)
    return gx, gP, None, None, None


_values_op.register_autograd(_backward, setup_context=_setup)


def compiled_mean_value(points: Tensor, cage: Cage, chunk_size: int | None, backend: str) -> Tensor:
    """``(*, V)`` (or ``(*B', N, V)`` for a batched cage) through the opaque ops; called by the
    public function under ``torch.compile``."""
    faces = cage.triangles if cage.dim == 3 else cage.edges
    return _values_op(points, cage.vertices, faces, chunk_size or 0, backend)
