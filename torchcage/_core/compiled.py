"""A family's public function inside ``torch.compile(fullgraph=True)``: one opaque custom op.

Dynamo cannot trace the public functions' checks (data-dependent branches, ``.item()``), the
native calls or the analytic backward passes. Under compilation a family's public function calls
instead ``torchcage::<name>``: the whole eager function (checks, centring, the kernel chosen by
:func:`torchcage.backends.select`, the far field) run as one custom op, differentiated through
``torchcage::<name>_backward`` (the eager backward, whatever it is for that family: analytic
gradients, fused vertex passes, autograd of the torch kernel). Both have fake implementations, so
the compiled graph knows their shapes; neither is traced into.

No backend is in their schemas: the tensors' device picks the kernel, through
:func:`torchcage.backends.select`, and the user's choice is the backend in force when the forward
op runs (:func:`torchcage.backends.use` around the compiled call). The forward op returns that
backend as one more output, a 0-dim int8 code (an index in :data:`torchcage.backends.BACKENDS`),
which the backward op takes as an input: the backward pass runs with the forward's backend, on
whatever thread and whenever it runs (after the ``use`` block; on CUDA autograd's device thread). A
``backend=`` other than ``"auto"`` inside a compiled function cannot reach the op, and raises with
that advice (a compiled graph replays its ops, not the Python that set a preference while it was
traced); ``fullgraph=True`` then fails, and without it Dynamo runs that call eagerly.

What compiles: values and first derivatives with respect to the points and the cage's vertices,
batched cages included. Not under compilation: double backward and ``torch.func`` transforms (eager
calls have both where the family does).

The same op serves ``torch.func.vmap`` of the values (:func:`through_op`): its vmap rule folds the
mapped axis into the points (one cage) or into a batch of cages (a mapped cage), so a mapped call
is one call of the eager function on all the point sets at once.

Examples:
    >>> import torch, torchcage
    >>> from torchcage import functional as F
    >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
    >>> x = torch.tensor([[0.1, 0.2, -0.3]], dtype=torch.float64)
    >>> f = torch.compile(lambda y: F.mean_value_coordinates(y, cube), fullgraph=True, backend="eager")
    >>> torch.allclose(f(x), F.mean_value_coordinates(x, cube))
    True
    >>> with torchcage.backends.use("torch"):  # (the backend of the compiled call's op)
    ...     torch.allclose(f(x), F.mean_value_coordinates(x, cube))
    True
    >>> torch._dynamo.reset()  # (the compiled code's caches, before the doctest's globals go)
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import List  # noqa: UP035 (torch 2.5 infers op schemas from typing.List only)

import torch
from torch import Tensor

from torchcage.backends import BACKENDS, Op, check, preferred, resolve, use
from torchcage.cage import Cage

__all__ = ["CompiledOp", "DerivativesOp", "through_op"]

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


def through_op(points: object, cage: object) -> bool:
    """Whether a public function runs as its op: under ``torch.compile``, or when ``torch.func.vmap``
    maps the points or the cage's vertices at the innermost level (the op's vmap rule then sees the
    whole batch; another transform inside the map, such as ``grad``, keeps the eager path)."""
    if torch.compiler.is_compiling():
        return True
    vertices = getattr(cage, "vertices", None)  # (anything else: the eager checks name the problem)
    tensors = [t for t in (points, vertices) if isinstance(t, Tensor)]
    if not any(torch._C._functorch.is_batchedtensor(t) for t in tensors):
        return False
    # Older torch (2.5) records no autograd through a custom op's vmap rule (and a mapped tensor
    # reads requires_grad=False there): gradients would be missing without a word. There the eager
    # path runs, as before the rule (and names what it cannot do).
    return _vmap_records_autograd()


@functools.cache
def _vmap_records_autograd() -> bool:
    """Whether this torch records autograd through a custom op's vmap rule (probed once on a
    private one-line op)."""
    x = torch.ones(2, 1, requires_grad=True)
    return bool(torch.func.vmap(_probe)(x).requires_grad)


@torch.library.custom_op("torchcage::_vmap_probe", mutates_args=())
def _probe(x: Tensor) -> Tensor:
    return x * 2


_probe.register_autograd(lambda ctx, g: g * 2)
_probe.register_vmap(lambda info, in_dims, x: (_probe(x), in_dims[0]))


def _vmap_inputs(
    points: Tensor, vertices: Tensor, pdim: int | None, vdim: int | None
) -> tuple[Tensor, Tensor, Callable[[Tensor], Tensor]]:
    """The op's arguments for all the mapped calls at once, and how to bring each output back to
    the mapped shape (the mapped axis first).

    One cage per call (vertices ``(V, D)`` for each call) and only the points mapped: the point sets
    are folded into one. A mapped cage: a batch of cages ``(size, *Bc, V, D)`` with the points
    ``(size or 1, *Bp, N, D)``, batch axes aligned as one call would broadcast them (a cage of one
    call, ``(V, D)``, takes each call's points as one set ``(N, D)``)."""
    p = points.movedim(pdim, 0) if pdim is not None else points.unsqueeze(0)
    if vdim is None and vertices.dim() == 2:
        lead = p.shape[:-1]
        return p.reshape(-1, p.shape[-1]), vertices, lambda o: o.reshape(*lead, o.shape[-1])
    v = vertices.movedim(vdim, 0) if vdim is not None else vertices.unsqueeze(0)
    if v.dim() == 3:  # one cage per call: its points as one set
        lead = p.shape[1:-1]
        p = p.reshape(p.shape[0], -1, p.shape[-1])
        return p, v, lambda o: o.reshape(o.shape[0], *lead, o.shape[-1])
    rank = max(p.dim(), v.dim()) - 2  # batch axes of one call's points and cages, the mapped one included
    p = p.reshape(p.shape[0], *[1] * (rank - (p.dim() - 2)), *p.shape[1:])
    v = v.reshape(v.shape[0], *[1] * (rank - (v.dim() - 2)), *v.shape[1:])
    return p, v, lambda o: o


def _cage(vertices: Tensor, triangles: Tensor, quads: Tensor, edges: Tensor) -> Cage:
    return Cage._trusted(vertices, triangles, quads, edges)


def _lead(points: Tensor, vertices: Tensor) -> list[int]:
    """The outputs' leading shape: ``(*)`` of points ``(*, D)`` for one cage, ``(*B', N)`` for a
    batch of cages."""
    if vertices.dim() == 2:
        return list(points.shape[:-1])
    return [*torch.broadcast_shapes(points.shape[:-2], vertices.shape[:-2]), points.shape[-2]]


def _positive_integers(**values: object) -> None:
    """Refuse options that must be positive integers when given (an op's sentinel 0 must not turn
    a wrong value into the default).

    Raises:
        ValueError: ``<name> must be a positive integer, got <value>``.
    """
    for name, value in values.items():
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ValueError(f"{name} must be a positive integer, got {value!r}")


def _auto_only(name: str, backend: str) -> None:
    """Refuse a per-call ``backend`` other than ``"auto"`` under compilation: it cannot reach the op
    ``torchcage::<name>``, which takes the backend in force when the compiled code runs.

    Raises:
        ValueError: the advice to set the backend around the compiled call instead.
    """
    if backend != "auto":
        raise ValueError(
            f"backend={backend!r} inside a compiled function: under torch.compile this runs as one op "
            f"(torchcage::{name}) that takes the backend in force when the compiled code runs; leave "
            f"backend='auto' and call the compiled function inside `with torchcage.backends.use({backend!r}):`"
        )


class CompiledOp:
    """The pair of opaque ops of one family (``torchcage::<name>`` and
    ``torchcage::<name>_backward``).

    Their schemas are a compatibility surface: ``torch.compile``'s on-disk caches keep compiled
    backward graphs that call the backward op with these arguments, found again by the forward
    graph (which does not show the backward op's schema). A changed argument list breaks every
    graph an earlier version cached (seen: a cached backward called the op without two arguments
    added since); give a changed op a new name instead (the backward ops were ``<name>_vjp`` while
    their schemas carried a backend string).

    Args:
        name: the op's name in the ``torchcage`` namespace.
        eager: the family's eager public function, as ``eager(points, cage, options)`` returning
            a tuple of outputs.
        widths: the last dimension of each output for a cage.
        op: the family's operation (the ``backend=`` values it accepts: one error text).
    """

    def __init__(self, name: str, eager: Eager, widths: Widths, op: Op) -> None:
        self.name, self.eager, self.widths, self.op = name, eager, widths, op
        outer = self

        @torch.library.custom_op(f"torchcage::{name}", mutates_args=())
        def values(
            points: Tensor,
            vertices: Tensor,
            triangles: Tensor,
            quads: Tensor,
            edges: Tensor,
            chunk_size: int,
            n: int,
            tol: float,
        ) -> List[Tensor]:  # noqa: UP006 (torch 2.5's infer_schema reads typing.List)
            code = torch.tensor(BACKENDS.index(preferred()), dtype=torch.int8)  # (for the backward op)
            with torch.no_grad():
                cage = _cage(vertices, triangles, quads, edges)
                outs = outer.eager(points, cage, outer._options(chunk_size, n, tol))
                return [*(o.clone() for o in outs), code]

        @values.register_fake
        def _(points, vertices, triangles, quads, edges, chunk_size, n, tol):
            dtype = torch.promote_types(points.dtype, vertices.dtype)
            lead = _lead(points, vertices)
            widths = outer.widths(vertices, triangles, quads, edges)
            code = points.new_empty((), dtype=torch.int8, device="cpu")
            return [*(points.new_empty([*lead, k], dtype=dtype) for k in widths), code]

        @torch.library.custom_op(f"torchcage::{name}_backward", mutates_args=())
        def vjp(
            points: Tensor,
            vertices: Tensor,
            triangles: Tensor,
            quads: Tensor,
            edges: Tensor,
            grads: List[Tensor],  # noqa: UP006
            code: Tensor,
            chunk_size: int,
            n: int,
            tol: float,
        ) -> List[Tensor]:  # noqa: UP006 (the two gradients)
            with use(BACKENDS[int(code)]):  # (the forward's backend: its code output)
                options = outer._options(chunk_size, n, tol)

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
        def _(points, vertices, triangles, quads, edges, grads, code, chunk_size, n, tol):
            return [torch.empty_like(points), torch.empty_like(vertices)]

        def setup(ctx, inputs, output) -> None:
            points, vertices, triangles, quads, edges, *options = inputs
            ctx.save_for_backward(points, vertices, triangles, quads, edges, output[-1])
            ctx.options = options

        def backward(ctx, grads):
            if torch.is_grad_enabled():
                raise RuntimeError(
                    f"double backward of torchcage::{name} is not available under torch.compile; call the function "
                    "eagerly for second derivatives"
                )
            points, vertices, triangles, quads, edges, code = ctx.saved_tensors
            grads = [g if g is not None else torch.zeros(()) for g in grads[:-1]]  # (not the code's)
            gx, gP = vjp(points, vertices, triangles, quads, edges, grads, code, *ctx.options)
            return gx, gP, None, None, None, None, None, None

        values.register_autograd(backward, setup_context=setup)

        def values_vmap(info, in_dims, points, vertices, triangles, quads, edges, chunk_size, n, tol):
            if any(d is not None for d in in_dims[2:5]):
                raise ValueError(
                    f"torchcage::{name}: vmap over the cage's faces is not supported (one topology for every "
                    "call); map over the points or the vertices"
                )
            p, v, back = _vmap_inputs(points, vertices, in_dims[0], in_dims[1])
            *outs, code = values(p, v, triangles, quads, edges, chunk_size, n, tol)
            return [*(back(o) for o in outs), code], [0] * len(outs) + [None]

        values.register_vmap(values_vmap)
        self.values, self.vjp = values, vjp

    @staticmethod
    def _options(chunk_size: int, n: int, tol: float) -> dict:
        """The public function's keyword options (0 and -1 stand for "not given"), with the backend
        in force where the op runs."""
        options: dict = {"chunk_size": chunk_size or None, "backend": preferred()}
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
        """The outputs, through the op (under ``torch.compile``, or ``torch.func.vmap``), in
        ``dtype`` when given. The options are checked as the eager function checks them (the op's
        sentinels 0 and -1 must not turn a wrong value into the default). ``backend`` reaches the op
        as the backend in force: set here for an eager call (vmap); under compilation, only
        ``"auto"`` (the op then takes the backend in force when the compiled graph runs).

        Raises:
            ValueError: ``chunk_size`` or ``n`` not a positive integer, a negative ``tol``, a
                ``backend`` the family does not have, or another backend than ``"auto"`` under
                ``torch.compile``.
            TypeError: ``dtype`` not a floating-point dtype.
        """
        _positive_integers(chunk_size=chunk_size, n=n)
        if tol is not None and not float(tol) >= 0:
            raise ValueError(f"tol must be a nonnegative number, got {tol!r}")
        if dtype is not None and not dtype.is_floating_point:
            raise TypeError(f"dtype must be a floating-point dtype, got {dtype}")
        check(self.op, backend)
        if torch.compiler.is_compiling():
            _auto_only(self.name, backend)
        args = (
            points,
            cage.vertices,
            cage.triangles,
            cage.quads,
            cage.edges,
            chunk_size or 0,
            0 if n is None else int(n),
            -1.0 if tol is None else float(tol),
        )
        if torch.compiler.is_compiling():
            outs = self.values(*args)[:-1]
        else:
            with use(resolve(backend)):
                outs = self.values(*args)[:-1]
        return outs if dtype is None else [o.to(dtype) for o in outs]


#: ``eager(points, cage, order, chunk_size, extend) -> outputs`` (``None`` for an output not asked).
DerivativesEager = Callable[[Tensor, Cage, int, "int | None", bool], tuple["Tensor | None", ...]]
#: ``tails(vertices, triangles, quads, edges, order) -> [trailing shape of each output, or None]``.
Tails = Callable[[Tensor, Tensor, Tensor, Tensor, int], list["list[int] | None"]]


class DerivativesOp:
    """``torchcage::<name>``: a family's analytic derivatives as one opaque op under
    ``torch.compile``, so that ``fullgraph=True`` takes them (their checks and kernels are not
    traceable). Their outputs are plain values (the eager function detaches its inputs: no
    autograd graph), so the op is called on detached inputs and has no autograd formula; the kernel
    is the backend in force where the op runs (no backend in the schema, as :class:`CompiledOp`).

    Args:
        name: the op's name in the ``torchcage`` namespace.
        eager: the eager public function as ``eager(points, cage, order, chunk_size, extend)``
            (``extend``: Green's ``exterior="extend"``; ignored where a family has no exterior).
        tails: each output's trailing shape after the points' (``None``: an output not computed
            for that order, returned as ``None``).
        op: the family's operation (the ``backend=`` values it accepts).
        promote: the outputs' dtype is the points' and the vertices' promoted (else the points').
    """

    def __init__(self, name: str, eager: DerivativesEager, tails: Tails, op: Op, promote: bool) -> None:
        self.name, self.tails, self.backends = name, tails, op

        @torch.library.custom_op(f"torchcage::{name}", mutates_args=())
        def values(
            points: Tensor,
            vertices: Tensor,
            triangles: Tensor,
            quads: Tensor,
            edges: Tensor,
            order: int,
            chunk_size: int,
            extend: bool,
        ) -> List[Tensor]:  # noqa: UP006 (torch 2.5's infer_schema reads typing.List)
            cage = _cage(vertices, triangles, quads, edges)
            with _autograd_inside_an_op():  # (the torch kernels' fallbacks differentiate by autograd)
                outs = eager(points, cage, order, chunk_size or None, extend)
            return [o.detach().clone() if o is not None else points.new_empty((0,)) for o in outs]

        @values.register_fake
        def _(points, vertices, triangles, quads, edges, order, chunk_size, extend):
            dtype = torch.promote_types(points.dtype, vertices.dtype) if promote else points.dtype
            lead = _lead(points, vertices)
            return [
                points.new_empty([*lead, *t] if t is not None else [0], dtype=dtype)
                for t in tails(vertices, triangles, quads, edges, order)
            ]

        self.values = values

    def __call__(
        self, points: Tensor, cage: Cage, order: int, chunk_size: int | None, backend: str, extend: bool = True
    ) -> tuple[Tensor | None, ...]:
        """The outputs through the op (under ``torch.compile``); ``None`` where the order asks for
        none. ``backend`` as :meth:`CompiledOp.__call__` takes it under compilation.

        Raises:
            ValueError: ``chunk_size`` not a positive integer, a ``backend`` the family does not
                have, or another backend than ``"auto"`` under ``torch.compile``.
        """
        _positive_integers(chunk_size=chunk_size)
        check(self.backends, backend)
        _auto_only(self.name, backend)
        c = cage
        outs = self.values(
            points.detach(), c.vertices.detach(), c.triangles, c.quads, c.edges, order, chunk_size or 0, extend
        )
        tails = self.tails(c.vertices, c.triangles, c.quads, c.edges, order)
        return tuple(o if t is not None else None for o, t in zip(outs, tails, strict=True))
