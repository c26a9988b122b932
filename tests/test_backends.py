"""The one backend mechanism (:mod:`torchcage.backends`): every family accepts the same values the
same way, refuses the others with one text, and the registry's ``backends`` say what each takes."""

from __future__ import annotations

import warnings

import pytest
import torch

import torchcage
from torchcage import functional as F
from torchcage._core.compiled import _vmap_records_autograd
from torchcage.backends import BACKENDS
from torchcage.families import FAMILIES

D64 = torch.float64
CLOSED = [f for f in FAMILIES if f.backends]
#: torch 2.5 records no autograd through a custom op's vmap rule: there the families' functions
#: run eagerly under vmap, and their Functions fail inside it (test_contract.py marks the same).
OLD_VMAP = "this torch (2.5) records no autograd through a custom op's vmap rule: the eager path runs under vmap"


def _maps(fam) -> bool:
    """Whether ``torch.func.vmap`` maps the family's function here (mean value coordinates: through
    the native kernel, the torch kernel branching on the data; the others: through their op's vmap
    rule, which torch 2.5 cannot differentiate)."""
    return torchcage.backends.native.available() if fam.short == "mvc" else _vmap_records_autograd()


#: What Dynamo reports for an exception raised in traced code: torch 2.5 shows no message.
REFUSED = r"torchcage.backends.use\('torch'\)|^Observed exception"


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


# ------------------------------------------------------------------ the backend in force: use()
@pytest.fixture
def fresh_dynamo():
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()


def _tuple(out) -> tuple:
    return out if isinstance(out, tuple) else (out,)


def _points() -> torch.Tensor:
    return torch.tensor([[0.1, 0.2, -0.3], [0.5, -0.4, 0.2]], dtype=D64)


