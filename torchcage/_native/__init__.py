"""Optional native CPU kernels, compiled on first use with the system C compiler.

The torch kernels in :mod:`torchcage.functional` run everywhere (CPU, GPU, any dtype). For the
hot path on CPU in float64, a plain-C version of the same formulas, parallel over points with
OpenMP, is about ten times faster. It is compiled once (about a second) into a cache folder
(``$TORCHCAGE_CACHE``, else ``~/.cache/torchcage``) and loaded with :mod:`ctypes`. Builds are
tried from the fastest variant down (AVX2 with glibc's vector math, SSE2, plain C, and last
without OpenMP, single-threaded). Without a C compiler, or with ``TORCHCAGE_NATIVE=0``, torchcage
uses the torch kernels. Extra compiler flags: ``$TORCHCAGE_CFLAGS``.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import threading
import warnings
from pathlib import Path

import torch

from . import abi

__all__ = ["available", "call", "failure_reason", "library", "select"]

_SOURCES = ("mvc3d.c", "mvc2d.c", "gc3d.c", "raster.c", "qmvc3d.c", "qgc3d.c", "mvcd3d.c", "mvcd2d.c", "mvc3d_vjp.c")
_HEADERS = ("native.h", "jet.h")

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_failed: str | None = None


def _compiler() -> str | None:
    for cand in (os.environ.get("CC"), sysconfig.get_config_var("CC"), "cc", "gcc", "clang"):
        if cand:
            exe = shutil.which(cand.split()[0])
            if exe:
                return exe
    return None


def _x86_glibc() -> bool:
    import platform

    return platform.machine().lower() in ("x86_64", "amd64") and platform.libc_ver()[0] == "glibc"


def _cpu_flags() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("flags"):
                    return "avx2" if " avx2" in line and " fma" in line else "base"
    except OSError:
        pass
    return "base"


def _cache_dir() -> Path:
    root = os.environ.get("TORCHCAGE_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "torchcage")
    return Path(root)


def _build() -> ctypes.CDLL:
    here = Path(__file__).parent
    sources = [here / s for s in _SOURCES]
    cc = _compiler()
    if cc is None:
        raise RuntimeError("no C compiler found (set CC)")
    # -fno-trapping-math: selects vectorise (nothing reads floating-point exception flags);
    # -fno-tree-loop-distribute-patterns: gcc 12.2 -O3 miscompiled a loop of in-place sums after
    # a zeroing store when it split the loop around a memset (found in qgc3d.c, reproduced alone).
    flags = ["-O3", "-fno-math-errno", "-fno-trapping-math", "-fno-tree-loop-distribute-patterns", "-fPIC",
             "-shared", "-fopenmp", "-std=c99"]  # fmt: skip
    flags += os.environ.get("TORCHCAGE_CFLAGS", "").split()
    # (compile flags, libraries): glibc's vector atan with AVX2, then SSE2, then plain scalar code.
    variants: list[tuple[list[str], list[str]]] = [([], [])]
    if _x86_glibc():
        mvec = (["-DTC_LIBMVEC"], ["-lmvec"])
        variants = [mvec, ([], [])]
        if _cpu_flags() == "avx2":
            variants.insert(0, (["-mavx2", "-mfma", "-DTC_LIBMVEC"], ["-lmvec"]))
    variants.append((["-fno-openmp"], []))  # a compiler without OpenMP: one thread, same results
    digest = hashlib.sha256()
    for src in [*sources, *(here / h for h in _HEADERS)]:
        digest.update(src.read_bytes())
    digest.update(" ".join([cc, *flags, sys.platform, _cpu_flags()]).encode())
    ext = ".dll" if sys.platform == "win32" else ".so"
    target = _cache_dir() / f"torchcage_native_{digest.hexdigest()[:16]}{ext}"
    if not target.exists():
        target.parent.mkdir(parents=True, exist_ok=True)
        errors = []
        with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
            out = Path(tmp) / target.name
            for cflags, libs in variants:
                cmd = [cc, *flags, *cflags, *map(str, sources), "-o", str(out), *libs, "-lm"]
                res = subprocess.run(cmd, capture_output=True, text=True)
                if res.returncode == 0:
                    break
                errors.append(f"{' '.join(cmd)}:\n{res.stderr[-1000:]}")
            else:
                raise RuntimeError("\n".join(errors))
            os.replace(out, target)  # atomic: concurrent builders never see a half-written library
    lib = ctypes.CDLL(str(target))
    for name in abi.SIGNATURES:
        fn = getattr(lib, name)
        fn.argtypes = abi.argtypes(name)
        fn.restype = None
    return lib


def library() -> ctypes.CDLL | None:
    """The loaded native library, building it on first use; ``None`` where it cannot be built."""
    global _lib, _failed
    if _lib is not None or _failed is not None:
        return _lib
    with _lock:
        if _lib is None and _failed is None:
            if os.environ.get("TORCHCAGE_NATIVE", "1") == "0":
                _failed = "disabled by TORCHCAGE_NATIVE=0"
            else:
                try:
                    _lib = _build()
                except Exception as err:  # no compiler, no OpenMP, read-only cache, ...
                    _failed = str(err)
                    warnings.warn(
                        f"torchcage's native CPU kernels are unavailable ({err.__class__.__name__}); "
                        "using the (slower) torch kernels",
                        stacklevel=3,
                    )
    return _lib


def failure_reason() -> str:
    """Why the native library is unavailable (empty when it is loaded or not yet tried)."""
    return _failed or ""


def available() -> bool:
    """True when the native kernels can be used."""
    return library() is not None


def select(
    backend: str, points: torch.Tensor, cage_vertices: torch.Tensor, dims: tuple[int, ...] = (3,)
) -> ctypes.CDLL | None:
    """The native library when it should serve a call, else ``None`` (use the torch kernel).

    ``"auto"`` takes it for float64 CPU points of a dimension in ``dims`` when no autograd graph is
    needed (neither the points nor the cage vertices require grad); ``"native"`` insists and raises
    where it cannot serve; ``"torch"`` never takes it.

    Raises:
        ValueError: an unknown backend.
        RuntimeError: ``"native"`` where the native kernel cannot serve (the message says why).
    """
    if backend not in ("auto", "native", "torch"):
        raise ValueError(f"backend must be 'auto', 'native' or 'torch', got {backend!r}")
    if backend == "torch" or points.shape[-1] not in dims:
        return None
    if torch.is_grad_enabled() and (points.requires_grad or cage_vertices.requires_grad):
        if backend == "native":
            raise RuntimeError(
                "the native kernel records no autograd graph; use backend='torch' (or 'auto') to "
                "differentiate with respect to the points or the cage vertices"
            )
        return None
    ok = points.device.type == "cpu" and points.dtype == torch.float64
    lib = library() if ok else None
    if backend == "native" and lib is None:
        raise RuntimeError(
            "the native kernel needs float64 points on the CPU and a C compiler; use backend='torch' "
            "(or 'auto', which falls back to it)"
        )
    return lib


def call(lib: ctypes.CDLL, name: str, **arguments: object) -> None:
    """Call native entry point ``name`` of ``lib`` by keyword (the names of its C prototype, see
    :mod:`torchcage._native.abi`); ``nthreads`` defaults to ``torch.get_num_threads()``. Every
    argument is checked (dtype, device, contiguity, shape) before a pointer is taken.

    Raises:
        TypeError, ValueError: an argument that does not match the entry point's signature.
    """
    arguments.setdefault("nthreads", torch.get_num_threads())
    getattr(lib, name)(*abi.check_arguments(name, arguments))
