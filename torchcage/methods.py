"""The coordinate families by short name (``mvc``, ``gc``, ...), as the CLI and the editor name
them, and :func:`build_module`: a family's module for a cage and a point set. The names and their
descriptions come from the registry, :mod:`torchcage.families`.

Examples:
    >>> import torch, torchcage
    >>> from torchcage.methods import build_module
    >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj"))
    >>> module = build_module("qmvc", cage, torch.zeros(1, 3, dtype=torch.float64))
    >>> module(cage.vertices + 1)
    tensor([[1., 1., 1.]], dtype=torch.float64)
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from torchcage.cage import Cage
from torchcage.families import FAMILIES, Family, family, names
from torchcage.functional.deform import OUTSIDE_EFFECT

__all__ = ["METHODS", "METHOD_EXTRAS", "METHOD_HELP", "METHOD_NAMES", "OUTSIDE_EFFECT", "build_module"]

#: The families' short names, in the registry's order (:data:`torchcage.families.FAMILIES`).
METHODS = names()
#: The optional extra (``pip install 'torchcage[<extra>]'``) that a method needs: the methods
#: solved on a mesh of the cage's interior need scipy (the mesher, the sparse solvers); the others
#: need nothing beyond torch.
METHOD_EXTRAS = {f.short: f.extra for f in FAMILIES if f.extra}


def _help(f: Family) -> str:
    return f"{f.short} ({f.help}{'; needs torchcage[' + f.extra + ']' if f.extra else ''})"


METHOD_HELP = "coordinates: " + ", ".join(_help(f) for f in FAMILIES) + f"; default {FAMILIES[0].short}"
#: ``"mean value coordinates (mvc)"`` by short name.
METHOD_NAMES = {f.short: f.name for f in FAMILIES}

#: A progress report: ``progress(done, total, message)``; ``total`` is ``None`` where the work has
#: no known length (the iterative LBC solve reports its iteration and residuals in ``message``).
Progress = Callable[[int, "int | None", str], None]


def build_module(
    method: str, cage: Cage, points: torch.Tensor, progress: bool | Progress = False, tol: float | None = None
) -> nn.Module:
    """The coordinate module of ``method`` for ``cage`` and ``points`` ``(N, D)``.

    ``mvc`` and ``gc`` split quads into triangles (along q0-q2); ``qmvc`` and ``qgc`` keep them.

    Args:
        method: one of :data:`METHODS`.
        cage: the rest cage.
        points: ``(N, D)`` points to embed.
        progress: ``True`` for the methods' own progress bars, or a callable
            ``progress(done, total, message)`` (see :data:`Progress`).
        tol: ``qmvc`` and ``qgc`` only: the quad integrals to this relative tolerance (see
            :func:`torchcage.functional.quad_mean_value_coordinates`).

    Returns:
        The module: ``module(vertices (*, V, D)) -> (*, N, D)``.

    Raises:
        ValueError: an unknown method, or ``tol`` with a method other than ``qmvc`` and ``qgc``
            (and every error of the module itself).
    """
    fam = family(method)
    method = fam.short
    if tol is not None and not fam.tol:
        raise ValueError(
            f"tol is an option of {' and '.join(names(lambda f: f.tol))} (the quad integrals to a tolerance), "
            f"not of {method}"
        )
    module = fam.module()
    if fam.faces == "triangles":
        cage = cage.triangulated()
    if not fam.solved:  # closed-form families: a progress bar over chunks of points
        return module(cage, points, progress=_by_points(progress), **({"tol": tol} if fam.tol else {}))
    if method == "hc":
        if callable(progress):
            progress(0, None, "meshing the cage interior and solving")
        return module(cage, points)
    if method == "bbw":  # an iterative solve: it reports its iteration and certified gap
        if not callable(progress):
            return module(cage, points, progress=bool(progress))
        report = progress
        report(0, None, "meshing the cage interior")
        return module(cage, points, progress=lambda it, gap: report(it, None, f"iteration {it}, gap {gap:.2g}"))
    # lbc: an iterative solve of unknown length; it reports its iteration and residuals
    if callable(progress):
        progress(0, None, "meshing the cage interior")
    return module(cage, points, progress=_by_iteration(progress))


def _by_points(progress: bool | Progress) -> bool | Callable[[int, int], None]:
    """The chunked kernels' ``progress(done, total)`` for a :data:`Progress` (bools pass through)."""
    if not callable(progress):
        return bool(progress)
    return lambda done, total: progress(done, total, f"{done:,} of {total:,} points")


def _by_iteration(progress: bool | Progress) -> bool | Callable[[int, float, float], None]:
    """The LBC solver's ``progress(iteration, primal, dual)`` for a :data:`Progress`."""
    if not callable(progress):
        return bool(progress)
    return lambda it, primal, dual: progress(it, None, f"iteration {it:,}, residuals {primal:.1e} / {dual:.1e}")
