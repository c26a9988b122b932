"""The old import path of :class:`torchcage.MaximumEntropyCoordinates` (its code:
``torchcage/families/maximum_entropy/module.py``), kept so that modules saved whole with
``torch.save`` before the families' folders still load."""

from torchcage.families.maximum_entropy.module import *  # noqa: F403
from torchcage.families.maximum_entropy.module import __all__  # noqa: F401
