"""Large output tensors on transparent huge pages.

A coordinate table is large (``N x V`` float64: 35 MB for 28,000 points and 152 vertices, 1.2 GB
for a million points). glibc serves an allocation that large with a fresh ``mmap`` each call, and
the first write to each 4 KiB page of it is a page fault: measured here on 2 cores, filling a fresh
103 MB tensor cost 61 ms against 7 ms for a reused one, a quarter of a Green coordinates call on the
Beast model. Advised with ``MADV_HUGEPAGE`` first, the same fill took 11 ms (2 MiB pages: 512 times
fewer faults). NumPy advises its own large arrays the same way (on Linux, from 4 MB).

:func:`empty_output` is ``torch.empty`` plus that advice for CPU tensors of at least
:data:`HUGE_PAGE_MIN_BYTES` on Linux, before anything writes them; elsewhere (another system, a
GPU tensor, a smaller one, a kernel whose transparent huge pages are off) it is ``torch.empty``. The
advice is a hint: it changes neither the values nor what the caller owns, and a failure is ignored.
"""

from __future__ import annotations

import ctypes
import mmap
import sys

import torch

from torchcage._core.common import records_graph

__all__ = ["HUGE_PAGE_MIN_BYTES", "advise_huge_pages", "cat_output", "empty_output", "zeros_output"]

#: Tensors at least this large are advised (NumPy's threshold for its own arrays). Below glibc's
#: largest mmap threshold (32 MiB) a table may come from glibc's heap, already faulted in, when the
#: previous one was freed; but where the caller keeps its results, or other large arrays come and
#: go between calls (``benchmarks/peers.py`` joins and copies them), the heap grows and shrinks and
#: fresh 4 KiB pages were faulted in on every call: 7,400-11,400 faults and 94-102 ms for a Green
#: call on FireHydrant (two tables of 15 and 29 MB) with only tables of 32 MiB and more advised,
#: 1,400-1,900 faults and 80-84 ms with tables from 2 MiB advised; where the heap is reused (the
#: result freed before the next call) the advice changed nothing (61.6 and 67.0 ms, noise).
HUGE_PAGE_MIN_BYTES = 4 << 20

_PAGE = mmap.PAGESIZE
_MADV_HUGEPAGE = getattr(mmap, "MADV_HUGEPAGE", None) if sys.platform.startswith("linux") else None
_madvise = None
if _MADV_HUGEPAGE is not None:
    try:
        _madvise = ctypes.CDLL(None, use_errno=True).madvise
        _madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
        _madvise.restype = ctypes.c_int
    except (OSError, AttributeError):  # (no libc symbol: the advice is skipped)
        _madvise = None


def advise_huge_pages(t: torch.Tensor) -> bool:
    """Advise the whole pages inside ``t``'s memory (a contiguous CPU tensor) for transparent huge
    pages; returns whether the advice was given (``False``: too small, not contiguous, not on Linux,
    not a CPU tensor, or refused by the kernel).

    Examples:
        >>> t = torch.empty(1 << 24)  # 64 MB of float32
        >>> advise_huge_pages(t) in (True, False)
        True
    """
    nbytes = t.numel() * t.element_size()
    if _madvise is None or t.device.type != "cpu" or nbytes < HUGE_PAGE_MIN_BYTES or not t.is_contiguous():
        return False
    start = t.data_ptr()
    lo = -(-start // _PAGE) * _PAGE  # the first whole page and the end of the last one
    hi = (start + nbytes) // _PAGE * _PAGE
    return hi > lo and _madvise(lo, hi - lo, _MADV_HUGEPAGE) == 0


def empty_output(*shape: int, dtype: torch.dtype, device: torch.device | str | None = None) -> torch.Tensor:
    """``torch.empty(shape, dtype=dtype, device=device)``, on transparent huge pages when large (a
    CPU tensor of at least :data:`HUGE_PAGE_MIN_BYTES` on Linux): for outputs that a kernel then
    writes in full.

    Examples:
        >>> out = empty_output(40_000, 152, dtype=torch.float64)  # 49 MB: advised
        >>> out.shape, out.dtype
        (torch.Size([40000, 152]), torch.float64)
    """
    t = torch.empty(shape, dtype=dtype, device=device)
    advise_huge_pages(t)
    return t


def zeros_output(*shape: int, dtype: torch.dtype, device: torch.device | str | None = None) -> torch.Tensor:
    """``torch.zeros`` on :func:`empty_output`'s memory: for outputs that a kernel writes in part.

    Examples:
        >>> float(zeros_output(3, 2, dtype=torch.float64).abs().sum())
        0.0
    """
    return empty_output(*shape, dtype=dtype, device=device).zero_()


def cat_output(parts: list[torch.Tensor], dim: int = 0) -> torch.Tensor:
    """``torch.cat(parts, dim)`` of a kernel's chunks (at least one part, all of the first part's
    shape but along ``dim``), written into an :func:`empty_output` when no part records a graph
    (``out=`` takes no autograd) and all share the first part's dtype and device (else plain
    ``torch.cat``).

    Examples:
        >>> cat_output([torch.zeros(2, 3), torch.ones(1, 3)]).shape
        torch.Size([3, 3])
    """
    first = parts[0]
    if records_graph(*parts) or any(p.dtype != first.dtype or p.device != first.device for p in parts):
        return torch.cat(parts, dim)
    shape = list(first.shape)
    shape[dim] = sum(p.shape[dim] for p in parts)
    return torch.cat(parts, dim, out=empty_output(*shape, dtype=first.dtype, device=first.device))
