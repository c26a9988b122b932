"""The contract every coordinate family keeps, one parametrised suite over the registry.

Each test runs for every family of :data:`torchcage.families.FAMILIES` (and each of its dims) on a
small cage of its kind: in 3D the packaged cube, triangulated for the ``"triangles"`` families and
kept with its quads for the ``"triquads"`` ones; in 2D a small pentagon; a handful of fixed points
inside (``support.contract_points``). The solved families (lbc, hc, bbw) solve once per cage on a
coarse mesh and reuse the solve (``solution=``).

Where a family does not keep an item today, its case is marked ``xfail(strict=True)`` with the
reason found (the first error, the first graph break), so that the table names why not and the
test fails the day the family starts to keep it (then drop the mark). A new family in the
registry is tested by every item at once.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import pytest
import torch
from support import CONTRACT_CELLS, contract_cage, contract_points, contract_solution, dense_outputs

import torchcage
from torchcage._core.compiled import _vmap_records_autograd
from torchcage.errors import PointsError
from torchcage.families import FAMILIES, Family, family

Unsupported = torch._dynamo.exc.Unsupported

# ------------------------------------------------------------------------------------ what we know
#: Functional entries that take a batch of cages ``(B, V, D)`` with one topology (the others refuse it
#: with a CageError naming the closed-form families; see ``test_batched_cage_equals_the_loop``).
BATCHED = {"mvc", "gc", "qmvc", "qgc"}
#: Families whose coordinates reproduce linear functions (``w @ V = x``; Green: with the normal
#: terms). Bounded biharmonic weights do not (their registry help says so).
LINEAR_PRECISION = {"mvc", "gc", "qmvc", "qgc", "lbc", "hc", "mec"}
#: Closed-form families whose functional is differentiable with respect to the points and the cage's
#: vertices (their docstrings' "Gradients" paragraphs; gc: the torch kernel, autograd throughout).
DIFFERENTIABLE = {"mvc", "gc", "qmvc", "qgc"}
#: The result dtype for float32 points and a float64 cage, as each family documents it: the solved
#: families give "the points' dtype"; the others "that of the inputs" (promoted).
POINTS_DTYPE_RESULT = {"lbc", "hc", "bbw"}

FIRST_GRAPH_BREAK = (
    "first graph break (the closed-form families compile: one opaque custom op each, _core/compiled.py; "
    "the solved ones and mec have none yet): torchcage/_core/common.py as_inputs calls "
    "torch._C._functorch.is_functorch_wrapped_tensor(cage.vertices), which Dynamo cannot trace, before "
    "torch.compiler.is_compiling() could short-circuit it; the next one is check_finite's data-dependent "
    "`if bool(bad.any())`"
)
#: The families whose functional entry runs as its registered op under vmap (its vmap rule).
VMAP_OP = ("gc", "qmvc", "qgc")
#: Why they do not map on a torch whose custom ops record no autograd through a vmap rule (2.5).
VMAP_OLD_TORCH = "this torch records no autograd through a custom op's vmap rule (2.5): the eager path runs"
VMAP_LOCATE = (
    "vmap: refused with a NotImplementedError naming what works (the point location reads the points' "
    "values: torchcage/solvers/locate.py)"
)


class NoRegisteredOpError(AssertionError):
    """The family's functional entry has no ``torch.ops.torchcage`` custom op yet."""


