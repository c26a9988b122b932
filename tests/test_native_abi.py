"""The native calling interface: the Python tables in ``torchcage/backends/native/abi.py`` agree with the
C prototypes (names and types, in order), and calls are checked before any pointer is taken."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from torchcage.backends.native import abi

NATIVE = Path(abi.__file__).parent


def _c_prototypes() -> dict[str, list[tuple[str, str]]]:
    """``{name: [(C type, argument name), ...]}`` of every exported ``void tc_*(...)`` definition."""
    out = {}
    for src in sorted(NATIVE.glob("*.c")):
        text = re.sub(r"/\*.*?\*/", "", src.read_text(), flags=re.S)
        for m in re.finditer(r"^void\s+(tc_\w+)\s*\(([^)]*)\)\s*\{", text, flags=re.M):
            params = []
            for p in m[2].split(","):
                p = " ".join(p.split())
                pm = re.fullmatch(r"(const\s+)?(unsigned char|[A-Za-z_]\w*)\s*(\*?)\s*(\w+)", p)
                assert pm, f"{src.name}: cannot read parameter {p!r} of {m[1]}"
                ctype = f"{pm[1] or ''}{pm[2]}{' *' if pm[3] else ''}"
                params.append((ctype, pm[4]))
            out[m[1]] = params
    return out


def test_every_signature_matches_its_c_prototype() -> None:
    protos = _c_prototypes()
    for name, sig in abi.SIGNATURES.items():
        assert name in protos, f"{name} is declared in abi.py but defined in no C file"
        assert [(a.c_type, a.name) for a in sig] == protos[name], f"{name}: abi.py and the C prototype differ"


def test_the_prototype_reader_sees_every_entry_point() -> None:
    # The entry points the library loads are exactly those abi.py declares; the others are shared
    # helpers between C files (they take structs or single points, never torch's arrays).
    basic = {"double", "long", "int", "unsigned char", "const double *", "double *", "const int *", "int *",
             "const unsigned char *", "unsigned char *"}  # fmt: skip
    protos = _c_prototypes()
    helpers = {name for name, params in protos.items() if any(t not in basic for t, _ in params)}
    assert helpers, "the reader should see the struct-taking helpers too"
    pair_helpers = {"tc_stable_face", "tc_quad_integrals", "tc_quad_whole"}  # one point (and face or quad)
    assert set(protos) - helpers - pair_helpers == set(abi.SIGNATURES)


def test_shapes_name_only_scalar_arguments() -> None:
    for name, sig in abi.SIGNATURES.items():
        scalars = {a.name for a in sig if not a.pointer}
        for a in sig:
            for dim in a.shape or ():
                for tok in re.findall(r"[A-Za-z_]\w*", dim):
                    assert tok in scalars, f"{name}.{a.name}: shape names {tok!r}, not a scalar argument"


def _mvc2d_args(**over: object) -> dict[str, object]:
    args: dict[str, object] = {
        "B": 1,
        "P": torch.zeros(1, 4, 2, dtype=torch.float64),
        "V": 4,
        "edges": torch.zeros(4, 2, dtype=torch.int32),
        "E": 4,
        "X": torch.zeros(1, 3, 2, dtype=torch.float64),
        "XB": 1,
        "n": 3,
        "tol": torch.full((1,), 1e-12, dtype=torch.float64),
        "nthreads": 1,
        "W": torch.zeros(1, 3, 4, dtype=torch.float64),
        "on": torch.zeros(1, 3, dtype=torch.uint8),
    }
    args.update(over)
    return args


def test_a_valid_call_becomes_pointers_and_scalars() -> None:
    args = _mvc2d_args()
    flat = abi.check_arguments("tc_mvc2d", args)
    assert flat[0] == 1 and flat[1] == args["P"].data_ptr() and flat[2] == 4  # type: ignore[union-attr]
    assert flat[8] == args["tol"].data_ptr()  # type: ignore[union-attr]


@pytest.mark.parametrize(
    ("over", "error", "match"),
    [
        ({"P": torch.zeros(1, 4, 2, dtype=torch.float32)}, ValueError, "'P' must be a contiguous CPU torch.float64"),
        ({"P": torch.zeros(1, 2, 4, dtype=torch.float64).transpose(1, 2)}, ValueError, "contiguous: False"),
        ({"W": torch.zeros(1, 3, 5, dtype=torch.float64)}, ValueError, "'W' must have shape"),
        ({"edges": torch.zeros(4, 2, dtype=torch.int64)}, ValueError, "'edges'"),
        ({"V": torch.tensor(4)}, TypeError, "'V' is a scalar"),
        ({"X": [[0.0, 0.0]]}, TypeError, "'X' must be a tensor"),
        ({"on": None}, TypeError, "'on' must be a tensor"),
        ({"extra": 1}, TypeError, "unknown arguments \\['extra'\\]"),
    ],
)
def test_a_bad_argument_is_named(over: dict, error: type, match: str) -> None:
    with pytest.raises(error, match=match):
        abi.check_arguments("tc_mvc2d", _mvc2d_args(**over))


def test_a_missing_argument_is_named() -> None:
    args = _mvc2d_args()
    del args["tol"]
    with pytest.raises(TypeError, match="missing arguments \\['tol'\\]"):
        abi.check_arguments("tc_mvc2d", args)


def test_optional_outputs_may_be_null() -> None:
    sig = {a.name: a for a in abi.SIGNATURES["tc_gc3d"]}
    assert sig["ONF"].optional and sig["AL"].optional and not sig["PHI"].optional


def test_a_failed_workspace_becomes_a_memory_error() -> None:
    """The kernels mark a failed allocation by NaN outputs; the glue turns it into a MemoryError that
    names the kernel and the remedies, and lets filled outputs (and empty ones) through."""
    from torchcage.backends.native import check_workspace

    check_workspace(torch.zeros(3, 4), "quad mean value")
    check_workspace(torch.empty(0, 4), "quad mean value")
    with pytest.raises(MemoryError, match=r"quad Green kernel .*\(about 2 MB per thread\).*set_num_threads"):
        check_workspace(torch.full((3, 4), float("nan")), "quad Green", "about 2 MB per thread")


@pytest.mark.native
def test_green_derivatives_report_a_failed_workspace(monkeypatch) -> None:
    """tc_gcd3d marks a workspace it could not allocate by NaN gradients (gcd3d.c); the glue raises
    MemoryError instead of returning them (simulated: the call marks them so)."""
    from support import cube

    import torchcage.functional as F
    from torchcage.backends import native as _native
    from torchcage.families.green import derivatives3d_native as glue

    if not _native.available():
        pytest.skip("native kernels not available")
    real = _native.call

    def failing(lib, name, **kw):
        real(lib, name, **kw)
        if name == "tc_gcd3d":
            kw["GPHI"].fill_(float("nan"))  # as the kernel marks a failed allocation

    monkeypatch.setattr(glue._native, "call", failing)
    x = torch.tensor([[0.1, 0.2, -0.3]], dtype=torch.float64)
    with pytest.raises(MemoryError, match="Green derivatives kernel"):
        F.green_derivatives(x, cube(), backend="native")
