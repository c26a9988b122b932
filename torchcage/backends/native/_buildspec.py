"""How the native kernels are compiled: sources, flags and variants, written once for the
install-time build (``setup.py``, which loads this file by path: no torch at build time) and the
run-time fallback build (:mod:`torchcage.backends.native`).

Two prebuilt libraries ship in a wheel (x86-64 with glibc): ``_kernels_avx2`` (AVX2 + FMA, glibc's
vector math) and ``_kernels`` (baseline SSE2 with the vector math; elsewhere plain C). The loader
picks the first that the CPU runs. Without a prebuilt library (an sdist built without a compiler,
an unusual platform) the run-time build tries the variants in order, into a cache folder.
"""

from __future__ import annotations

import hashlib
import platform
from pathlib import Path

__all__ = ["BASE_FLAGS", "HEADERS", "SOURCES", "cpu_has_avx2", "prebuilt_variants", "runtime_variants",
           "source_digest", "x86_glibc"]  # fmt: skip

SOURCES = ("mvc3d.c", "mvc2d.c", "gc3d.c", "gcd3d.c", "raster.c", "qmvc3d.c", "qgc3d.c", "mvcd3d.c", "mvcd2d.c",
           "mvc3d_vjp.c", "mvc3d_vjp_near.c", "gc3d_vjp.c", "geometry.c", "quadrature.c", "lbc.c",
           "version.c")  # fmt: skip
HEADERS = ("native.h", "jet.h")


def source_digest(folder: str | Path) -> str:
    """16 hex digits of the SHA-256 of the kernel sources and headers in ``folder`` (``version.c``
    excluded: it carries the digest). A library whose ``tc_source_digest()`` differs is stale."""
    h = hashlib.sha256()
    for name in (*SOURCES, *HEADERS):
        if name != "version.c":
            h.update((Path(folder) / name).read_bytes())
    return h.hexdigest()[:16]


# -fno-trapping-math: selects vectorise (nothing reads floating-point exception flags);
# -fno-tree-loop-distribute-patterns: gcc 12.2 -O3 miscompiled a loop of in-place sums after a
# zeroing store when it split the loop around a memset (found in qgc3d.c, reproduced alone).
BASE_FLAGS = ("-O3", "-fno-math-errno", "-fno-trapping-math", "-fno-tree-loop-distribute-patterns", "-fopenmp",
              "-std=c99")  # fmt: skip

_AVX2 = (["-mavx2", "-mfma", "-DTC_LIBMVEC"], ["mvec"])
_MVEC = (["-DTC_LIBMVEC"], ["mvec"])
_PLAIN: tuple[list[str], list[str]] = ([], [])


def x86_glibc() -> bool:
    """x86-64 Linux with glibc (where libmvec, glibc's vector math library, exists)."""
    return platform.machine().lower() in ("x86_64", "amd64") and platform.libc_ver()[0] == "glibc"


def cpu_has_avx2() -> bool:
    """Whether this CPU runs AVX2 and FMA code (read from /proc/cpuinfo; False where unknown)."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("flags"):
                    return " avx2" in line and " fma" in line
    except OSError:
        pass
    return False


def prebuilt_variants() -> dict[str, tuple[list[str], list[str]]]:
    """``{library name: (extra compile flags, libraries)}`` built at install time, fastest first."""
    if x86_glibc():
        return {"_kernels_avx2": _AVX2, "_kernels": _MVEC}
    return {"_kernels": _PLAIN}


def runtime_variants() -> list[tuple[list[str], list[str]]]:
    """``(extra flags, libraries)`` the run-time build tries in order; the last drops OpenMP."""
    variants = [_PLAIN]
    if x86_glibc():
        variants = [_MVEC, _PLAIN]
        if cpu_has_avx2():
            variants.insert(0, _AVX2)
    return [*variants, (["-fno-openmp"], [])]
