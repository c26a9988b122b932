"""Optional native CPU kernels: built at install time, else compiled on first use.

The torch kernels in :mod:`torchcage.functional` run everywhere (CPU, GPU, any dtype). For the
hot path on CPU in float64, a plain-C version of the same formulas, parallel over points with
OpenMP, is about ten times faster. ``pip install`` builds it (``setup.py``: an AVX2 library and a
baseline one on x86-64 Linux) and the loader takes the first that this CPU runs (:func:`variant`
says which). Where no prebuilt library loads, it is compiled once into a cache folder
(``$TORCHCAGE_CACHE``, else ``~/.cache/torchcage``), trying the variants from the fastest down
(AVX2 with glibc's vector math, SSE2, plain C, and last without OpenMP, single-threaded). Without
either, or with ``TORCHCAGE_NATIVE=0``, torchcage uses the torch kernels. Extra compiler flags of
the run-time build: ``$TORCHCAGE_CFLAGS``.
"""

from __future__ import annotations

import ctypes
import hashlib
import math
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

from torchcage.backends.native import _buildspec as build_spec
from torchcage.backends.native import abi

__all__ = ["available", "call", "check_workspace", "failure_reason", "library", "variant"]

_SOURCES = build_spec.SOURCES
_HEADERS = build_spec.HEADERS

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_failed: str | None = None
_variant: str = ""


def _compiler() -> str | None:
    for cand in (os.environ.get("CC"), sysconfig.get_config_var("CC"), "cc", "gcc", "clang"):
        if cand:
            exe = shutil.which(cand.split()[0])
            if exe:
                return exe
    return None


def _cpu_flags() -> str:
    return "avx2" if build_spec.cpu_has_avx2() else "base"


def _bind(lib: ctypes.CDLL) -> ctypes.CDLL:
    for name in abi.SIGNATURES:
        fn = getattr(lib, name)
        fn.argtypes = abi.argtypes(name)
        fn.restype = None
    return lib


def _load_prebuilt() -> tuple[ctypes.CDLL, str] | None:
    """The library built at install time (``setup.py``), fastest variant this CPU runs first;
    ``None`` when none is installed or none loads (a missing libgomp or libmvec, say)."""
    here = Path(__file__).parent
    suffix = sysconfig.get_config_var("EXT_SUFFIX") or (".pyd" if sys.platform == "win32" else ".so")
    for name in build_spec.prebuilt_variants():
        if name.endswith("_avx2") and not build_spec.cpu_has_avx2():
            continue
        path = here / f"{name}{suffix}"
        if not path.exists():
            continue
        try:
            lib = ctypes.CDLL(str(path))
            lib.tc_source_digest.restype = ctypes.c_char_p
            if lib.tc_source_digest().decode() != build_spec.source_digest(here):
                continue  # built from other sources (an editable install whose C files changed since)
            lib = _bind(lib)
        except (OSError, AttributeError):  # unloadable here (a missing libgomp or libmvec, say)
            continue
        return lib, f"prebuilt {name.removeprefix('_kernels').removeprefix('_') or 'baseline'} ({path.name})"
    return None


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
    flags = [*build_spec.BASE_FLAGS, "-fPIC", "-shared", f'-DTC_SOURCE_DIGEST="{build_spec.source_digest(here)}"']
    flags += os.environ.get("TORCHCAGE_CFLAGS", "").split()
    # (compile flags, libraries): glibc's vector atan with AVX2, then SSE2, then plain scalar code,
    # then without OpenMP (one thread, same results)
    variants = [(cflags, [f"-l{lib}" for lib in libs]) for cflags, libs in build_spec.runtime_variants()]
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
                    try:  # a library that links may still not load (libmvec symbols of a newer glibc)
                        ctypes.CDLL(str(out))
                        break
                    except OSError as err:
                        errors.append(f"{' '.join(cmd)}: built, but does not load: {err}")
                        continue
                errors.append(f"{' '.join(cmd)}:\n{res.stderr[-1000:]}")
            else:
                raise RuntimeError("\n".join(errors))
            os.replace(out, target)  # atomic: concurrent builders never see a half-written library
    return _bind(ctypes.CDLL(str(target)))


