"""The coordinate modules: thin ``nn.Module`` wrappers around precomputed weights."""

from torchcage._core.module import CageModule
from torchcage.families.biharmonic.module import BoundedBiharmonicWeights
from torchcage.families.green.module import GreenCoordinates
from torchcage.families.harmonic.module import HarmonicCoordinates
from torchcage.families.local_barycentric.module import LocalBarycentricCoordinates
from torchcage.families.maximum_entropy.module import MaximumEntropyCoordinates
from torchcage.families.mean_value.module import MeanValueCoordinates
from torchcage.families.quad_green.module import QuadGreenCoordinates
from torchcage.families.quad_mean_value.module import QuadMeanValueCoordinates

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
