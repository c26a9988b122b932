"""Large outputs on transparent huge pages (torchcage._core.alloc): the advice reaches the kernel's
mapping of a large tensor and no other, and the allocation helpers return what torch.empty and
torch.cat would (values, shapes, graphs)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from support import box_cage, box_points

import torchcage.functional as F
from torchcage._core.alloc import HUGE_PAGE_MIN_BYTES, advise_huge_pages, cat_output, empty_output

THP = Path("/sys/kernel/mm/transparent_hugepage/enabled")


def _vm_flags(address: int) -> list[str]:
    """The VmFlags of the mapping holding ``address`` in /proc/self/smaps."""
    flags: list[str] | None = None
    inside = False
    for line in Path("/proc/self/smaps").read_text().splitlines():
        head = line.split()[0]
        if "-" in head and not head.endswith(":"):
            lo, hi = (int(v, 16) for v in head.split("-"))
            inside = lo <= address < hi
        elif inside and head == "VmFlags:":
            flags = line.split()[1:]
    assert flags is not None, "no mapping holds the tensor"
    return flags


@pytest.mark.skipif(not sys.platform.startswith("linux") or not THP.exists(), reason="Linux with THP only")
def test_large_output_is_advised_and_small_is_not() -> None:
    big = empty_output(2 * HUGE_PAGE_MIN_BYTES // 8, dtype=torch.float64)
    # (the advice covers the whole pages inside the tensor: its middle page is in an advised range)
    assert "hg" in _vm_flags(big.data_ptr() + big.numel() * 4)
    small = torch.empty(1024, dtype=torch.float64)
    assert advise_huge_pages(small) is False
    strided = torch.empty(2 * HUGE_PAGE_MIN_BYTES // 8, 2, dtype=torch.float64)[:, 0]
    assert advise_huge_pages(strided) is False


def test_empty_output_is_a_plain_tensor() -> None:
    out = empty_output(HUGE_PAGE_MIN_BYTES // 4, 2, dtype=torch.float32)
    assert out.shape == (HUGE_PAGE_MIN_BYTES // 4, 2) and out.dtype == torch.float32 and out.is_contiguous()
    out.fill_(3.0)
    assert float(out.sum()) == 3.0 * out.numel()


def test_cat_output_equals_cat_and_keeps_graphs() -> None:
    g = torch.Generator().manual_seed(0)
    parts = [torch.randn(n, 5, generator=g, dtype=torch.float64) for n in (7, 0, 3)]
    assert torch.equal(cat_output(parts), torch.cat(parts))
    assert torch.equal(cat_output(parts, dim=0), torch.cat(parts, 0))
    cols = [torch.randn(4, n, generator=g) for n in (2, 5)]
    assert torch.equal(cat_output(cols, dim=1), torch.cat(cols, 1))
    leaf = torch.randn(3, 5, dtype=torch.float64, requires_grad=True)
    out = cat_output([parts[0], leaf * 2])
    out.sum().backward()
    assert leaf.grad is not None and torch.equal(leaf.grad, torch.full((3, 5), 2.0, dtype=torch.float64))


def test_coordinates_on_advised_outputs_are_the_coordinates() -> None:
    """Outputs above the threshold (mean value and Green coordinates of 30,000 points on a box of
    152 vertices: 36 MB each) keep partition of unity and linear precision: the advice changes no
    value."""
    cage = box_cage(5, 5, 5).triangulated()
    x = box_points(cage, 30_000, spread=0.9)
    v = cage.vertices.to(torch.float64)
    w = F.mean_value_coordinates(x, cage)
    assert w.numel() * w.element_size() >= HUGE_PAGE_MIN_BYTES
    assert torch.allclose(w.sum(1), torch.ones(len(x), dtype=torch.float64), atol=1e-13)
    assert torch.allclose(w @ v, x, atol=1e-12)
    phi, psi = F.green_coordinates(x, cage)
    assert torch.allclose(phi @ v + psi @ cage.triangle_normals().to(torch.float64), x, atol=1e-12)


def test_the_advised_range_lies_inside_the_tensor(monkeypatch) -> None:
    """The advice covers whole pages inside the tensor's memory and nothing outside it (recorded
    calls, tensors at offsets that are not page-aligned; memory around a tensor may belong to
    others, so this is checked on the range itself, not on the mappings)."""
    from torchcage._core import alloc

    calls: list[tuple[int, int]] = []
    monkeypatch.setattr(alloc, "_madvise", lambda lo, n, advice: calls.append((lo, n)) or 0)
    base = torch.empty(HUGE_PAGE_MIN_BYTES // 8 + 4096, dtype=torch.float64)
    for offset in (0, 1, 7, 513):
        t = base[offset : offset + HUGE_PAGE_MIN_BYTES // 8]
        assert alloc.advise_huge_pages(t)
        lo, n = calls[-1]
        start, end = t.data_ptr(), t.data_ptr() + t.numel() * 8
        assert lo % alloc._PAGE == 0 and n % alloc._PAGE == 0
        assert start <= lo and lo + n <= end and lo - start < alloc._PAGE and end - (lo + n) < alloc._PAGE
