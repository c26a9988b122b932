"""Small data bundled with torchcage for the demo, the docs and the doctests.

- ``cube.obj``: the quad cube ``[-1, 1]^3`` (8 vertices, 6 quads).
- ``bar.obj``: a bumpy bar (a mesh made by ``examples/make_demo_data.py``).
- ``bar_cage.obj``: its quad cage (16 vertices, 14 quads); ``bar_cage_deformed.obj``: a bent,
  twisted pose of that cage.
- ``blob2d.obj``: a 2D polygon cage (vertices in order, z = 0).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["path"]


def path(name: str) -> Path:
    """Path of a bundled data file.

    Examples:
        >>> import torchcage
        >>> torchcage.data.path("cube.obj").name
        'cube.obj'
    """
    p = Path(str(resources.files(__package__).joinpath(name)))
    if not p.is_file():
        available = sorted(f.name for f in p.parent.iterdir() if f.suffix == ".obj")
        raise FileNotFoundError(f"no bundled data file {name!r}; available: {available}")
    return p
