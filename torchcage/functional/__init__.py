"""Functional API: pure, stateless coordinate kernels, chunked over points.

Every function takes query points ``(*, D)`` and a :class:`~torchcage.Cage` and returns the
coordinates ``(*, V)`` (or their derivatives), computed in float64 by default.
"""

from .biharmonic import bounded_biharmonic_weights, solve_bounded_biharmonic_weights
from .deform import deform
from .green import green_coordinates
from .green_derivatives import green_derivatives
from .harmonic import harmonic_coordinates, solve_harmonic_coordinates
from .local_barycentric import local_barycentric_coordinates, locality_statistics, solve_local_barycentric
from .maximum_entropy import maximum_entropy_coordinates
from .mean_value import mean_value_coordinates
from .mean_value_derivatives import mean_value_derivatives, mean_value_gradients, mean_value_hessians
from .quad_green import quad_green_coordinates
from .quad_mean_value import quad_mean_value_coordinates

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
