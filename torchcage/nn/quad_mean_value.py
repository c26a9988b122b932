"""The old import path of :class:`torchcage.QuadMeanValueCoordinates` (its code:
``torchcage/families/quad_mean_value/module.py``), kept so that modules saved whole with
``torch.save`` before the families' folders still load."""

from torchcage.families.quad_mean_value.module import *  # noqa: F403
from torchcage.families.quad_mean_value.module import __all__  # noqa: F401
