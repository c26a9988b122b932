"""Lazy imports of the cage maker's optional dependencies (the ``cage`` extra)."""

from __future__ import annotations

import importlib
from types import ModuleType

#: import name -> distribution name, for the message.
_PACKAGES = {
    "scipy.ndimage": "scipy",
    "skimage.measure": "scikit-image",
    "fast_simplification": "fast-simplification",
    "networkx": "networkx",
}


def require(module: str) -> ModuleType:
    """Import ``module`` or raise an ``ImportError`` that names the extra to install.

    Examples:
        >>> require("scipy.ndimage").__name__
        'scipy.ndimage'
    """
    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise ImportError(
            f"torchcage.make_cage needs {_PACKAGES.get(module, module)}: install the cage maker's dependencies "
            "with `pip install 'torchcage[cage]'` (scipy, scikit-image, fast-simplification, networkx)"
        ) from err
