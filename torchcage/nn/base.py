"""The old import path of :class:`torchcage.nn.CageModule` (its code:
``torchcage/_core/module.py``), kept so that modules saved whole with ``torch.save`` before the
families' folders still load."""

from torchcage._core.module import *  # noqa: F403
from torchcage._core.module import __all__  # noqa: F401
