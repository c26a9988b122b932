"""The one backend mechanism (:mod:`torchcage.backends`): every family accepts the same values the
same way, refuses the others with one text, and the registry's ``backends`` say what each takes."""

from __future__ import annotations

import warnings

import pytest
import torch

import torchcage
from torchcage import functional as F
from torchcage.backends import BACKENDS
from torchcage.families import FAMILIES

D64 = torch.float64
CLOSED = [f for f in FAMILIES if f.backends]


def _call(fn, x, cage, backend):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = fn(x, cage, backend=backend)
    return out if isinstance(out, tuple) else (out,)


def _cage(fam):
    cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
    return cube.triangulated() if fam.faces == "triangles" else cube


@pytest.mark.parametrize("fam", CLOSED, ids=lambda f: f.short)
def test_every_value_behaves_the_same_for_every_family(fam) -> None:
    cage, fn = _cage(fam), fam.function()
    x = torch.tensor([[0.1, 0.2, -0.3], [0.5, -0.4, 0.2]], dtype=D64)
    ref = _call(fn, x, cage, "torch")
    ops = {"mvc": "MVC", "gc": "GC", "qmvc": "QMVC", "qgc": "QGC"}
    module = __import__(fam.function().__module__.replace(".api", ".dispatch") if fam.short in ("mvc", "gc")
                        else fam.function().__module__, fromlist=["x"])  # fmt: skip
    assert getattr(module, ops[fam.short]).supported == ("auto", *fam.backends)  # the registry says what select does
    for backend in BACKENDS:
        if backend not in ("auto", *fam.backends):
            with pytest.raises(ValueError, match=f"backend must be one of 'auto', .* got '{backend}'"):
                _call(fn, x, cage, backend)
            continue
        try:
            out = _call(fn, x, cage, backend)
        except RuntimeError as err:  # a kernel that cannot serve here says why
            assert backend in ("native", "triton") and "backend=" in str(err), err
            continue
        for a, b in zip(out, ref, strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    for bad in ("cuda", "gpu", "", "Native"):
        with pytest.raises(ValueError, match="backend must be one of 'auto'"):
            _call(fn, x, cage, bad)


@pytest.mark.parametrize(
    "fn", [F.mean_value_derivatives, F.green_derivatives], ids=["mean_value_derivatives", "green_derivatives"]
)
def test_derivatives_refuse_with_the_same_text(fn) -> None:
    cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
    with pytest.raises(ValueError, match="backend must be one of 'auto', 'native', 'torch'"):
        fn(torch.zeros(1, 3, dtype=D64), cube, backend="cuda")


def test_triton_without_a_device_says_why() -> None:
    """On CPU tensors without Triton's interpreter, ``backend="triton"`` is a RuntimeError that
    names the reason, for every family that has a Triton kernel."""
    import os

    if os.environ.get("TRITON_INTERPRET", "0") not in ("", "0"):
        pytest.skip("the interpreter serves CPU tensors")
    x = torch.tensor([[0.1, 0.2, -0.3]], dtype=D64)
    for fam in CLOSED:
        if "triton" in fam.backends:
            with pytest.raises(RuntimeError, match=r"[Tt]riton"):
                _call(fam.function(), x, _cage(fam), "triton")
