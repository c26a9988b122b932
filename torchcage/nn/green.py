"""The Green coordinates module: quasi-conformal, detail-preserving cage deformation."""

from __future__ import annotations

import torch

from ..cage import Cage
from ..errors import warn_outside
from ..functional._stretch import conformal_stretch, stretched_normals, stretched_triangle_normals, triangle_frames
from ..functional.deform import green_deformation
from ..functional.green import green_coordinates
from .base import CageModule, detached, module_points

# The stretch helpers live in functional/_stretch.py; they are re-exported here for existing imports.
__all__ = [
    "GreenCoordinates",
    "conformal_stretch",
    "stretched_normals",
    "stretched_triangle_normals",
    "triangle_frames",
]


class GreenCoordinates(CageModule):
    """Deform points embedded in a closed triangle cage (or a closed polygon) with Green coordinates.

    ``phi`` ``(N, V)`` and ``psi`` ``(N, T)`` are computed once at rest (buffers in the
    ``state_dict``). ``forward`` computes, from the deformed cage, the unit normals ``n'`` and
    Lipman's stretch factors ``s_t = sqrt(|u'|^2 |v|^2 - 2 (u'.v')(u.v) + |v'|^2 |u|^2) / (sqrt(8) area_t)``
    (``u, v`` two edges of the rest triangle, primes deformed), and returns
    ``phi @ V' + psi @ (s * n')``. Everything is differentiable with respect to the deformed
    vertices, normals and stretch included. Rotations, uniform scalings and translations of the
    cage move the points by the same similarity.

    Args:
        cage: a closed triangle cage (triangulate quad cages with ``cage.triangulated()``), or a
            closed polygon (then the stretch of an edge is ``|a'| / |a|`` and the warp is conformal).
        points: ``(N, D)`` points inside the cage (points outside it warn with their count
            (:class:`torchcage.OutsideCageWarning`): Green coordinates map them to nearly the origin).
        chunk_size: points per chunk while computing the coordinates.
        dtype: dtype of the stored coordinates (float64 by default).

    Shape:
        - Input: ``(*, V, D)`` deformed cage vertices.
        - Output: ``(*, N, D)`` deformed points.

    Examples:
        >>> import torch, torchcage
        >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> pts = torch.rand(50, 3, dtype=torch.float64) * 1.8 - 0.9
        >>> gc = torchcage.GreenCoordinates(cage, pts)
        >>> torch.allclose(gc(cage.vertices), pts)
        True
        >>> torch.allclose(gc(3 * cage.vertices + 1), 3 * pts + 1)
        True
    """

    phi: torch.Tensor
    psi: torch.Tensor
    triangles: torch.Tensor
    edges: torch.Tensor

    def __init__(
        self, cage: Cage, points: torch.Tensor, *, chunk_size: int | None = None, dtype: torch.dtype = torch.float64
    ) -> None:
        points = module_points(points, cage)
        cage = detached(cage)
        phi, psi = green_coordinates(points, cage, chunk_size=chunk_size, dtype=dtype)
        super().__init__(cage, points)
        warn_outside(phi.sum(dim=-1).reshape(-1), "Green coordinates")
        self.register_buffer("phi", phi)
        self.register_buffer("psi", psi)
        self.register_buffer("triangles", cage.triangles.clone())
        self.register_buffer("edges", cage.edges.clone())

    def forward(self, vertices: torch.Tensor) -> torch.Tensor:
        """Deformed points ``(*, N, D)`` for deformed cage vertices ``(*, V, D)``."""
        self._check_vertices(vertices, self.phi)
        faces = self.edges if self.dim == 2 else self.triangles
        return green_deformation(self.phi, self.psi, self.rest_vertices, vertices, faces)
