"""Shared fixtures: kernels, devices and dtypes (the builders they share live in support.py)."""

from __future__ import annotations

import os

import pytest
import torch

# Under pytest-xdist (pyproject's -n auto) the workers share the cores: each takes its share of
# threads, so that torch's and the native kernels' thread pools do not oversubscribe them.
if os.environ.get("PYTEST_XDIST_WORKER_COUNT"):
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"])))

#: Kernels of the functions that have a native CPU kernel beside the torch one.
BACKENDS = ["native", "torch"]


@pytest.fixture(params=BACKENDS)
def backend(request) -> str:
    if request.param == "native":
        from torchcage.backends import native as _native

        if not _native.available():
            pytest.skip("no C compiler: native kernel unavailable")
    return request.param


@pytest.fixture(name="lib")
def native_library():
    """The native kernels' library (``ctypes.CDLL``): a test that takes it skips where none loads."""
    from torchcage.backends import native as _native

    lib = _native.library()
    if lib is None:
        pytest.skip("native kernel unavailable")
    return lib


DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    return request.param


@pytest.fixture(params=[torch.float32, torch.float64], ids=["float32", "float64"])
def dtype(request) -> torch.dtype:
    return request.param


def pytest_collection_modifyitems(config, items) -> None:
    """Tests marked ``native`` test the native kernels by name: skip them where none loads."""
    from torchcage.backends import native as _native

    if _native.available():
        return
    skip = pytest.mark.skip(reason=f"native kernel unavailable ({_native.failure_reason()})")
    for item in items:
        if "native" in item.keywords:
            item.add_marker(skip)
