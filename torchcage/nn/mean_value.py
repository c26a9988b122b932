"""The old import path of :class:`torchcage.MeanValueCoordinates` (its code:
``torchcage/families/mean_value/module.py``), kept so that modules saved whole with
``torch.save`` before the families' folders still load."""

from torchcage.families.mean_value.module import *  # noqa: F403
from torchcage.families.mean_value.module import __all__  # noqa: F401
