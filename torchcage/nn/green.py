"""The old import path of :class:`torchcage.GreenCoordinates` (its code:
``torchcage/families/green/module.py``), kept so that modules saved whole with ``torch.save``
before the families' folders still load."""

from torchcage.families.green.module import *  # noqa: F403
from torchcage.families.green.module import __all__  # noqa: F401
