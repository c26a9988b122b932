"""The cage maker: closed, enclosing, self-intersection-free cages for meshes and point clouds
(``pip install 'torchcage[cage]'``). See :func:`make_cage` and ``docs/cagegen.md``."""

from torchcage.cagegen.checks import self_intersections, signed_clearance
from torchcage.cagegen.maker import DEFAULT_MARGIN, DEFAULT_SEAL, make_cage
from torchcage.cagegen.report import CageReport, measure_cage

__all__ = [
    "DEFAULT_MARGIN",
    "DEFAULT_SEAL",
    "CageReport",
    "make_cage",
    "measure_cage",
    "self_intersections",
    "signed_clearance",
]
