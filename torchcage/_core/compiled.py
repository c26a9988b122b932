"""A family's public function inside ``torch.compile(fullgraph=True)``: one opaque custom op.

Dynamo cannot trace the public functions' checks (data-dependent branches, ``.item()``), the
native calls or the analytic backward passes. Under compilation a family's public function calls
instead ``torchcage::<name>``: the whole eager function (checks, centring, the kernel chosen by
:func:`torchcage.backends.select`, the far field) run as one custom op, differentiated through
``torchcage::<name>_vjp`` (the eager backward, whatever it is for that family: analytic gradients,
fused vertex passes, autograd of the torch kernel). Both have fake implementations, so the compiled
graph knows their shapes; neither is traced into.

What compiles: values and first derivatives with respect to the points and the cage's vertices,
batched cages included. Not under compilation: double backward and ``torch.func`` transforms (eager
calls have both where the family does).

Examples:
    >>> import torch, torchcage
    >>> from torchcage import functional as F
    >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
    >>> x = torch.tensor([[0.1, 0.2, -0.3]], dtype=torch.float64)
    >>> f = torch.compile(lambda y: F.mean_value_coordinates(y, cube), fullgraph=True, backend="eager")
    >>> torch.allclose(f(x), F.mean_value_coordinates(x, cube))
    True
    >>> torch._dynamo.reset()  # (the compiled code's caches, before the doctest's globals go)
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import List  # noqa: UP035 (torch 2.5 infers op schemas from typing.List only)

import torch
from torch import Tensor

from torchcage.cage import Cage

__all__ = ["CompiledOp"]

#: ``eager(points, cage, options) -> tuple of outputs`` (each ``(*, N, K)``).
Eager = Callable[[Tensor, Cage, dict], tuple[Tensor, ...]]
#: ``widths(vertices, triangles, quads, edges) -> [K of each output]``.
Widths = Callable[[Tensor, Tensor, Tensor, Tensor], list[int]]


@contextmanager
def _autograd_inside_an_op() -> Iterator[None]:
    """Autograd recording within a custom op's body. The dispatcher runs the body below the
    autograd keys (they are in the thread's exclude set: nothing computed there records a graph);
    the eager backward differentiates parts of the torch kernels by autograd, so the block lifts
    that exclusion, on the same thread (another thread would wait on the autograd engine's device
    thread that runs this backward on CUDA)."""
    C = torch._C
    autograd_keys = C._dispatch_keyset_full() - C._after_autograd_keyset
    exclude = C._dispatch_tls_local_exclude_set() - autograd_keys
    with C._ForceDispatchKeyGuard(C._dispatch_tls_local_include_set(), exclude), torch.enable_grad():
        yield


def _cage(vertices: Tensor, triangles: Tensor, quads: Tensor, edges: Tensor) -> Cage:
    return Cage._trusted(vertices, triangles, quads, edges)


def _lead(points: Tensor, vertices: Tensor) -> list[int]:
    """The outputs' leading shape: ``(*)`` of points ``(*, D)`` for one cage, ``(*B', N)`` for a
    batch of cages."""
    if vertices.dim() == 2:
        return list(points.shape[:-1])
    return [*torch.broadcast_shapes(points.shape[:-2], vertices.shape[:-2]), points.shape[-2]]


class CompiledOp:
    """The pair of opaque ops of one family (``torchcage::<name>`` and ``torchcage::<name>_vjp``).

    Args:
        name: the op's name in the ``torchcage`` namespace.
        eager: the family's eager public function, as ``eager(points, cage, options)`` returning
            a tuple of outputs.
        widths: the last dimension of each output for a cage.
    """

    def __init__(self, name: str, eager: Eager, widths: Widths) -> None:
        self.name, self.eager, self.widths = name, eager, widths
        outer = self

        @torch.library.custom_op(f"torchcage::{name}", mutates_args=())
        def values(
            points: Tensor,
            vertices: Tensor,
            triangles: Tensor,
            quads: Tensor,
            edges: Tensor,
            chunk_size: int,
            backend: str,
            n: int,
            tol: float,
        ) -> List[Tensor]:  # noqa: UP006 (torch 2.5's infer_schema reads typing.List)
            with torch.no_grad():
                cage = _cage(vertices, triangles, quads, edges)
                return [o.clone() for o in outer.eager(points, cage, outer._options(chunk_size, backend, n, tol))]

        @values.register_fake
        def _(points, vertices, triangles, quads, edges, chunk_size, backend, n, tol):
            dtype = torch.promote_types(points.dtype, vertices.dtype)
            lead = _lead(points, vertices)
            return [points.new_empty([*lead, k], dtype=dtype) for k in outer.widths(vertices, triangles, quads, edges)]

        @torch.library.custom_op(f"torchcage::{name}_vjp", mutates_args=())
        def vjp(
            points: Tensor,
            vertices: Tensor,
            triangles: Tensor,
            quads: Tensor,
            edges: Tensor,
            grads: List[Tensor],  # noqa: UP006
            chunk_size: int,
            backend: str,
            n: int,
            tol: float,
        ) -> List[Tensor]:  # noqa: UP006 (the two gradients)
            options = outer._options(chunk_size, backend, n, tol)

            def run() -> tuple[Tensor | None, Tensor | None]:
                x = points.detach().requires_grad_()
                P = vertices.detach().requires_grad_()
                outs = outer.eager(x, _cage(P, triangles, quads, edges), options)
                cot = [
                    torch.zeros_like(o) if g.dim() == 0 else g.to(o.dtype)  # (0-dim: an output not used)
                    for g, o in zip(grads, outs, strict=True)
                ]
                gx, gP = torch.autograd.grad(outs, (x, P), cot, allow_unused=True)
                return gx, gP

            with _autograd_inside_an_op():
                gx, gP = run()
            gx = torch.zeros_like(points) if gx is None else gx.to(points.dtype)
            gP = torch.zeros_like(vertices) if gP is None else gP.to(vertices.dtype)
            return [gx, gP]

        @vjp.register_fake
        def _(points, vertices, triangles, quads, edges, grads, chunk_size, backend, n, tol):
            return [torch.empty_like(points), torch.empty_like(vertices)]

        def setup(ctx, inputs, output) -> None:
            points, vertices, triangles, quads, edges, *options = inputs
            ctx.save_for_backward(points, vertices, triangles, quads, edges)
            ctx.options = options

        def backward(ctx, grads):
            if torch.is_grad_enabled():
                raise RuntimeError(
                    f"double backward of torchcage::{name} is not available under torch.compile; call the function "
                    "eagerly for second derivatives"
                )
            points, vertices, triangles, quads, edges = ctx.saved_tensors
            grads = [g if g is not None else torch.zeros(()) for g in grads]
            gx, gP = vjp(points, vertices, triangles, quads, edges, list(grads), *ctx.options)
            return gx, gP, None, None, None, None, None, None, None

        values.register_autograd(backward, setup_context=setup)
        self.values, self.vjp = values, vjp

    @staticmethod
    def _options(chunk_size: int, backend: str, n: int, tol: float) -> dict:
        """The public function's keyword options (0 and -1 stand for "not given")."""
        options: dict = {"chunk_size": chunk_size or None, "backend": backend}
        if n > 0:
            options["n"] = n
        if tol >= 0:
            options["tol"] = tol
        return options

    def __call__(
        self,
        points: Tensor,
        cage: Cage,
        chunk_size: int | None = None,
        backend: str = "auto",
        n: int | None = None,
        tol: float | None = None,
        dtype: torch.dtype | None = None,
    ) -> list[Tensor]:
        """The outputs, through the op (under ``torch.compile``), in ``dtype`` when given. The
        options are checked as the eager function checks them (the op's sentinels 0 and -1 must
        not turn a wrong value into the default).

        Raises:
            ValueError: ``chunk_size`` or ``n`` not a positive integer, a negative ``tol``.
            TypeError: ``dtype`` not a floating-point dtype.
        """
        for name, value in (("chunk_size", chunk_size), ("n", n)):
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if tol is not None and not float(tol) >= 0:
            raise ValueError(f"tol must be a nonnegative number, got {tol!r}")
        if dtype is not None and not dtype.is_floating_point:
            raise TypeError(f"dtype must be a floating-point dtype, got {dtype}")
        outs = self.values(
            points,
            cage.vertices,
            cage.triangles,
            cage.quads,
            cage.edges,
            chunk_size or 0,
            backend,
            0 if n is None else int(n),
            -1.0 if tol is None else float(tol),
        )
        return outs if dtype is None else [o.to(dtype) for o in outs]
