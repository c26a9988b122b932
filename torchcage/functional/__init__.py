"""Functional API: pure, stateless coordinate kernels, chunked over points.

Every function takes query points ``(*, D)`` and a :class:`~torchcage.Cage` and returns the
coordinates ``(*, V)`` (or their derivatives), computed in float64 by default.
"""

from torchcage.families.biharmonic.api import bounded_biharmonic_weights, solve_bounded_biharmonic_weights
from torchcage.families.green.api import green_coordinates
from torchcage.families.green.derivatives import green_derivatives
from torchcage.families.harmonic.api import harmonic_coordinates, solve_harmonic_coordinates
from torchcage.families.local_barycentric.api import (
    local_barycentric_coordinates,
    locality_statistics,
    solve_local_barycentric,
)
from torchcage.families.maximum_entropy.api import maximum_entropy_coordinates
from torchcage.families.mean_value.api import mean_value_coordinates
from torchcage.families.mean_value.derivatives import mean_value_derivatives, mean_value_gradients, mean_value_hessians
from torchcage.families.quad_green.api import quad_green_coordinates
from torchcage.families.quad_mean_value.api import quad_mean_value_coordinates
from torchcage.functional.deform import deform

__all__ = [
    "bounded_biharmonic_weights",
    "deform",
    "green_coordinates",
    "green_derivatives",
    "harmonic_coordinates",
    "local_barycentric_coordinates",
    "locality_statistics",
    "maximum_entropy_coordinates",
    "mean_value_coordinates",
    "mean_value_derivatives",
    "mean_value_gradients",
    "mean_value_hessians",
    "quad_green_coordinates",
    "quad_mean_value_coordinates",
    "solve_bounded_biharmonic_weights",
    "solve_harmonic_coordinates",
    "solve_local_barycentric",
]