# ----------------------------------------------------------------------------------------- cases
@dataclass
class Case:
    """One family on its contract cage: the functional call and the module, with the options that
    keep it fast (a reused solve for the solved families)."""

    fam: Family
    dim: int
    cage: torchcage.Cage
    points: torch.Tensor
    options: dict[str, Any] = field(default_factory=dict)

    @property
    def short(self) -> str:
        return self.fam.short

    def call(
        self, points: torch.Tensor | None = None, cage: torchcage.Cage | None = None, **kw: Any
    ) -> tuple[torch.Tensor, ...]:
        """The functional entry's outputs as a tuple of dense tensors."""
        x = self.points if points is None else points
        return dense_outputs(self.fam.function()(x, self.cage if cage is None else cage, **self.options, **kw))

    def module(self, points: torch.Tensor | None = None, **kw: Any) -> torch.nn.Module:
        """The family's module on this case's cage, embedding ``points`` (default: the case's)."""
        return self.fam.module()(self.cage, self.points if points is None else points, **self.options, **kw)

    def rebuilt(self, vertices: torch.Tensor) -> torchcage.Cage:
        """A cage of this case's topology around ``vertices`` ``(*B, V, D)``, by the constructor."""
        return torchcage.Cage(vertices, self.cage.faces if self.dim == 3 else self.cage.edges)

    def inner_points(self, scale: float) -> torch.Tensor:
        """The case's points moved toward an interior centre by ``scale`` (still inside)."""
        centre = self.points.new_tensor([1.0, 0.7] if self.dim == 2 else [0.0, 0.0, 0.0])
        return centre + scale * (self.points - centre)


