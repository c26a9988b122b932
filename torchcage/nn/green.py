"""The Green coordinates module: quasi-conformal, detail-preserving cage deformation."""

from __future__ import annotations

import torch

from ..cage import Cage
from ..functional.green import green_coordinates
from .base import CageModule

__all__ = ["GreenCoordinates", "conformal_stretch", "stretched_normals", "stretched_triangle_normals"]


def stretched_normals(rest: torch.Tensor, deformed: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Outward edge normals of a deformed polygon scaled by the edge stretch ``|a'| / |a|``
    (the 2D Green deformation's ``s_j n'_j``), differentiable in ``deformed``.

    Args:
        rest: ``(V, 2)`` rest vertices.
        deformed: ``(*, V, 2)`` deformed vertices.
        edges: ``(E, 2)`` counter-clockwise edges.

    Returns:
        ``(*, E, 2)``.
    """
    a0 = rest[edges[:, 1]] - rest[edges[:, 0]]
    a1 = deformed[..., edges[:, 1], :] - deformed[..., edges[:, 0], :]
    return torch.stack([a1[..., 1], -a1[..., 0]], dim=-1) / a0.norm(dim=-1).to(deformed.dtype)[:, None]


def triangle_frames(vertices: torch.Tensor, triangles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Edge vectors ``u = p1 - p0``, ``v = p2 - p0`` and unit normals of triangles, for vertices
    ``(*, V, 3)`` and triangles ``(T, 3)``: each ``(*, T, 3)``."""
    p = vertices[..., triangles, :]  # (*, T, 3, 3)
    u, v = p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :]
    n = torch.nn.functional.normalize(torch.linalg.cross(u, v, dim=-1), dim=-1)
    return u, v, n


def conformal_stretch(u0: torch.Tensor, v0: torch.Tensor, u1: torch.Tensor, v1: torch.Tensor) -> torch.Tensor:
    """Lipman's stretch factor of the linear map taking the tangent pair ``(u0, v0)`` to ``(u1, v1)``
    (all ``(..., 3)``): ``sqrt(|u1|^2 |v0|^2 - 2 (u1.v1)(u0.v0) + |v1|^2 |u0|^2) / (sqrt(2) |u0 x v0|)``,
    the root mean square of its two singular values (``s`` for a similarity of scale ``s``)."""
    s2 = (
        u1.square().sum(-1) * v0.square().sum(-1)
        - 2 * (u1 * v1).sum(-1) * (u0 * v0).sum(-1)
        + v1.square().sum(-1) * u0.square().sum(-1)
    )
    return torch.sqrt(s2.clamp_min(0.0)) / (2**0.5 * torch.linalg.cross(u0, v0, dim=-1).norm(dim=-1))


def stretched_triangle_normals(rest: torch.Tensor, deformed: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    """Unit outward normals of deformed triangles times Lipman's stretch factors (the 3D Green
    deformation's ``s_t n'_t``), ``(*, T, 3)`` for vertices ``(V, 3)`` / ``(*, V, 3)``."""
    u0, v0, _ = triangle_frames(rest.to(deformed.dtype), triangles)
    u1, v1, n1 = triangle_frames(deformed, triangles)
    return conformal_stretch(u0, v0, u1, v1)[..., None] * n1


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
        points: ``(N, D)`` points inside the cage.
        chunk_size: points per chunk while computing the coordinates.
        dtype: dtype of the stored coordinates (float64 by default).

    Shape:
        - Input: ``(*, V, D)`` deformed cage vertices.
        - Output: ``(*, N, D)`` deformed points.

    Example:
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
        phi, psi = green_coordinates(points, cage, chunk_size=chunk_size, dtype=dtype)
        super().__init__(cage, torch.as_tensor(points).reshape(-1, cage.dim))
        phi = phi.reshape(-1, cage.num_vertices)
        self.register_buffer("phi", phi)
        self.register_buffer("psi", psi.reshape(phi.shape[0], -1))
        self.register_buffer("triangles", cage.triangles.clone())
        self.register_buffer("edges", cage.edges.clone())

    def forward(self, vertices: torch.Tensor) -> torch.Tensor:
        """Deformed points ``(*, N, D)`` for deformed cage vertices ``(*, V, D)``."""
        self._check_vertices(vertices, self.phi)
        if self.dim == 2:
            # s_j n'_j = R(-90) a'_j / |a_j|: the stretch |a'| / |a| times the unit outward normal.
            sn = stretched_normals(self.rest_vertices, vertices, self.edges)
        else:
            sn = stretched_triangle_normals(self.rest_vertices, vertices, self.triangles)
        return torch.matmul(self.phi.to(vertices.dtype), vertices) + torch.matmul(self.psi.to(vertices.dtype), sn)
