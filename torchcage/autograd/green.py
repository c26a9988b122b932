"""The old import path of the green autograd Functions (their code:
``torchcage/families/green/ops.py``)."""

from torchcage.families.green.ops import *  # noqa: F403
from torchcage.families.green.ops import __all__  # noqa: F401