_CASES: dict[tuple[str, int], Case] = {}


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """One torch thread for this file, as the default tier's xdist workers have on two cores
    (conftest.py): the cases are a few points, where a thread pool on a busy machine costs 3-4x the
    work (measured here: 31 s with two threads, 8.5 s with one, under ``-n 0``)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def get_case(key: tuple[str, int]) -> Case:
    """The case of family ``key[0]`` in ``key[1]`` dimensions (built once per session)."""
    if key not in _CASES:
        fam = family(key[0])
        if fam.extra is not None:
            pytest.importorskip("scipy", reason=f"{fam.short} needs the '{fam.extra}' extra (scipy)")
        cage = contract_cage(fam.faces, key[1])
        options: dict[str, Any] = {}
        if fam.solved:
            sol = contract_solution(fam.short, cage)
            options = {"solution": sol} if sol is not None else {"target_cells": CONTRACT_CELLS}
        _CASES[key] = Case(fam, key[1], cage, contract_points(key[1]), options)
    return _CASES[key]


def cases(
    where: Callable[[Family], bool] | None = None,
    xfail: dict[str, str] | None = None,
    raises: type[BaseException] | tuple[type[BaseException], ...] | None = None,
) -> list:
    """Parameters ``(short, dim)`` of every family (those for which ``where(family)`` holds), with
    ``xfail(strict=True)`` on the cases named in ``xfail`` (by ``"short"`` or ``"short-2d"``)."""
    params = []
    for fam in FAMILIES:
        if where is not None and not where(fam):
            continue
        for dim in fam.dims:
            name = f"{fam.short}-{dim}d"
            reason = (xfail or {}).get(name) or (xfail or {}).get(fam.short)
            marks = [pytest.mark.xfail(strict=True, reason=reason, raises=raises)] if reason else []
            params.append(pytest.param((fam.short, dim), id=name, marks=marks))
    return params


ALL = cases()


def close(actual: torch.Tensor, expected: torch.Tensor, atol: float, what: str = "") -> None:
    """``|actual - expected| <= atol`` everywhere (``expected`` cast to ``actual``'s dtype)."""
    torch.testing.assert_close(actual, expected.to(actual.dtype), rtol=0, atol=atol, msg=lambda m: f"{what}: {m}")


def expected_widths(case: Case) -> tuple[int, ...]:
    """The widths of the outputs: ``V`` per weight row; Green's ``psi`` one per face: triangles (3D),
    edges (2D), and four per quad (quad Green)."""
    V = case.cage.num_vertices
    if case.fam.outputs == ("weights",):
        return (V,)
    faces = case.cage.triangles.shape[0] if case.dim == 3 else case.cage.edges.shape[0]
    if case.fam.faces == "triquads":
        faces += 4 * case.cage.quads.shape[0]
    return (V, faces)


def normals(case: Case) -> torch.Tensor:
    """The normal terms' vectors of Green's linear precision, one row per ``psi`` column."""
    if case.dim == 2:
        return case.cage.edge_normals()
    parts = [case.cage.triangle_normals()[: case.cage.triangles.shape[0]]]  # (the cage's own triangles first)
    if case.fam.faces == "triquads":
        parts.append(case.cage.quad_corner_normals().reshape(-1, 3))
    return torch.cat(parts)


# ------------------------------------------------------------------------------------- shapes
@pytest.mark.parametrize("key", ALL)
def test_output_shapes(key) -> None:
    """Points ``(N, D)`` give one output per name in the registry's ``outputs``: weights ``(N, V)``;
    Green's ``phi (N, V)`` and ``psi (N, faces)`` (triangles, edges, or ``T + 4 Q`` for quad Green)."""
    case = get_case(key)
    outs = case.call()
    assert len(outs) == len(case.fam.outputs)
    N = case.points.shape[0]
    assert [tuple(o.shape) for o in outs] == [(N, w) for w in expected_widths(case)]


@pytest.mark.parametrize("key", ALL)
def test_leading_point_dims(key) -> None:
    """Points ``(2, 3, N, D)`` (a different permutation of the points in each ``[i, j]``) give
    ``(2, 3, N, ...)``, each ``[i, j]`` the rows of the call on ``(N, D)`` in that permutation;
    lbc, whose result is a sparse ``(N, V)`` matrix, refuses them with a PointsError."""
    case = get_case(key)
    x = case.points
    X = torch.stack([x.roll(k, 0) for k in range(6)]).reshape(2, 3, *x.shape)
    if case.short == "lbc":
        with pytest.raises(PointsError, match="sparse"):
            case.call(X)
        return
    outs = case.call(X)
    for o, r in zip(outs, case.call(), strict=True):
        assert o.shape == (2, 3, *r.shape)
        for k in range(6):  # (each row depends on its own point only)
            close(o[k // 3, k % 3], r.roll(k, 0), 1e-12, f"[{k // 3}, {k % 3}]")


# ------------------------------------------------------------------------------------- dtypes
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["float32", "float64"])
@pytest.mark.parametrize("key", ALL)
def test_dtype_follows_the_inputs(key, dtype) -> None:
    """Points and cage in ``dtype`` give outputs in ``dtype`` (nothing hard-coded to one precision),
    equal to the float64 outputs to float32's accuracy (DESIGN.md: 1e-4)."""
    case = get_case(key)
    ref = case.call()
    outs = case.call(case.points.to(dtype), case.cage.to(dtype))
    for o, r in zip(outs, ref, strict=True):
        assert o.dtype == dtype
        close(o, r, 1e-4)


@pytest.mark.parametrize("key", ALL)
def test_mixed_dtypes_give_the_documented_dtype(key) -> None:
    """float32 points with a float64 cage: the closed-form families and mec give the promoted dtype
    ("that of the inputs"), the solved families "the points' dtype" (their docstrings)."""
    case = get_case(key)
    want = torch.float32 if case.short in POINTS_DTYPE_RESULT else torch.float64
    for o in case.call(case.points.float()):
        assert o.dtype == want


@pytest.mark.parametrize("key", ALL)
def test_dtype_option(key) -> None:
    """Where the entry has ``dtype=``: float64 inputs with ``dtype=torch.float32`` give float32 (the
    float64 values rounded), float32 inputs with ``dtype=torch.float64`` give float64. Where it has
    none, ``dtype=`` is refused (TypeError) rather than ignored."""
    case = get_case(key)
    if "dtype" not in inspect.signature(case.fam.function()).parameters:
        with pytest.raises(TypeError):
            case.call(dtype=torch.float32)
        return
    ref = case.call()
    for o, r in zip(case.call(dtype=torch.float32), ref, strict=True):
        assert o.dtype == torch.float32
        close(o, r, 1e-6)
    for o, r in zip(case.call(case.points.float(), case.cage.to(torch.float32), dtype=torch.float64), ref, strict=True):
        assert o.dtype == torch.float64
        close(o, r, 1e-5)


# ------------------------------------------------------------------------------------ devices
DEVICES = [
    "cpu",
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")),
]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("key", ALL)
def test_device_follows_the_inputs(key, device) -> None:
    """Points and cage on ``device`` give outputs on ``device`` equal to the CPU's (to 1e-9: the
    kernels differ between devices, the formulas do not)."""
    case = get_case(key)
    ref = case.call()
    outs = case.call(case.points.to(device), case.cage.to(device))
    for o, r in zip(outs, ref, strict=True):
        assert o.device.type == device
        close(o.cpu(), r, 1e-9)


# ----------------------------------------------------------------------------- memory layouts
@pytest.mark.parametrize("key", ALL)
def test_non_contiguous_inputs(key) -> None:
    """A transposed view and a strided view of the points, and a cage built from a transposed view of
    its vertices, give the results of the contiguous ones."""
    case = get_case(key)
    x = case.points
    ref = case.call()
    transposed = x.t().contiguous().t()
    wide = torch.zeros(x.shape[0], 2 * x.shape[1], dtype=x.dtype)
    wide[:, ::2] = x
    strided = wide[:, ::2]
    assert not transposed.is_contiguous() and not strided.is_contiguous()
    cage = case.rebuilt(case.cage.vertices.t().contiguous().t())
    for label, outs in (
        ("transposed", case.call(transposed)),
        ("strided", case.call(strided)),
        ("cage view", case.call(cage=cage)),
    ):
        for o, r in zip(outs, ref, strict=True):
            close(o, r, 1e-14, label)


# ------------------------------------------------------------------------------------- batching
def _poses(case: Case, B: int = 3) -> torch.Tensor:
    """``B`` valid poses of the case's cage: rest, scaled and moved, slightly jittered."""
    V = case.cage.vertices
    g = torch.Generator().manual_seed(7)
    jitter = 0.03 * case.cage.scale * (torch.rand(V.shape, generator=g, dtype=V.dtype) * 2 - 1)
    return torch.stack([V, 1.2 * V + 0.1, V + jitter][:B])


@pytest.mark.parametrize("key", ALL)
def test_batched_cage_equals_the_loop(key) -> None:
    """Closed-form families: a batch of cages ``(B, V, D)`` with one topology
    (``Cage(vertices_batched, faces)``), with shared points ``(N, D)`` and with one point set per cage
    ``(B, N, D)``, equals the calls on each element. The others refuse a batch with a ValueError
    (CageError) that says to call per element, rather than answering for one element."""
    case = get_case(key)
    poses = _poses(case)
    batch = case.rebuilt(poses)
    X = torch.stack([case.inner_points(s) for s in (1.0, 0.9, 0.8)])
    if case.short not in BATCHED:
        with pytest.raises(ValueError, match="per element"):
            case.call(cage=batch)
        return
    shared, each = case.call(cage=batch), case.call(X, batch)
    for b in range(poses.shape[0]):
        one = case.rebuilt(poses[b])
        for o, r in zip(shared, case.call(cage=one), strict=True):
            close(o[b], r, 1e-12, f"shared points, cage {b}")
        for o, r in zip(each, case.call(X[b], one), strict=True):
            close(o[b], r, 1e-12, f"points per cage, cage {b}")


# ---------------------------------------------------------------------------------------- module
@pytest.mark.parametrize("key", ALL)
def test_module_state_dict_round_trip(key) -> None:
    """A module built on other points takes the ``state_dict`` of another (``load_state_dict``) and
    then deforms exactly as the original: the buffers are the whole state."""
    case = get_case(key)
    m = case.module()
    fresh = case.module(points=case.inner_points(0.9))
    pose = _poses(case)[1]
    assert not torch.equal(fresh(pose), m(pose))
    fresh.load_state_dict(m.state_dict())
    assert torch.equal(fresh(pose), m(pose))
    for name, buf in m.state_dict().items():
        assert torch.equal(fresh.state_dict()[name], buf), name


@pytest.mark.parametrize("key", ALL)
def test_module_to_dtype_and_device(key) -> None:
    """``.to(torch.float32)`` gives a module whose forward on float32 vertices is float32 and equal
    to the float64 one to 1e-5 of the cage's size; ``.to("cpu")`` keeps it as it is."""
    case = get_case(key)
    m = case.module()
    pose = _poses(case)[2]
    ref = m(pose)
    assert m.to("cpu") is m and torch.equal(m(pose), ref)
    out = m.to(torch.float32)(pose.float())
    assert out.dtype == torch.float32
    close(out, ref, 1e-5 * case.cage.scale)


@pytest.mark.parametrize("key", ALL)
def test_module_batched_poses(key) -> None:
    """Deformed vertices ``(K, V, D)`` give ``(K, N, D)`` and ``(2, K, V, D)`` give ``(2, K, N, D)``,
    each pose's points equal to the forward of that pose alone."""
    case = get_case(key)
    m = case.module()
    poses = _poses(case)
    out = m(poses)
    N, D = case.points.shape
    assert out.shape == (poses.shape[0], N, D)
    for k in range(poses.shape[0]):
        close(out[k], m(poses[k]), 1e-13, f"pose {k}")
    twice = m(torch.stack([poses, poses.flip(0)]))
    assert twice.shape == (2, poses.shape[0], N, D)
    close(twice[1], out.flip(0), 1e-13)


@pytest.mark.parametrize("key", ALL)
def test_module_reproduces_the_rest_pose_and_translations(key) -> None:
    """``forward(rest vertices)`` gives the points back to 1e-10 and a translated cage translates
    them (bounded biharmonic weights too: their module deforms by the vertices' displacements)."""
    case = get_case(key)
    m = case.module()
    V = case.cage.vertices
    close(m(V), case.points, 1e-10, "rest pose")
    t = V.new_tensor([0.3, -0.2, 0.5][: case.dim])
    close(m(V + t), case.points + t, 1e-10, "translation")


# ------------------------------------------------------------------------------------ properties
@pytest.mark.parametrize("key", ALL)
def test_partition_of_unity(key) -> None:
    """The weights (Green: ``phi``) of points inside the cage sum to one."""
    case = get_case(key)
    w = case.call()[0]
    close(w.sum(-1), torch.ones(w.shape[0], dtype=w.dtype), 1e-10)


@pytest.mark.parametrize("key", ALL)
def test_linear_precision(key) -> None:
    """``w @ V = x`` (Green: ``phi @ V + psi @ normals = x``, quad Green's corner normals
    unnormalised) to 1e-10 of the cage's size; bounded biharmonic weights, which do not promise it,
    are at least 1e-3 off (the reason their module deforms by displacements)."""
    case = get_case(key)
    outs = case.call()
    y = outs[0] @ case.cage.vertices
    if len(outs) == 2:
        y = y + outs[1] @ normals(case)
    err = float((y - case.points).abs().max())
    if case.short in LINEAR_PRECISION:
        assert err <= 1e-10 * case.cage.scale
    else:
        assert err >= 1e-3 * case.cage.scale


# -------------------------------------------------------------------------------------- gradients
@pytest.mark.parametrize("key", ALL)
def test_gradcheck_points(key) -> None:
    """float64 gradcheck (fast mode) of the functional with respect to two points, where the family
    says it is differentiable (closed form; hc and bbw: piecewise linear on the solve's mesh, so at
    points inside its cells); mec and lbc refuse points that require grad with a PointsError."""
    case = get_case(key)
    x = case.points[:2].clone().requires_grad_()
    if case.short in ("mec", "lbc"):
        with pytest.raises(PointsError, match="not differentiable"):
            case.call(x)
        return
    assert torch.autograd.gradcheck(lambda y: case.call(y), (x,), fast_mode=True)


@pytest.mark.parametrize("key", ALL)
def test_gradcheck_vertices(key) -> None:
    """float64 gradcheck (fast mode) of the closed-form functionals with respect to the cage's
    vertices; mec refuses a cage that requires grad with a PointsError."""
    case = get_case(key)
    if case.fam.solved:
        pytest.skip(f"{case.short}: the weights are a constant of the rest cage's solve (no cage derivative)")
    V = case.cage.vertices.clone().requires_grad_()
    if case.short == "mec":
        with pytest.raises(PointsError, match="not differentiable"):
            case.call(case.points[:2], case.cage.with_vertices(V))
        return
    assert case.short in DIFFERENTIABLE
    assert torch.autograd.gradcheck(
        lambda v: case.call(case.points[:2], case.cage.with_vertices(v)), (V,), fast_mode=True
    )


@pytest.mark.parametrize("key", ALL)
def test_forward_mode_points(key) -> None:
    """Forward-mode derivatives (``torch.autograd.forward_ad``) along a tangent of the points agree
    with central differences of the functional wherever reverse mode works: a tangent is never
    dropped (the kernels without a graph must not take dual points); mec and lbc refuse dual points
    as they refuse points that require grad."""
    import torch.autograd.forward_ad as fwAD

    case = get_case(key)
    x = case.points[:2].clone()
    t = torch.randn(x.shape, generator=torch.Generator().manual_seed(3), dtype=x.dtype)
    with fwAD.dual_level():
        dual = fwAD.make_dual(x, t)
        if case.short in ("mec", "lbc"):
            with pytest.raises(PointsError, match="not differentiable"):
                case.call(dual)
            return
        tangents = [fwAD.unpack_dual(o).tangent for o in case.call(dual)]
    h = 1e-6
    for tan, plus, minus in zip(tangents, case.call(x + h * t), case.call(x - h * t), strict=True):
        assert tan is not None
        fd = (plus - minus) / (2 * h)
        assert float((tan - fd).abs().max()) <= 1e-6 * max(1.0, float(fd.abs().max()))


@pytest.mark.slow
@pytest.mark.parametrize("key", cases(lambda f: f.short in DIFFERENTIABLE))
def test_gradcheck_full(key) -> None:
    """Full (not fast-mode) gradcheck of the closed-form functionals, points and vertices at once."""
    case = get_case(key)
    x = case.points[:2].clone().requires_grad_()
    V = case.cage.vertices.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda y, v: case.call(y, case.cage.with_vertices(v)), (x, V))


# ------------------------------------------------------------------------------ custom ops, compile
def _op_arguments(case: Case) -> tuple:
    """The arguments of a family's registered op (``torchcage._core.compiled.CompiledOp``)."""
    c = case.cage
    n, tol = case.options.get("n", 0), case.options.get("tol", -1.0)
    return (case.points, c.vertices, c.triangles, c.quads, c.edges, 0, n, tol)


@pytest.mark.parametrize(
    "key",
    cases(xfail={f.short: "no registered op yet" for f in FAMILIES if f.op is None}, raises=NoRegisteredOpError),
)
def test_opcheck(key) -> None:
    """The family's custom op ``torch.ops.torchcage.<family.op>`` passes ``torch.library.opcheck``
    (schema, fake tensor, autograd registration, AOT dispatch) and equals the functional entry."""
    case = get_case(key)
    if case.fam.op is None:
        raise NoRegisteredOpError(f"{case.short}: the registry names no op")
    op = getattr(torch.ops.torchcage, case.fam.op)
    args = _op_arguments(case)
    torch.library.opcheck(op.default, args)
    *outs, code = op(*args)  # (code: the backend the op ran with, for its backward op)
    assert code.dtype == torch.int8 and torchcage.backends.BACKENDS[int(code)] == "auto"
    for o, r in zip(outs, case.call(), strict=True):
        close(o, r, 1e-14)


@pytest.fixture
def fresh_dynamo():
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()


@pytest.mark.filterwarnings("ignore:Dynamo does not know how to trace")
@pytest.mark.parametrize(
    "key",
    cases(xfail={f.short: FIRST_GRAPH_BREAK for f in FAMILIES if f.short not in DIFFERENTIABLE}, raises=Unsupported),
)
def test_compile_functional(key, fresh_dynamo) -> None:
    """``torch.compile(fullgraph=True)`` of the functional call (backend "eager") gives the eager
    outputs; for the closed-form families (one opaque custom op each under compilation) the
    gradients with respect to the points and the cage's vertices too (backend "aot_eager")."""
    case = get_case(key)
    fn, opts = case.fam.function(), case.options  # (the registry's import is resolved outside)
    compiled = torch.compile(lambda y: dense_outputs(fn(y, case.cage, **opts)), fullgraph=True, backend="eager")
    for o, r in zip(compiled(case.points), case.call(), strict=True):
        close(o, r, 1e-14)
    if case.short not in DIFFERENTIABLE:
        return

    faces = case.cage.faces if case.dim == 3 else case.cage.edges

    def f(y, P):  # (the constructor, not with_vertices: torch 2.5's dynamo cannot trace cls.__new__)
        return torch.cat(dense_outputs(fn(y, torchcage.Cage(P, faces, validate=False), **opts)), dim=-1)

    compiled_f = torch.compile(f, fullgraph=True, backend="aot_eager")
    for wrt in ("both", "points", "vertices"):  # (the compiled backward differentiates what is needed only)
        x = case.points.clone().requires_grad_(wrt != "vertices")
        P = case.cage.vertices.clone().requires_grad_(wrt != "points")
        inputs = [t for t in (x, P) if t.requires_grad]
        out = compiled_f(x, P)
        g = torch.randn(out.shape, generator=torch.Generator().manual_seed(3), dtype=out.dtype)
        got = torch.autograd.grad(out, inputs, g)
        want = torch.autograd.grad(f(x, P), inputs, g)
        for a, b in zip(got, want, strict=True):
            close(a, b, 1e-12, wrt)


@pytest.mark.parametrize(
    "key",
    cases(
        xfail={
            "lbc": "LocalBarycentricCoordinates.forward enters warnings.catch_warnings() (to silence the sparse CSR "
            "beta warning), which Dynamo cannot trace (_warnings._filters_mutated)"
        },
        raises=Unsupported,
    ),
)
def test_compile_module(key, fresh_dynamo) -> None:
    """``torch.compile(module, fullgraph=True)`` (backend "aot_eager") of the forward on batched poses
    gives the eager result."""
    case = get_case(key)
    m = case.module()
    poses = _poses(case)
    compiled = torch.compile(m, fullgraph=True, backend="aot_eager")
    close(compiled(poses), m(poses), 1e-14)


# ---------------------------------------------------------------------------------------- torch.func
@pytest.mark.filterwarnings("ignore:There is a performance drop")
@pytest.mark.parametrize(
    "key",
    cases(
        xfail={
            "lbc": "vmap: refused with a PointsError (a transform records a graph, and the sparse, thresholded "
            "weights are not differentiable)",
            "hc": VMAP_LOCATE,
            "bbw": VMAP_LOCATE,
            "mec": "vmap: .item() on a vmapped tensor: the on-cage tolerance reads the points' extent "
            "(maximum_entropy.py: float(x.abs().max()))",
        },
        raises=(RuntimeError, PointsError),
    ),
)
def test_vmap_over_point_sets(key) -> None:
    """``torch.func.vmap`` of the functional over a batch of point sets ``(B, N, D)`` equals the call
    on each set (mvc: through its custom op's vmap rule, where the native kernel serves)."""
    case = get_case(key)
    if case.short == "mvc" and not torchcage.backends.native.available():
        pytest.xfail(
            "vmap without the native kernel: the torch kernel branches on the data (kernel3d/kernel2d: "
            "bool(on_cage.any()))"
        )
    if case.short in VMAP_OP and not _vmap_records_autograd():
        pytest.xfail(VMAP_OLD_TORCH)
    X = torch.stack([case.inner_points(s) for s in (1.0, 0.9, 0.8)])
    outs = torch.func.vmap(lambda y: case.fam.function()(y, case.cage, **case.options))(X)
    outs = outs if isinstance(outs, tuple) else (outs,)
    for b in range(X.shape[0]):
        for o, r in zip(outs, case.call(X[b]), strict=True):
            close(o[b], r, 1e-12, f"set {b}")


@pytest.mark.parametrize("key", cases(lambda f: f.short in ("hc", "bbw")))
def test_meshed_families_refuse_torch_func_transforms(key) -> None:
    """Harmonic and bounded biharmonic coordinates locate the points in a meshed interior, which
    reads their values: every ``torch.func`` transform raises an error naming what works instead
    (it was an internal "Cannot access data pointer" or ``.item()`` error), and forward mode through
    ``torch.autograd.forward_ad`` (which works) agrees with central differences."""
    case = get_case(key)
    f = case.fam.function()
    x = case.inner_points(0.9)
    transforms = {
        "vmap": lambda: torch.func.vmap(lambda y: f(y, case.cage, **case.options))(x[None]),
        "jvp": lambda: torch.func.jvp(lambda y: f(y, case.cage, **case.options), (x,), (torch.ones_like(x),)),
        "jacrev": lambda: torch.func.jacrev(lambda y: f(y, case.cage, **case.options))(x),
    }
    for run in transforms.values():
        with pytest.raises(NotImplementedError, match=r"torch\.func transforms"):
            run()
    import torch.autograd.forward_ad as fwAD

    t = torch.zeros_like(x)
    t[:, 0] = 1.0
    with fwAD.dual_level():
        tangent = fwAD.unpack_dual(f(fwAD.make_dual(x, t), case.cage, **case.options)).tangent
    h = 1e-6
    fd = (f(x + h * t, case.cage, **case.options) - f(x - h * t, case.cage, **case.options)) / (2 * h)
    close(tangent, fd, 1e-6, "forward mode")


@pytest.mark.parametrize("key", cases(lambda f: f.short in VMAP_OP))
def test_vmap_over_cages(key) -> None:
    """``torch.func.vmap`` over the cage's vertices (several poses of one topology), the points shared
    or mapped too, equals the call on each pose; gradients through the mapped call equal those of
    the loop."""
    if not _vmap_records_autograd():
        pytest.skip(VMAP_OLD_TORCH)
    case = get_case(key)
    f = case.fam.function()
    poses = _poses(case)
    X = torch.stack([case.inner_points(s) for s in (1.0, 0.9, 0.8)][: poses.shape[0]])

    def mapped(y: torch.Tensor, v: torch.Tensor) -> Any:
        return f(y, case.cage.with_vertices(v), **case.options)

    for shared in (True, False):  # one point set for every pose, or one per pose
        outs = torch.func.vmap(mapped, in_dims=(None if shared else 0, 0))(case.points if shared else X, poses)
        outs = outs if isinstance(outs, tuple) else (outs,)
        for b in range(poses.shape[0]):
            x = case.points if shared else X[b]
            for o, r in zip(outs, case.call(x, case.cage.with_vertices(poses[b])), strict=True):
                close(o[b], r, 1e-12, f"pose {b}")
    Xg, Pg = X.clone().requires_grad_(), poses.clone().requires_grad_()
    outs = torch.func.vmap(mapped)(Xg, Pg)
    outs = outs if isinstance(outs, tuple) else (outs,)
    sum((o**2).sum() for o in outs).backward()
    Xr, Pr = X.clone().requires_grad_(), poses.clone().requires_grad_()
    total = sum(
        sum((r**2).sum() for r in case.call(Xr[b], case.cage.with_vertices(Pr[b]))) for b in range(poses.shape[0])
    )
    total.backward()
    close(Xg.grad, Xr.grad, 1e-10, "d/dpoints")
    close(Pg.grad, Pr.grad, 1e-10, "d/dvertices")


@pytest.mark.parametrize("key", cases(lambda f: f.short == "mvc"))
def test_jacrev_points_mvc(key) -> None:
    """``torch.func.jacrev`` with respect to the points gives ``(N, V, N, D)``: zero across points,
    and each point's block equal to central differences of the coordinates (step 1e-6, to 1e-7)."""
    case = get_case(key)
    f = case.fam.function()
    x = case.points
    J = torch.func.jacrev(lambda y: f(y, case.cage))(x)
    N, D = x.shape
    V = case.cage.num_vertices
    assert J.shape == (N, V, N, D)
    eye = torch.eye(N, dtype=torch.bool)
    assert float(J.permute(0, 2, 1, 3)[~eye].abs().max()) == 0.0
    h = 1e-6
    for c in range(D):
        e = torch.zeros(D, dtype=x.dtype)
        e[c] = h
        fd = (f(x + e, case.cage) - f(x - e, case.cage)) / (2 * h)
        close(J[torch.arange(N), :, torch.arange(N), c], fd, 1e-7, f"d/dx_{c}")


def test_every_family_is_covered() -> None:
    """The suite's tables name only registered families, and every family has at least one case."""
    shorts = {f.short for f in FAMILIES}
    for table in (BATCHED, LINEAR_PRECISION, DIFFERENTIABLE, POINTS_DTYPE_RESULT):
        assert table <= shorts
    assert {p.values[0][0] for p in ALL} == shorts
