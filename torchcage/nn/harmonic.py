"""The old import path of :class:`torchcage.HarmonicCoordinates` (its code:
``torchcage/families/harmonic/module.py``), kept so that modules saved whole with ``torch.save``
before the families' folders still load."""

from torchcage.families.harmonic.module import *  # noqa: F403
from torchcage.families.harmonic.module import __all__  # noqa: F401
