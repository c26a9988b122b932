"""Cages for Gaussian splat scenes and radiance fields.

- :class:`GaussianScene`, :func:`read_ply`, :func:`write_ply`: the 3D Gaussian splatting PLY file
  as tensors (numpy alone; a read file written back is the same bytes).
- :func:`rotate_sh`, :func:`eval_sh`: view-dependent colours (real spherical harmonics, degrees
  0-3) and their exact rotation.
"""

from __future__ import annotations

from torchcage.splats.deform import DeformedGaussians, DeformGaussians
from torchcage.splats.inverse import RestPoints, rest_points
from torchcage.splats.ply import PlyError, PlyLayout, read_ply, write_ply
from torchcage.splats.scene import GaussianScene, quaternion_to_matrix
from torchcage.splats.sh import eval_sh, rotate_sh, sh_basis

__all__ = [
    "DeformGaussians",
    "DeformedGaussians",
    "GaussianScene",
    "PlyError",
    "PlyLayout",
    "RestPoints",
    "eval_sh",
    "quaternion_to_matrix",
    "read_ply",
    "rest_points",
    "rotate_sh",
    "sh_basis",
    "write_ply",
]