def library() -> ctypes.CDLL | None:
    """The loaded native library: the one built at install time, else built on first use into
    the cache; ``None`` where neither is possible."""
    global _lib, _failed, _variant
    if _lib is not None or _failed is not None:
        return _lib
    with _lock:
        if _lib is None and _failed is None:
            if os.environ.get("TORCHCAGE_NATIVE", "1") == "0":
                _failed = "disabled by TORCHCAGE_NATIVE=0"
            elif (found := _load_prebuilt()) is not None:
                _lib, _variant = found
            else:
                try:
                    _lib = _build()
                    _variant = f"compiled at first use ({_cpu_flags()}) into {_cache_dir()}"
                except Exception as err:  # no compiler, no OpenMP, read-only cache, ...
                    _failed = str(err)
                    first = str(err).strip().splitlines()[0] if str(err).strip() else err.__class__.__name__
                    warnings.warn(
                        "torchcage's native CPU kernels are unavailable: no library built at install time loads "
                        f"here and the run-time build failed ({first[:200]}); using the torch kernels (5 to 10 "
                        "times slower on the CPU). Reinstall with a C compiler present (pip install builds them), "
                        "or set TORCHCAGE_NATIVE=0 to choose the torch kernels silently",
                        stacklevel=3,
                    )
    return _lib


def variant() -> str:
    """Which native library serves (``"prebuilt avx2 (...)"``, ``"compiled at first use ..."``), or
    ``""`` when none is loaded."""
    library()
    return _variant


def failure_reason() -> str:
    """Why the native library is unavailable (empty when it is loaded or not yet tried)."""
    return _failed or ""


def available() -> bool:
    """True when the native kernels can be used."""
    return library() is not None


def call(lib: ctypes.CDLL, name: str, **arguments: object) -> None:
    """Call native entry point ``name`` of ``lib`` by keyword (the names of its C prototype, see
    :mod:`torchcage.backends.native.abi`); ``nthreads`` defaults to ``torch.get_num_threads()``. Every
    argument is checked (dtype, device, contiguity, shape) before a pointer is taken.

    Raises:
        TypeError, ValueError: an argument that does not match the entry point's signature.
    """
    arguments.setdefault("nthreads", torch.get_num_threads())
    getattr(lib, name)(*abi.check_arguments(name, arguments))


def check_workspace(out: torch.Tensor, kernel: str, size: str = "") -> None:
    """Raise ``MemoryError`` when the kernel named ``kernel`` could not allocate its workspace: the
    kernels say so by a NaN in the first entry of ``out`` (every entry NaN), a value they never
    give otherwise. ``size``: the workspace's size, for the message (e.g. ``"about 3 MB per thread"``).

    Examples:
        >>> check_workspace(torch.zeros(2, 3), "quad mean value")  # a filled output: no error
    """
    if out.numel() and math.isnan(float(out.reshape(-1)[0])):
        _refuse_workspace(kernel, size)


#: The flag value of every point of a call whose kernel could not allocate its workspace (kernels
#: whose outputs may hold NaN of their own, rows where the total weight vanishes, say so in their
#: uint8 flags instead: see :func:`check_workspace_flags`).
WORKSPACE_FAILED = 3


def check_workspace_flags(flags: torch.Tensor, kernel: str) -> None:
    """Raise ``MemoryError`` when the kernel named ``kernel`` could not allocate its workspace: the
    kernels say so by :data:`WORKSPACE_FAILED` in every entry of their uint8 ``flags``, a value
    they never give otherwise.

    Examples:
        >>> check_workspace_flags(torch.zeros(4, dtype=torch.uint8), "mean value derivatives")
    """
    if flags.numel() and int(flags.reshape(-1)[0]) == WORKSPACE_FAILED:
        _refuse_workspace(kernel, "")


def _refuse_workspace(kernel: str, size: str) -> None:
    raise MemoryError(
        f"the native {kernel} kernel could not allocate its per-thread workspace"
        f"{f' ({size})' if size else ''}; use fewer threads (torch.set_num_threads), fewer points per "
        "chunk (chunk_size) or backend='torch'"
    )
