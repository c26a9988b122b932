"""Install-time build of torchcage's native CPU kernels (plain C shared libraries loaded with
ctypes, not Python extension modules). Everything else is in pyproject.toml.

Each library is an optional extension: where a compiler or OpenMP is missing the install still
succeeds, and torchcage falls back to a run-time build, then to its torch kernels.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

HERE = Path(__file__).parent
NATIVE = HERE / "torchcage" / "backends" / "native"
_spec = importlib.util.spec_from_file_location("_tc_build", NATIVE / "_buildspec.py")
_build = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_build)


class BuildNative(build_ext):
    """Compiler-specific flags (MSVC takes its own) and no Python module init: the libraries are
    loaded with ctypes."""

    def build_extension(self, ext: Extension) -> None:
        if self.compiler.compiler_type == "msvc":
            ext.extra_compile_args = ["/O2", "/openmp", "/fp:fast"]
            ext.extra_link_args = []
            ext.libraries = []
        # the variants compile the same sources with different flags: separate object folders
        temp = self.build_temp
        self.build_temp = str(Path(temp) / ext.name.rsplit(".", 1)[-1])
        try:
            super().build_extension(ext)
        finally:
            self.build_temp = temp

    def get_export_symbols(self, ext: Extension) -> list[str]:
        return []  # no PyInit_<name>: these are not Python modules


extensions = [
    Extension(
        f"torchcage.backends.native.{name}",
        sources=[f"torchcage/backends/native/{s}" for s in _build.SOURCES],
        depends=[f"torchcage/backends/native/{h}" for h in _build.HEADERS],
        extra_compile_args=[*_build.BASE_FLAGS, *flags],
        extra_link_args=["-fopenmp"],
        libraries=[*libs, "m"],
        define_macros=[("TC_SOURCE_DIGEST", f'"{_build.source_digest(NATIVE)}"')],
        optional=True,
    )
    for name, (flags, libs) in _build.prebuilt_variants().items()
]

setup(ext_modules=extensions, cmdclass={"build_ext": BuildNative})
