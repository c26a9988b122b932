"""The one place that chooses a kernel: native C, Triton or torch.

Every functional entry names its operation (an :class:`Op`: which backends serve it, on which
dimensions and dtypes) and calls :func:`select` once with the user's ``backend=``; the same values
behave the same for every operation:

- ``"auto"``: the native C kernel for CPU points it takes (when the library loads and no autograd
  graph is recorded, unless the op's native kernel computes derivatives itself), the Triton kernel
  for CUDA points where the op lets ``auto`` take it, else the torch kernel;
- ``"native"`` / ``"triton"``: insist, and raise :class:`RuntimeError` saying why where that kernel
  cannot serve this call;
- ``"torch"``: the torch kernel (any device and dtype; it records autograd);
- anything else, or a backend the op does not have: :class:`ValueError` with one text that lists
  what the op supports.

A call's ``"auto"`` means the backend in force: ``"auto"`` unless a :func:`use` block sets another
(on the thread that runs the call); each family's public functions read it once, on entry
(:func:`resolve`), so internal helpers keep their own choice. The block is also how a compiled graph chooses: under
``torch.compile`` a family runs as one registered op whose schema carries no backend (the device
of the tensors picks the kernel, through :func:`select`), so a compiled call takes its backend from
a ``with torchcage.backends.use(...)`` around it, not from its own ``backend=``.

Examples:
    >>> import torch
    >>> from torchcage.backends import Op, select
    >>> op = Op("an example", native=False)
    >>> select(op, "auto", torch.zeros(2, 3, dtype=torch.float64)).kind
    'torch'
    >>> select(op, "cuda", torch.zeros(2, 3))
    Traceback (most recent call last):
    ...
    ValueError: backend must be one of 'auto', 'torch' for an example, got 'cuda'
"""

from __future__ import annotations

import ctypes
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Literal

import torch
from torch._C._functorch import is_functorch_wrapped_tensor
from torch.autograd import forward_ad

from torchcage.backends import native as _native
from torchcage.backends import triton as _triton

__all__ = ["BACKENDS", "Backend", "Choice", "Op", "check", "preferred", "resolve", "select", "use"]

#: Every value of ``backend=`` that some operation accepts.
BACKENDS = ("auto", "native", "torch", "triton")
Backend = Literal["auto", "native", "torch", "triton"]


_preference = threading.local()


def preferred() -> str:
    """The backend in force on this thread: the innermost :func:`use` block's, else ``"auto"``."""
    return getattr(_preference, "backend", "auto")


def resolve(backend: str) -> str:
    """A call's ``backend=`` with ``"auto"`` read as the backend in force (:func:`preferred`).
    (Traced by ``torch.compile``, the read is guarded: a compiled function that reaches it is
    compiled again when it runs under another backend.)"""
    return preferred() if backend == "auto" else backend


@contextmanager
def use(backend: str) -> Iterator[None]:
    """Run the coordinate functions called inside (those of the closed-form families, and what
    calls them: modules, ``deform``, image warping) with ``backend`` wherever they pass
    ``backend="auto"`` (the default), on this thread; a call that names another backend keeps its
    own. Blocks nest; leaving one restores the backend before it. A family that does not have the
    backend raises the error it raises for that ``backend=``.

    Around a compiled function it chooses the backend of the compiled calls (their registered ops
    read it when they run, and the backward pass keeps the forward's); inside a compiled function
    it is refused (the compiled graph would not replay it).

    Args:
        backend: ``"auto"``, ``"native"``, ``"torch"`` or ``"triton"``.

    Raises:
        ValueError: any other value.
        RuntimeError: under ``torch.compile``'s tracing.

    Examples:
        >>> import torch, torchcage
        >>> from torchcage import functional as F
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> x = torch.tensor([[0.1, 0.2, -0.3]], dtype=torch.float64)
        >>> with torchcage.backends.use("torch"):
        ...     w = F.mean_value_coordinates(x, cube)  # the torch kernel
        >>> torchcage.backends.preferred()
        'auto'
        >>> torch.allclose(w, F.mean_value_coordinates(x, cube))
        True
    """
    if torch.compiler.is_compiling():
        raise RuntimeError(
            "torchcage.backends.use() inside a compiled function: the compiled graph would not replay it; "
            "call the compiled function inside the block instead"
        )
    if backend not in BACKENDS:
        raise ValueError(
            f"backend must be one of {', '.join(map(repr, BACKENDS))}, got {backend!r} (torchcage.backends.use)"
        )
    before = preferred()
    _preference.backend = backend
    try:
        yield
    finally:
        _preference.backend = before


@dataclass(frozen=True)
class Op:
    """What kernels an operation has.

    Attributes:
        name: what the error texts call it (``"mean value coordinates"``).
        native: a native C kernel exists.
        native_dims: the dimensions it serves (others take the torch kernel under ``"auto"``).
        native_float64_only: it takes float64 points only (others are refused by ``"native"``,
            served by torch under ``"auto"``); when False the caller casts.
        native_graph: the native kernel serves calls that record an autograd graph (it computes
            derivatives itself); otherwise a graph sends ``"auto"`` to torch and ``"native"`` raises.
        triton: a Triton kernel exists.
        triton_dims: the dimensions it serves.
        triton_auto: ``"auto"`` takes it for CUDA points (False: only ``"triton"`` does, e.g. a
            kernel not yet checked on a device).
    """

    name: str
    native: bool = True
    native_dims: tuple[int, ...] = (3,)
    native_float64_only: bool = True
    native_graph: bool = False
    triton: bool = False
    triton_dims: tuple[int, ...] = (3,)
    triton_auto: bool = True

    @property
    def supported(self) -> tuple[str, ...]:
        """The ``backend=`` values this operation accepts."""
        return ("auto", *(("native",) if self.native else ()), "torch", *(("triton",) if self.triton else ()))


