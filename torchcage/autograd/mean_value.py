"""The old import path of the mean value autograd Functions (their code:
``torchcage/families/mean_value/ops.py``)."""

from torchcage.families.mean_value.ops import *  # noqa: F403
from torchcage.families.mean_value.ops import __all__  # noqa: F401
