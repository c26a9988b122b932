"""torchcage: cage coordinates (mean value, quad mean value, Green, local barycentric) as PyTorch
building blocks.

Examples:
    >>> import torch, torchcage
    >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
    >>> mvc = torchcage.MeanValueCoordinates(cage, torch.zeros(1, 3, dtype=torch.float64))
    >>> moved = mvc(cage.vertices * 2 + 1)          # scale the cage by 2, shift it by 1
    >>> torch.allclose(moved, torch.ones(1, 3, dtype=torch.float64))
    True
"""

from torchcage import data, distributed, functional, variational
from torchcage.cage import Cage
from torchcage.cagegen import make_cage
from torchcage.errors import (
    CageError,
    CageOrientationError,
    CageTopologyError,
    DegenerateFaceError,
    OutsideCageWarning,
    PointsError,
)
from torchcage.functional.deform import deform
from torchcage.io import load_cage, load_mesh, save_cage, save_mesh
from torchcage.nn import (
    BoundedBiharmonicWeights,
    GreenCoordinates,
    HarmonicCoordinates,
    LocalBarycentricCoordinates,
    MaximumEntropyCoordinates,
    MeanValueCoordinates,
    QuadGreenCoordinates,
    QuadMeanValueCoordinates,
)
from torchcage.viewer import view

__version__ = "0.1.0"

__all__ = [
    "BoundedBiharmonicWeights",
    "Cage",
    "CageError",
    "CageOrientationError",
    "CageTopologyError",
    "DegenerateFaceError",
    "GreenCoordinates",
    "HarmonicCoordinates",
    "LocalBarycentricCoordinates",
    "MaximumEntropyCoordinates",
    "MeanValueCoordinates",
    "OutsideCageWarning",
    "PointsError",
    "QuadGreenCoordinates",
    "QuadMeanValueCoordinates",
    "__version__",
    "data",
    "deform",
    "distributed",
    "functional",
    "load_cage",
    "load_mesh",
    "make_cage",
    "save_cage",
    "save_mesh",
    "variational",
    "view",
]
