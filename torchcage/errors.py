"""Exceptions raised by torchcage.

Every error is a subclass of :class:`ValueError` or :class:`TypeError` so that callers can catch
them with the builtin classes; the message names the problem and the way to fix it.
"""

from __future__ import annotations

__all__ = [
    "CageError",
    "CageMakerError",
    "CageOrientationError",
    "CageTopologyError",
    "DegenerateFaceError",
    "MeshError",
    "OutsideCageWarning",
    "PointsError",
]


class CageError(ValueError):
    """A cage is not usable as given (bad vertices, faces, or dimension)."""


class CageTopologyError(CageError):
    """A cage is open or non-manifold; the message names the offending edges."""


class CageOrientationError(CageError):
    """A cage's faces are not consistently oriented; the message names a face pair."""


class DegenerateFaceError(CageError):
    """A cage face has (numerically) zero area or length; the message names the faces."""


class MeshError(ValueError):
    """An input mesh or point set is unusable: empty, non-finite, without extent, or with faces
    that index no vertex; the message names the problem."""


class CageMakerError(ValueError):
    """The cage maker could not meet its guarantees (enclosure, no self-intersection) for the
    given settings; the message names the setting to change."""


class PointsError(ValueError):
    """Query points are unusable: wrong shape, non-finite values, or a mismatched device."""


class OutsideCageWarning(UserWarning):
    """Points lie outside what a cage's coordinates cover: outside the cage for quad Green
    coordinates (which map them to nearly the origin), beyond the exterior band for Green
    coordinates (continued through the nearest faces); the message gives their count."""


def warn_outside(phi_sum, what: str) -> None:
    """Warn with the count of points whose Green coordinates sum to less than 1/2 (their winding
    number: 1 inside the cage, 0 outside). ``phi_sum`` ``(N,)``."""
    import warnings

    outside = int((phi_sum < 0.5).sum())
    if outside:
        warnings.warn(
            f"{outside} of {phi_sum.shape[0]} points lie outside the cage: {what} are defined inside it and "
            "map these points to (nearly) the origin; enlarge the cage around them or use mean value "
            "coordinates (defined everywhere)",
            OutsideCageWarning,
            stacklevel=3,
        )
