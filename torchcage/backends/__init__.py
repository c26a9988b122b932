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
from dataclasses import dataclass
from typing import Literal

import torch
from torch._C._functorch import is_functorch_wrapped_tensor
from torch.autograd import forward_ad

from torchcage.backends import native as _native
from torchcage.backends import triton as _triton

__all__ = ["BACKENDS", "Backend", "Choice", "Op", "check", "select"]

#: Every value of ``backend=`` that some operation accepts.
BACKENDS = ("auto", "native", "torch", "triton")
Backend = Literal["auto", "native", "torch", "triton"]


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
        raise ValueError(f"backend must be one of {', '.join(map(repr, op.supported))} for {op.name}, got {backend!r}")


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
        backend: the user's ``backend=``.
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
