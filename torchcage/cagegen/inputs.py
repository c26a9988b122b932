"""Checks and normalises the cage maker's input: a triangle mesh or a point cloud."""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from torchcage.errors import MeshError

#: A face whose area is below this fraction of ``diagonal^2`` counts as degenerate.
DEGENERATE_AREA = 1e-14


@dataclass(frozen=True)
class MeshInput:
    """A checked input: ``vertices (N, 3)`` float64, ``faces (F, 3)`` int64 (``None`` for a point
    cloud), bounding box ``lo``, ``hi`` and its ``diagonal``."""

    vertices: np.ndarray
    faces: np.ndarray | None
    lo: np.ndarray
    hi: np.ndarray
    diagonal: float


def _as_array(x: Any, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    try:
        return np.asarray(x)
    except Exception as err:  # ragged lists and the like
        raise MeshError(f"{name} could not be read as an array: {err}") from err


def check_input(vertices: Any, faces: Any = None) -> MeshInput:
    """Check a mesh (``faces (F, 3)``) or a point cloud (``faces=None``) for the cage maker.

    Faces with (numerically) zero area are ignored with a warning that counts them; a mesh whose
    faces are all degenerate is refused.

    Args:
        vertices: ``(N, 3)`` array-like.
        faces: ``(F, 3)`` integer array-like, or ``None``.

    Returns:
        the checked :class:`MeshInput`.

    Raises:
        MeshError: empty input, wrong shapes, non-finite coordinates, a single point (or coincident
            points: no extent), face indices out of range, or only degenerate faces.

    Examples:
        >>> tet = [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
        >>> m = check_input(tet, [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        >>> m.faces.shape, round(m.diagonal, 6)
        ((4, 3), 1.732051)
    """
    v = _as_array(vertices, "vertices")
    if v.ndim != 2 or v.shape[-1] != 3:
        raise MeshError(f"vertices must have shape (N, 3), got {tuple(v.shape)}")
    if v.shape[0] == 0:
        raise MeshError("the mesh is empty (no vertices): a cage needs a shape to enclose")
    if not np.issubdtype(v.dtype, np.number):
        raise MeshError(f"vertices must be numbers, got dtype {v.dtype}")
    v = v.astype(np.float64)
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise MeshError(
            f"{int(bad.sum())} of {v.shape[0]} vertices have NaN or infinite coordinates (first: vertex "
            f"{int(np.nonzero(bad)[0][0])}); remove or repair them before making a cage"
        )
    lo, hi = v.min(axis=0), v.max(axis=0)
    diagonal = float(np.linalg.norm(hi - lo))
    if not diagonal > 0.0:
        raise MeshError(
            f"the {v.shape[0]} vertices coincide (a single point, no extent): a cage needs a shape with a size; "
            "give at least two distinct points"
        )
    if faces is None:
        return MeshInput(v, None, lo, hi, diagonal)
    f = _as_array(faces, "faces")
    if f.size == 0:
        raise MeshError("the mesh has no faces: pass faces=None to make a cage around the vertices as a point cloud")
    if f.ndim != 2 or f.shape[1] != 3:
        raise MeshError(f"faces must have shape (F, 3) (triangles), got {tuple(f.shape)}")
    if not np.issubdtype(f.dtype, np.integer):
        if np.issubdtype(f.dtype, np.floating) and np.all(np.isfinite(f)) and np.all(f == np.round(f)):
            f = f.astype(np.int64)
        else:
            raise MeshError(f"faces must hold integer vertex indices, got dtype {f.dtype}")
    f = f.astype(np.int64)
    out = (f < 0) | (f >= v.shape[0])
    if out.any():
        k = int(np.nonzero(out.any(axis=1))[0][0])
        raise MeshError(
            f"face {k} {f[k].tolist()} indexes a vertex outside 0..{v.shape[0] - 1} "
            f"({int(out.any(axis=1).sum())} such faces); faces index the rows of vertices, from 0"
        )
    p = v[f]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    keep = area > DEGENERATE_AREA * diagonal**2
    if not keep.any():
        raise MeshError(
            f"all {f.shape[0]} faces are degenerate (zero area: repeated or collinear vertices); "
            "repair the faces or pass faces=None to use the vertices as a point cloud"
        )
    if not keep.all():
        warnings.warn(
            f"{int((~keep).sum())} of {f.shape[0]} faces have zero area (repeated or collinear vertices) "
            "and are ignored",
            stacklevel=3,
        )
    return MeshInput(v, f[keep], lo, hi, diagonal)