@dataclass(frozen=True)
class Choice:
    """The kernel chosen for a call: ``kind`` and, for ``"native"``, the loaded library."""

    kind: Literal["native", "triton", "torch"]
    lib: ctypes.CDLL | None = None


def check(op: Op, backend: str) -> None:
    """Refuse a ``backend`` value that ``op`` does not accept.

    Raises:
        ValueError: ``backend must be one of 'auto', ... for <op>, got <value>``.
    """
    if backend not in op.supported:
        where = " (the backend in force: torchcage.backends.use)" if backend == preferred() != "auto" else ""
        raise ValueError(
            f"backend must be one of {', '.join(map(repr, op.supported))} for {op.name}, got {backend!r}{where}"
        )


def select(
    op: Op,
    backend: str,
    points: torch.Tensor,
    cage_vertices: torch.Tensor | None = None,
    *,
    graph: bool | None = None,
) -> Choice:
    """The kernel that serves ``op`` for ``points`` ``(N, D)`` (and the cage's vertices).

    Args:
        op: the operation.
        backend: the user's ``backend=``, resolved (:func:`resolve`) by the public function.
        points: the query points (their device, dtype and ``D`` decide).
        cage_vertices: the cage's vertices (whether they require grad).
        graph: whether the call records an autograd graph (default: a ``torch.func`` transform
            wraps the points or the vertices, or grad mode is on and one of them requires grad).

    Returns:
        The :class:`Choice`.

    Raises:
        ValueError: a value ``op`` does not accept (see :func:`check`), or ``"native"`` /
            ``"triton"`` for points of a dimension that kernel does not serve.
        RuntimeError: ``"native"`` or ``"triton"`` where that kernel cannot serve this call; the
            message says why and what to use instead.
    """
    check(op, backend)
    if graph is None:
        tensors = (points,) if cage_vertices is None else (points, cage_vertices)
        # (_core.common.records_graph's test, written out: backends sit below _core)
        graph = any(
            is_functorch_wrapped_tensor(t) or forward_ad.unpack_dual(t).tangent is not None  # (forward mode)
            for t in tensors
        ) or (torch.is_grad_enabled() and any(t.requires_grad for t in tensors))
    dim = points.shape[-1]
    if backend == "torch":
        return Choice("torch")
    if backend == "triton":
        if dim not in op.triton_dims:
            raise ValueError(
                f"backend='triton' for {op.name} serves {_dims(op.triton_dims)}, got {dim}D points; use 'auto'"
            )
        if graph:
            raise RuntimeError(
                f"the Triton kernel of {op.name} records no autograd graph; use backend='auto' to differentiate "
                "(values then come from the Triton kernel inside the autograd Function where one exists, "
                "derivatives from the closed forms or autograd of the torch kernel)"
            )
        why = _triton.reason(points)
        if why is not None:
            raise RuntimeError(f"backend='triton' cannot serve {op.name}: {why}")
        return Choice("triton")
    if backend == "native":
        return Choice("native", _native_library(op, points, graph, dim))
    # auto
    if op.triton and op.triton_auto and points.device.type == "cuda" and dim in op.triton_dims and not graph:
        if _triton.available(points):
            return Choice("triton")
    if (
        op.native
        and points.device.type == "cpu"
        and dim in op.native_dims
        and (op.native_graph or not graph)
        and (points.dtype == torch.float64 or not op.native_float64_only)
    ):
        lib = _native.library()
        if lib is not None:
            return Choice("native", lib)
    return Choice("torch")


def _native_library(op: Op, points: torch.Tensor, graph: bool, dim: int) -> ctypes.CDLL:
    """The library for ``backend="native"``, or the reason it cannot serve."""
    if dim not in op.native_dims:
        raise ValueError(
            f"backend='native' for {op.name} serves {_dims(op.native_dims)}, got {dim}D points; use 'auto'"
        )
    if graph and not op.native_graph:
        raise RuntimeError(
            f"the native kernel of {op.name} records no autograd graph; use backend='torch' (or 'auto') to "
            "differentiate with respect to the points or the cage vertices"
        )
    if points.device.type != "cpu" or (op.native_float64_only and points.dtype != torch.float64):
        need = "float64 points on the CPU" if op.native_float64_only else "points on the CPU"
        raise RuntimeError(
            f"the native kernel of {op.name} needs {need}, got {points.dtype} on {points.device.type}; use "
            "backend='auto' (which falls back to the torch kernel) or backend='torch'"
        )
    lib = _native.library()
    if lib is None:
        raise RuntimeError(
            f"the native kernel of {op.name} is unavailable ({_native.failure_reason()}); use backend='torch' "
            "(or 'auto', which falls back to it)"
        )
    return lib


def _dims(dims: tuple[int, ...]) -> str:
    return " and ".join(f"{d}D" for d in dims) + " points"
