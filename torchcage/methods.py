"""The coordinate families by short name (``mvc``, ``gc``, ...): one place that the CLI and the
editor share to build a coordinate module for a cage and a point set.

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

from .cage import Cage
from .functional.deform import OUTSIDE_EFFECT

__all__ = ["METHODS", "METHOD_EXTRAS", "METHOD_HELP", "METHOD_NAMES", "OUTSIDE_EFFECT", "build_module"]

METHODS = ("mvc", "gc", "qmvc", "qgc", "lbc", "hc", "bbw", "mec")
#: The optional extra (``pip install 'torchcage[<extra>]'``) that a method needs: the methods
#: solved on a mesh of the cage's interior need scipy (the mesher, the sparse solvers); the others
#: need nothing beyond torch.
METHOD_EXTRAS = {"lbc": "lbc", "hc": "lbc", "bbw": "lbc"}


def _needs(method: str) -> str:
    extra = METHOD_EXTRAS.get(method)
    return f"; needs torchcage[{extra}]" if extra else ""


METHOD_HELP = (
    "coordinates: mvc (mean value, any closed cage, quads split), gc (Green, quasi-conformal, quads split), "
    "qmvc (quad mean value, quads kept), qgc (quad Green, quads kept), lbc (local barycentric, solved on a mesh "
    f"of the cage interior; slower, with progress{_needs('lbc')}), hc (harmonic, solved on a mesh of the cage "
    f"interior{_needs('hc')}), bbw (bounded biharmonic weights, solved on that mesh; no linear precision"
    f"{_needs('bbw')}), mec (maximum entropy: positive, with the mvc or qmvc prior; points must be inside the "
    "cage); default mvc"
)
METHOD_NAMES = {
    "mvc": "mean value coordinates (mvc)",
    "gc": "Green coordinates (gc)",
    "qmvc": "quad mean value coordinates (qmvc)",
    "qgc": "quad Green coordinates (qgc)",
    "lbc": "local barycentric coordinates (lbc)",
    "hc": "harmonic coordinates (hc)",
    "bbw": "bounded biharmonic weights (bbw)",
    "mec": "maximum entropy coordinates (mec)",
}

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
    import torchcage

    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    if tol is not None and method not in ("qmvc", "qgc"):
        raise ValueError(f"tol is an option of qmvc and qgc (the quad integrals to a tolerance), not of {method}")
    by_points = _by_points(progress)
    if method == "mvc":
        return torchcage.MeanValueCoordinates(cage.triangulated(), points, progress=by_points)
    if method == "gc":
        return torchcage.GreenCoordinates(cage.triangulated(), points, progress=by_points)
    if method == "qmvc":
        return torchcage.QuadMeanValueCoordinates(cage, points, progress=by_points, tol=tol)
    if method == "qgc":
        return torchcage.QuadGreenCoordinates(cage, points, progress=by_points, tol=tol)
    if method == "mec":
        return torchcage.MaximumEntropyCoordinates(cage, points, progress=by_points)
    if method == "hc":
        if callable(progress):
            progress(0, None, "meshing the cage interior and solving")
        return torchcage.HarmonicCoordinates(cage, points)
    if method == "bbw":  # an iterative solve: it reports its iteration and certified gap
        if not callable(progress):
            return torchcage.BoundedBiharmonicWeights(cage, points, progress=bool(progress))
        report = progress
        report(0, None, "meshing the cage interior")
        return torchcage.BoundedBiharmonicWeights(
            cage, points, progress=lambda it, gap: report(it, None, f"iteration {it}, gap {gap:.2g}")
        )
    # lbc: an iterative solve of unknown length; it reports its iteration and residuals
    if callable(progress):
        progress(0, None, "meshing the cage interior")
    return torchcage.LocalBarycentricCoordinates(cage, points, progress=_by_iteration(progress))


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
