"""The coordinate modules: thin ``nn.Module`` wrappers around precomputed weights."""

from .base import CageModule
from .biharmonic import BoundedBiharmonicWeights
from .green import GreenCoordinates
from .harmonic import HarmonicCoordinates
from .local_barycentric import LocalBarycentricCoordinates
from .maximum_entropy import MaximumEntropyCoordinates
from .mean_value import MeanValueCoordinates
from .quad_green import QuadGreenCoordinates
from .quad_mean_value import QuadMeanValueCoordinates

__all__ = [
    "BoundedBiharmonicWeights",
    "CageModule",
    "GreenCoordinates",
    "HarmonicCoordinates",
    "LocalBarycentricCoordinates",
    "MaximumEntropyCoordinates",
    "MeanValueCoordinates",
    "QuadGreenCoordinates",
    "QuadMeanValueCoordinates",
]