@pytest.mark.parametrize("fam", CLOSED, ids=lambda f: f.short)
def test_use_is_the_backend_of_auto_calls(fam, monkeypatch) -> None:
    """Inside ``use(b)`` a call that leaves ``backend="auto"`` runs as ``backend=b`` (the native loader
    is never reached under ``use("torch")``; a backend the family lacks gets its one error text,
    naming the block); a call that names its backend keeps it; the block restores the one before."""
    cage, fn, x = _cage(fam), fam.function(), _points()
    ref = _call(fn, x, cage, "torch")
    with monkeypatch.context() as m:
        m.setattr(torchcage.backends.native, "library", lambda: (_ for _ in ()).throw(AssertionError("native")))
        with torchcage.backends.use("torch"):
            out = _call(fn, x, cage, "auto")
        with pytest.raises(AssertionError, match="native"):  # (outside the block: auto asks for it)
            _call(fn, x, cage, "auto")
    for a, b in zip(out, ref, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    missing = [b for b in BACKENDS if b not in ("auto", *fam.backends)]
    for backend in missing:
        with torchcage.backends.use(backend):
            with pytest.raises(ValueError, match=rf"got '{backend}' \(the backend in force: torchcage.backends.use\)"):
                _call(fn, x, cage, "auto")
            for a, b in zip(_call(fn, x, cage, "torch"), ref, strict=True):  # the call's own backend wins
                torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert torchcage.backends.preferred() == "auto"


def test_use_nests_restores_and_refuses_unknown_values() -> None:
    use, preferred = torchcage.backends.use, torchcage.backends.preferred
    with use("torch"):
        with use("native"):
            assert preferred() == "native"
        assert preferred() == "torch"
        with pytest.raises(RuntimeError, match="boom"), use("triton"):
            raise RuntimeError("boom")
        assert preferred() == "torch"
    assert preferred() == "auto"
    for bad in ("cuda", "", "Torch"):
        with pytest.raises(ValueError, match="backend must be one of 'auto', 'native', 'torch', 'triton'"):
            with use(bad):
                pass


def test_use_is_per_thread() -> None:
    import threading

    seen = []
    with torchcage.backends.use("torch"):
        t = threading.Thread(target=lambda: seen.append(torchcage.backends.preferred()))
        t.start()
        t.join()
        assert torchcage.backends.preferred() == "torch"
    assert seen == ["auto"]


def test_registered_ops_carry_no_backend() -> None:
    """No torchcage op's schema has a backend argument (or any string): the tensors' device and the
    backend in force choose the kernel."""
    names = [f.op for f in FAMILIES if f.op] + [f"{f.op}_backward" for f in FAMILIES if f.op]
    names += ["mean_value_coordinates", "mean_value_derivatives"]
    assert len(names) >= 10
    for name in names:
        schema = getattr(torch.ops.torchcage, name).default._schema
        kinds = {a.name: str(a.type) for a in schema.arguments}
        assert "backend" not in kinds and "str" not in kinds.values(), (name, kinds)


@pytest.mark.parametrize("fam", CLOSED, ids=lambda f: f.short)
def test_vmap_takes_the_calls_backend(fam, monkeypatch) -> None:
    """Under ``torch.func.vmap`` (the families' registered ops, or for mean value coordinates the
    autograd Function's op) a call's ``backend="torch"`` reaches the kernel choice without a string
    in any schema: the native loader is never reached (mean value coordinates: the Function's op
    computes the values with the torch kernel; its derivatives stay analytic where they can)."""
    cage, fn = _cage(fam), fam.function()
    X = torch.stack([_points(), 0.5 * _points()])
    if not _maps(fam):
        pytest.skip(OLD_VMAP if fam.short != "mvc" else "no native kernel: the torch kernel branches on the data")
    if fam.short == "mvc":
        from torchcage.families.mean_value import ops

        seen, flat = [], ops.coordinates_flat
        monkeypatch.setattr(ops, "coordinates_flat", lambda *a: seen.append(a[-1]) or flat(*a))
    else:
        monkeypatch.setattr(torchcage.backends.native, "library", lambda: (_ for _ in ()).throw(AssertionError()))
    out = torch.func.vmap(lambda y: _call(fn, y, cage, "torch"))(X)
    monkeypatch.undo()
    assert fam.short != "mvc" or seen == ["torch"]
    for b in range(2):
        for a, r in zip(out, _call(fn, X[b], cage, "torch"), strict=True):
            torch.testing.assert_close(a[b], r, rtol=0, atol=1e-14)


@pytest.mark.filterwarnings("ignore:Dynamo does not know how to trace")
@pytest.mark.parametrize("fam", CLOSED, ids=lambda f: f.short)
def test_compiled_calls_take_the_backend_in_force_when_they_run(fam, monkeypatch, fresh_dynamo) -> None:
    """A compiled call's op reads the backend in force when the graph runs, not when it was traced:
    compiled (and run once) outside any block, then run inside ``use("torch")``, it never reaches
    the native loader, and gives the torch kernel's numbers; a ``backend=`` inside the compiled
    function is refused with that advice."""
    cage, fn, x = _cage(fam), fam.function(), _points()
    compiled = torch.compile(lambda y: _tuple(fn(y, cage)), fullgraph=True, backend="eager")
    compiled(x)
    with monkeypatch.context() as m:
        m.setattr(torchcage.backends.native, "library", lambda: (_ for _ in ()).throw(AssertionError("native")))
        with torchcage.backends.use("torch"):
            out = compiled(x)
        with pytest.raises(AssertionError, match="native"):
            compiled(x)
    for a, b in zip(out, _call(fn, x, cage, "torch"), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    named = torch.compile(lambda y: _tuple(fn(y, cage, backend="torch")), fullgraph=True, backend="eager")
    with pytest.raises(Exception, match=REFUSED):
        named(x)


def _refuse_native(m: pytest.MonkeyPatch) -> None:
    m.setattr(torchcage.backends.native, "library", lambda: (_ for _ in ()).throw(AssertionError("native")))


def _spy(m: pytest.MonkeyPatch, fam) -> list[str]:
    """Refuse the native kernel (``AssertionError``); for mean value coordinates, whose analytic
    point derivatives take the native kernel whatever the values' backend, record instead the
    backend its values' op computes with."""
    seen: list[str] = []
    if fam.short != "mvc":
        _refuse_native(m)
        return seen
    from torchcage.families.mean_value import ops

    flat = ops.coordinates_flat
    m.setattr(ops, "coordinates_flat", lambda *a: seen.append(a[-1]) or flat(*a))
    return seen


@pytest.mark.filterwarnings("ignore:Dynamo does not know how to trace")
@pytest.mark.parametrize("fam", CLOSED, ids=lambda f: f.short)
def test_the_backward_pass_keeps_the_forwards_backend(fam, monkeypatch, fresh_dynamo) -> None:
    """The backward pass of a compiled call (and of a mapped one) runs with the backend its forward
    ran with: forward inside ``use("torch")`` (or with ``backend="torch"`` under vmap), backward
    after the block, never the native kernel (:func:`_spy`); the gradients equal eager's with the
    torch kernel."""
    cage, fn = _cage(fam), fam.function()
    x0 = _points()

    def loss(y: torch.Tensor) -> torch.Tensor:
        return sum((o * o).sum() for o in _tuple(fn(y, cage)))

    compiled = torch.compile(loss, fullgraph=True, backend="aot_eager")
    compiled(x0.clone().requires_grad_())  # (compiled outside any block)
    x = x0.clone().requires_grad_()
    X = torch.stack([x0, 0.5 * x0]).requires_grad_()
    mapped = torch.func.vmap(lambda y: torch.cat([o.flatten() for o in _tuple(fn(y, cage, backend="torch"))]))
    with monkeypatch.context() as m:
        seen = _spy(m, fam)
        with torchcage.backends.use("torch"):
            value = compiled(x)
        (g,) = torch.autograd.grad(value, x)  # (after the block)
        checks = [(x0, g)]
        if _maps(fam):
            (gm,) = torch.autograd.grad((mapped(X) ** 2).sum(), X)
            checks += [(x0, gm[0]), (0.5 * x0, gm[1])]
    assert fam.short != "mvc" or (seen and set(seen) == {"torch"}), seen
    for y, got in checks:
        ye = y.clone().requires_grad_()
        with torchcage.backends.use("torch"):
            (want,) = torch.autograd.grad(loss(ye), ye)
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("fam", CLOSED, ids=lambda f: f.short)
def test_unknown_values_with_a_graph_get_the_familys_text(fam) -> None:
    """With an autograd graph (and under vmap) an unknown ``backend=`` gets the same text as
    without: naming the family's operation."""
    cage, fn = _cage(fam), fam.function()
    x = _points().requires_grad_()
    with pytest.raises(ValueError, match=r"backend must be one of 'auto', .* for .*, got 'cuda'$"):
        fn(x, cage, backend="cuda")
    if _maps(fam):
        with pytest.raises(ValueError, match=r"backend must be one of 'auto', .* for .*, got 'cuda'$"):
            torch.func.vmap(lambda y: _tuple(fn(y, cage, backend="cuda"))[0])(x.detach()[None])


def test_green_derivatives_take_the_block_as_their_backend() -> None:
    """Inside ``use(b)`` Green derivatives behave as with ``backend=b``: the block is the
    derivatives' backend, not that of the values they compute first."""
    square = torchcage.Cage(
        torch.tensor([[0.0, 0], [1, 0], [1, 1], [0, 1]], dtype=D64), torch.tensor([[0, 1], [1, 2], [2, 3], [3, 0]])
    )
    x = torch.tensor([[0.3, 0.4]], dtype=D64)
    with pytest.raises(ValueError) as said:
        F.green_derivatives(x, square, backend="native")
    with torchcage.backends.use("native"), pytest.raises(ValueError) as block:
        F.green_derivatives(x, square)
    assert str(block.value).startswith(str(said.value))


@pytest.mark.filterwarnings("ignore:Dynamo does not know how to trace")
def test_compiled_code_outside_the_ops_follows_the_block(monkeypatch, fresh_dynamo) -> None:
    """Compiled code that chooses its kernel while traced (the derivatives: no registered op) is
    compiled again under another backend in force (its read is guarded)."""
    from packaging.version import Version

    if Version(torch.__version__).release < (2, 6):
        pytest.skip("torch 2.5's Dynamo cannot trace mean_value_derivatives (it iterates a Proxy)")
    cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
    x = _points()
    f = torch.compile(lambda y: F.mean_value_derivatives(y, cube, 1)[1], backend="eager")
    f(x)
    with monkeypatch.context() as m:
        _refuse_native(m)
        with torchcage.backends.use("torch"):
            got = f(x)
    torch.testing.assert_close(got, F.mean_value_derivatives(x, cube, 1, backend="torch")[1], rtol=0, atol=0)


@pytest.mark.filterwarnings("ignore:Dynamo does not know how to trace")
def test_use_inside_a_compiled_function_is_refused(fresh_dynamo) -> None:
    cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
    x = _points()

    def inner(y: torch.Tensor) -> torch.Tensor:
        with torchcage.backends.use("torch"):
            return F.mean_value_coordinates(y, cube)

    with pytest.raises(Exception, match=r"inside a compiled function|skip function use"):
        torch.compile(inner, fullgraph=True, backend="eager")(x)
