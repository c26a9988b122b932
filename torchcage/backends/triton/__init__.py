"""Triton kernels (optional: ``pip install torchcage[triton]``): the closed-form coordinates on GPUs,
and on CPU tensors through Triton's interpreter (``TRITON_INTERPRET=1``), which is how the test
suite checks them against the native kernels.

Nothing here imports triton at import time: :func:`available` says whether a kernel can run on a
tensor, :func:`reason` why not. The kernels follow the formulas of the native kernels, point by
point (``torchcage/backends/native/*.c``, whose docstrings derive them); the rare cases those handle with
long special forms (thin faces seen from a few widths) are flagged by the kernels and redone by the
torch kernel, so every value comes from one formulation.
"""

from __future__ import annotations

import importlib.util
import os

import torch

__all__ = ["available", "device_function", "interpreted", "reason", "warps"]


def interpreted() -> bool:
    """Whether Triton runs its interpreter (``TRITON_INTERPRET=1``: kernels on CPU tensors)."""
    return os.environ.get("TRITON_INTERPRET", "0") not in ("", "0")


def device_function(fn=None, *, noinline: bool = False):  # a decorator of Triton device functions
    """``triton.jit`` for a device function called by kernels (``noinline=True``: compiled once and
    called, for large functions called several times, which keeps the kernels' compile time in
    bounds); under the interpreter the plain function (each call of a jit function there patches
    ``triton.language`` anew, about 1 ms, and the kernel's own patch already holds while it runs;
    the compiled path is unchanged)."""
    import triton

    def wrap(f):
        return f if interpreted() else triton.jit(f, noinline=noinline)

    return wrap if fn is None else wrap(fn)


def warps(block: int) -> int:
    """Warps per program for a block of ``block`` points, one point per thread (1 to 4): a 1D block
    smaller than ``32 num_warps`` is replicated across the warps, every warp doing the same work
    (Triton's default is 4 warps)."""
    return max(1, min(4, block // 32))


def point_batch(
    x: torch.Tensor, cages: int, kernel: str, what: str = "cages", dim: int = 3
) -> tuple[torch.Tensor, bool]:
    """A Triton wrapper's points ``x`` as ``(XB, n, D)`` contiguous, and whether they came batched:
    ``(n, D)`` for tables of one cage, or ``(XB, n, D)`` with ``XB`` 1 (shared) or ``cages``.

    Raises:
        ValueError: points of another shape than ``(n, dim)`` or ``(XB, n, dim)``, or whose batch
            is neither 1 nor ``cages`` (naming ``kernel`` and ``what``).

    Examples:
        >>> X, batched = point_batch(torch.zeros(5, 2), 1, "k", dim=2)
        >>> tuple(X.shape), batched
        ((1, 5, 2), False)
    """
    batched = x.dim() == 3
    X = x.contiguous() if batched else x.contiguous()[None]
    D = dim
    if x.dim() not in (2, 3) or x.shape[-1] != dim or X.shape[0] not in (1, cages) or (not batched and cages != 1):
        raise ValueError(
            f"{kernel}: points of shape {tuple(x.shape)} for tables of {cages} {what}: give (1 or {cages}, n, {D})"
            + (f" or (n, {D})" if cages == 1 else "")
        )
    return X, batched


def reason(t: torch.Tensor | None = None) -> str | None:
    """Why the Triton kernels cannot serve tensor ``t`` (any tensor when ``None``), or ``None``."""
    if importlib.util.find_spec("triton") is None:
        return "triton is not installed (pip install torchcage[triton]; CUDA builds of torch ship it)"
    if t is None:
        return None
    if t.device.type == "cuda":
        return None
    if t.device.type == "cpu" and interpreted():
        return None
    return (
        f"Triton kernels run on CUDA tensors (or on CPU tensors with TRITON_INTERPRET=1), got a tensor on "
        f"{t.device.type}"
    )


def available(t: torch.Tensor | None = None) -> bool:
    """Whether the Triton kernels can serve tensor ``t``."""
    return reason(t) is None
