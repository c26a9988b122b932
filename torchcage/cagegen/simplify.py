"""Coarsening of the fine envelope to a target vertex count: quadric error decimation
(fast-simplification, Garland-Heckbert edge collapses), then a clean-up of what decimation can
leave behind (unused vertices, zero-area faces, pieces that collapsed)."""

from __future__ import annotations

import numpy as np

from torchcage.cagegen._deps import require


def _clean(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop faces with a repeated index and vertices that no face uses (reindexed)."""
    f = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])]
    used, inverse = np.unique(f, return_inverse=True)
    return vertices[used], inverse.reshape(-1, 3).astype(np.int64)


def decimate(
    vertices: np.ndarray, faces: np.ndarray, target_vertices: int, attempts: int = 4
) -> tuple[np.ndarray, np.ndarray]:
    """Decimate a closed triangle surface to about ``target_vertices`` vertices.

    A closed surface with ``c`` components of genus ``g`` has ``F = 2 V - 4 (c - g)`` faces; the
    face target follows from that and is corrected from the count each attempt gives (within 10%
    of the target, or the closest of ``attempts``). Where a pass stalls well above its goal, the
    next one simplifies that pass's output (its quadrics then start afresh from the coarser mesh).

    Args:
        vertices: ``(M, 3)``.
        faces: ``(K, 3)``.
        target_vertices: wanted vertex count.

    Returns:
        ``vertices (V, 3)``, ``faces (F, 3)``.

    Examples:
        >>> from skimage.draw import ellipsoid
        >>> from skimage.measure import marching_cubes
        >>> v, f, _, _ = marching_cubes(ellipsoid(20, 20, 20).astype(float), 0.5)
        >>> w, g = decimate(v, f.astype(np.int64), 100)
        >>> 90 <= w.shape[0] <= 110, g.shape[0] == 2 * w.shape[0] - 4
        (True, True)
    """
    fs = require("fast_simplification")
    v0, f0 = _clean(np.ascontiguousarray(vertices, dtype=np.float64), np.ascontiguousarray(faces, dtype=np.int64))
    if v0.shape[0] <= target_vertices:
        return v0, f0
    goal = 2 * target_vertices
    best: tuple[np.ndarray, np.ndarray] | None = None
    src_v, src_f = v0, f0
    for _ in range(attempts):
        reduction = float(np.clip(1.0 - goal / src_f.shape[0], 0.0, 1.0 - 1e-9))
        v, f = fs.simplify(src_v, src_f, target_reduction=reduction, agg=7)
        v, f = _clean(np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64))
        if best is None or abs(v.shape[0] - target_vertices) < abs(best[0].shape[0] - target_vertices):
            best = (v, f)
        if abs(v.shape[0] - target_vertices) <= 0.1 * target_vertices or v.shape[0] == 0:
            break
        if f.shape[0] > 1.5 * goal:
            # Stalled: the decimation can stop well short of its goal (measured: 262 vertices for
            # a goal of 60, whatever the reduction asked, on FireHydrant's envelope at four times
            # the margin); a pass over its own output goes on from there (62 in one pass).
            src_v, src_f, goal = v, f, 2 * target_vertices
        else:
            goal = max(8, round(goal * target_vertices / max(v.shape[0], 1)))
    if best is None:
        raise ValueError(f"attempts must be at least 1, got {attempts}")
    return best
