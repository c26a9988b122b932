"""Exceptions raised by torchcage.

Every error is a subclass of :class:`ValueError` or :class:`TypeError` so that callers can catch
them with the builtin classes; the message names the problem and the way to fix it.
"""

from __future__ import annotations

__all__ = ["CageError", "CageOrientationError", "CageTopologyError", "DegenerateFaceError", "PointsError"]


class CageError(ValueError):
    """A cage is not usable as given (bad vertices, faces, or dimension)."""


class CageTopologyError(CageError):
    """A cage is open or non-manifold; the message names the offending edges."""


class CageOrientationError(CageError):
    """A cage's faces are not consistently oriented; the message names a face pair."""


class DegenerateFaceError(CageError):
    """A cage face has (numerically) zero area or length; the message names the faces."""


class PointsError(ValueError):
    """Query points are unusable: wrong shape, non-finite values, or a mismatched device."""
