"""The old import path of :class:`torchcage.QuadGreenCoordinates` (its code:
``torchcage/families/quad_green/module.py``), kept so that modules saved whole with
``torch.save`` before the families' folders still load."""

from torchcage.families.quad_green.module import *  # noqa: F403
from torchcage.families.quad_green.module import __all__  # noqa: F401
