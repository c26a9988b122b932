"""The old import path of :class:`torchcage.BoundedBiharmonicWeights` (its code:
``torchcage/families/biharmonic/module.py``), kept so that modules saved whole with
``torch.save`` before the families' folders still load."""

from torchcage.families.biharmonic.module import *  # noqa: F403
from torchcage.families.biharmonic.module import __all__  # noqa: F401
