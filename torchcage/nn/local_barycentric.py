"""The old import path of :class:`torchcage.LocalBarycentricCoordinates` (its code:
``torchcage/families/local_barycentric/module.py``), kept so that modules saved whole with
``torch.save`` before the families' folders still load."""

from torchcage.families.local_barycentric.module import *  # noqa: F403
from torchcage.families.local_barycentric.module import __all__  # noqa: F401
