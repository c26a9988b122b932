"""Reusable property checks for cage coordinates, for this library's tests and for users' own.

Example:
    >>> import torch, torchcage
    >>> from torchcage.testing import assert_partition_of_unity, assert_linear_precision
    >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
    >>> x = torch.rand(50, 3, dtype=torch.float64) * 4 - 2
    >>> w = torchcage.functional.mean_value_coordinates(x, cage)
    >>> assert_partition_of_unity(w, atol=1e-12)
    >>> assert_linear_precision(w, cage.vertices, x, rtol=1e-10)
"""

from __future__ import annotations

import torch

__all__ = ["assert_interpolates", "assert_linear_precision", "assert_partition_of_unity"]


def assert_partition_of_unity(weights: torch.Tensor, *, atol: float = 1e-12) -> None:
    """Every row of ``weights`` ``(*, V)`` sums to one within ``atol`` and is finite."""
    if not bool(torch.isfinite(weights).all()):
        raise AssertionError("weights contain NaN or inf")
    err = float((weights.sum(dim=-1) - 1).abs().max()) if weights.numel() else 0.0
    if err > atol:
        raise AssertionError(f"partition of unity violated: max |sum - 1| = {err:.3e} > {atol:.1e}")


def assert_linear_precision(
    weights: torch.Tensor, vertices: torch.Tensor, points: torch.Tensor, *, rtol: float = 1e-10
) -> None:
    """``weights @ vertices`` reproduces ``points`` within ``rtol`` times the cage's bounding-box diagonal.

    Args:
        weights: ``(N, V)`` coordinates.
        vertices: ``(V, D)`` rest cage vertices.
        points: ``(N, D)`` the points the coordinates were computed for.
    """
    scale = float((vertices.max(dim=0).values - vertices.min(dim=0).values).norm())
    err = float((weights.to(vertices.dtype) @ vertices - points).abs().max()) / scale if points.numel() else 0.0
    if not err <= rtol:
        raise AssertionError(f"linear precision violated: max error {err:.3e} x cage size > {rtol:.1e}")


def assert_interpolates(weights: torch.Tensor, expected: torch.Tensor, *, atol: float = 1e-12) -> None:
    """Coordinates equal the expected hat-function values (``(N, V)`` each) within ``atol``."""
    err = float((weights - expected).abs().max()) if weights.numel() else 0.0
    if not err <= atol:
        raise AssertionError(f"interpolation violated: max error {err:.3e} > {atol:.1e}")
