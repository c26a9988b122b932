"""The coordinate families: one record per family, the one place that names them.

The CLI, the editor, :func:`torchcage.deform`, image warping, the splat deformer, the benchmarks
and the contract tests read this registry; a new family adds its :class:`Family` here (and its
code, docs and tests) and nothing else. Each family has one short name (``mvc``, ``gc``, ...);
an old spelling is accepted as an alias with a :class:`DeprecationWarning`.

The registry imports nothing of torchcage at import time: :meth:`Family.function` and
:meth:`Family.module` import the family's code on first use.

Examples:
    >>> from torchcage.families import family, FAMILIES
    >>> [f.short for f in FAMILIES]
    ['mvc', 'gc', 'qmvc', 'qgc', 'lbc', 'hc', 'bbw', 'mec']
    >>> gc = family("gc")
    >>> gc.title, gc.dims, gc.outputs
    ('Green coordinates', (2, 3), ('phi', 'psi'))
    >>> gc.function().__name__
    'green_coordinates'
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Literal

__all__ = ["ALIASES", "FAMILIES", "Family", "family", "names"]

#: What a family's cages may hold: ``"triangles"`` (quads are split along q0-q2 when the family's
#: module is built by :func:`torchcage.methods.build_module`), ``"triquads"`` (quads kept).
FaceKind = Literal["triangles", "triquads"]


@dataclass(frozen=True)
class Family:
    """One coordinate family.

    Attributes:
        short: the one name used everywhere (CLI ``--method``, ``deform(method=)``, the editor).
        title: what a person reads (``"mean value coordinates"``).
        function_path: ``"module:name"`` of the public functional entry.
        module_path: ``"module:name"`` of the :class:`torch.nn.Module`.
        dims: the cage dimensions served.
        faces: ``"triangles"`` (quads split) or ``"triquads"`` (quads kept).
        outputs: the names of the functional entry's outputs: ``("weights",)`` or
            ``("phi", "psi")`` (Green's vertex and face coordinates).
        backends: the ``backend=`` values the functional entry accepts besides ``"auto"`` (empty:
            it takes no ``backend=``).
        tol: the functional entry and the module take ``tol=`` (error-controlled quadrature).
        solved: computed by a solve on a mesh of the cage's interior (slow, iterative or sparse).
        extra: the optional extra it needs (``pip install 'torchcage[<extra>]'``), or ``None``.
        deform: served by :func:`torchcage.deform`, which recomputes the coordinates under
            autograd on every call (the closed-form families); the others are computed once, by
            their module.
        jacobian: the module offers ``jacobian`` (the splat deformer's families).
        inside_only: defined inside the cage only (points outside are refused or meaningless).
        help: a one-line description for ``--help``.
        outside: what the family does with points outside the cage (ends the outside warning).
        op: the name of its registered op, ``torch.ops.torchcage.<op>`` (the functional entry as
            one opaque custom op, which ``torch.compile(fullgraph=True)`` calls:
            :mod:`torchcage._core.compiled`), or ``None``.
    """

    short: str
    title: str
    function_path: str
    module_path: str
    dims: tuple[int, ...]
    faces: FaceKind
    outputs: tuple[str, ...] = ("weights",)
    backends: tuple[str, ...] = ()
    tol: bool = False
    solved: bool = False
    extra: str | None = None
    deform: bool = True
    jacobian: bool = False
    inside_only: bool = False
    help: str = ""
    outside: str = ""
    op: str | None = None
    _cache: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @property
    def name(self) -> str:
        """``"mean value coordinates (mvc)"``: the title with the short name."""
        return f"{self.title} ({self.short})"

    def function(self) -> Callable[..., Any]:
        """The public functional entry (imported on first use)."""
        return self._load("function", self.function_path)

    def module(self) -> type:
        """The :class:`torch.nn.Module` class (imported on first use)."""
        return self._load("module", self.module_path)

    def _load(self, key: str, path: str) -> Any:
        if key not in self._cache:
            mod, _, attr = path.partition(":")
            self._cache[key] = getattr(importlib.import_module(mod), attr)
        return self._cache[key]


_NEEDS_MESH = "solved on a mesh of the cage interior"
_NEAREST_CELL = (
    "they take the coordinates of the nearest point of the meshed interior (they move with it, not with the cage); "
    "enlarge the cage around them"
)
FAMILIES: tuple[Family, ...] = (
    Family(
        "mvc",
        "mean value coordinates",
        "torchcage.families.mean_value.api:mean_value_coordinates",
        "torchcage.families.mean_value.module:MeanValueCoordinates",
        dims=(2, 3),
        faces="triangles",
        backends=("native", "torch", "triton"),
        jacobian=True,
        op="mvc",
        help="mean value, any closed cage, quads split",
        outside="mean value coordinates extrapolate there (defined, but the farther out a point lies the less it "
        "follows the cage); enlarge the cage around them",
    ),
    Family(
        "gc",
        "Green coordinates",
        "torchcage.families.green.api:green_coordinates",
        "torchcage.families.green.module:GreenCoordinates",
        dims=(2, 3),
        faces="triangles",
        outputs=("phi", "psi"),
        backends=("native", "torch", "triton"),
        jacobian=True,
        op="green",
        help="Green, quasi-conformal, quads split",
        outside="Green coordinates continue them through the nearest faces, exact at rest but extrapolating those "
        "faces' motion; enlarge the cage around them",
    ),
    Family(
        "qmvc",
        "quad mean value coordinates",
        "torchcage.families.quad_mean_value.api:quad_mean_value_coordinates",
        "torchcage.families.quad_mean_value.module:QuadMeanValueCoordinates",
        dims=(3,),
        faces="triquads",
        backends=("native", "torch", "triton"),
        tol=True,
        op="qmvc",
        help="quad mean value, quads kept",
        outside="quad mean value coordinates extrapolate there (defined, but the farther out a point lies the less "
        "it follows the cage); enlarge the cage around them",
    ),
    Family(
        "qgc",
        "quad Green coordinates",
        "torchcage.families.quad_green.api:quad_green_coordinates",
        "torchcage.families.quad_green.module:QuadGreenCoordinates",
        dims=(3,),
        faces="triquads",
        outputs=("phi", "psi"),
        backends=("native", "torch"),
        tol=True,
        op="qgc",
        help="quad Green, quads kept",
        outside="quad Green coordinates are defined inside the cage only and map these points to (nearly) the "
        "origin; enlarge the cage around them or use mean value coordinates",
    ),
    Family(
        "lbc",
        "local barycentric coordinates",
        "torchcage.families.local_barycentric.api:local_barycentric_coordinates",
        "torchcage.families.local_barycentric.module:LocalBarycentricCoordinates",
        dims=(2, 3),
        faces="triquads",
        solved=True,
        extra="lbc",
        deform=False,
        help=f"local barycentric, {_NEEDS_MESH}; slower, with progress",
        outside=_NEAREST_CELL,
    ),
    Family(
        "hc",
        "harmonic coordinates",
        "torchcage.families.harmonic.api:harmonic_coordinates",
        "torchcage.families.harmonic.module:HarmonicCoordinates",
        dims=(2, 3),
        faces="triquads",
        solved=True,
        extra="lbc",
        deform=False,
        help=f"harmonic, {_NEEDS_MESH}",
        outside=_NEAREST_CELL,
    ),
    Family(
        "bbw",
        "bounded biharmonic weights",
        "torchcage.families.biharmonic.api:bounded_biharmonic_weights",
        "torchcage.families.biharmonic.module:BoundedBiharmonicWeights",
        dims=(2, 3),
        faces="triquads",
        solved=True,
        extra="lbc",
        deform=False,
        help=f"bounded biharmonic weights, {_NEEDS_MESH}; no linear precision",
        outside=_NEAREST_CELL,
    ),
    Family(
        "mec",
        "maximum entropy coordinates",
        "torchcage.families.maximum_entropy.api:maximum_entropy_coordinates",
        "torchcage.families.maximum_entropy.module:MaximumEntropyCoordinates",
        dims=(2, 3),
        faces="triquads",
        deform=False,
        inside_only=True,
        help="maximum entropy: positive, with the mvc or qmvc prior; points must be inside the cage",
        outside="maximum entropy coordinates exist only inside the cage; enlarge the cage around them or use mean "
        "value coordinates",
    ),
)

#: Old spellings still accepted, with a :class:`DeprecationWarning`: ``{alias: short name}``.
ALIASES = {"green": "gc"}

_BY_NAME = {f.short: f for f in FAMILIES}


def names(where: Callable[[Family], bool] | None = None) -> tuple[str, ...]:
    """The short names of the families (those for which ``where(family)`` holds), in registry order."""
    return tuple(f.short for f in FAMILIES if where is None or where(f))


def family(
    name: str,
    among: Iterable[str] | None = None,
    *,
    argument: str = "method",
    stacklevel: int = 2,
) -> Family:
    """The family called ``name`` (an alias warns and resolves).

    Args:
        name: a short name (``"mvc"``) or an alias (``"green"``).
        among: the short names the caller serves (default: every family); others are refused.
        argument: the caller's argument name, for the error text.
        stacklevel: of the deprecation warning, counted from the caller of this function.

    Returns:
        The :class:`Family`.

    Raises:
        ValueError: an unknown name, or one that the caller does not serve; the text lists the
            choices.
    """
    allowed = tuple(among) if among is not None else names()
    if isinstance(name, str) and name in ALIASES:
        short = ALIASES[name]
        warnings.warn(
            f"{argument}={name!r} is deprecated; the family's name is {short!r} everywhere",
            DeprecationWarning,
            stacklevel=stacklevel + 1,
        )
        name = short
    if name not in allowed:
        raise ValueError(f"unknown {argument} {name!r}: {argument} must be one of {', '.join(allowed)}")
    return _BY_NAME[name]
