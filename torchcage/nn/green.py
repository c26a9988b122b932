"""The Green coordinates module: quasi-conformal, detail-preserving cage deformation."""

from __future__ import annotations

import warnings
from collections.abc import Callable

import torch

from ..cage import Cage
from ..errors import OutsideCageWarning, warn_outside
from ..functional._exterior import extend_outside
from ..functional._stretch import conformal_stretch, stretched_normals, stretched_triangle_normals, triangle_frames
from ..functional.deform import green_deformation
from ..functional.green import green_coordinates
from .base import CageModule, detached, module_points

#: Default distance outside the cage (relative to its size) beyond which extended points warn.
EXTERIOR_BAND = 0.25


def _extend(
    points: torch.Tensor, cage: Cage, phi: torch.Tensor, psi: torch.Tensor, band: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Continue ``phi (*B, N, V)``, ``psi (*B, N, T)`` outside the cage (one batch element at a
    time) and warn with the count of points farther out than ``band`` times the cage's size."""
    cages = cage.unbind() if cage.is_batched else [cage]
    B = len(cages)  # (explicit: with no points a -1 in the shapes below would be ambiguous)
    pts = points.expand(*cage.batch_shape, *points.shape[-2:]).reshape(B, *points.shape[-2:])
    phis, psis = phi.reshape(B, *phi.shape[-2:]), psi.reshape(B, *psi.shape[-2:])
    out_phi, out_psi, far, outside = [], [], 0, 0
    for b, c in enumerate(cages):
        p64 = pts[b].to(torch.float64)
        ph, ps, dist = extend_outside(p64, c.to(torch.float64), phis[b].to(torch.float64), psis[b].to(torch.float64))
        out_phi.append(ph.to(phi.dtype))
        out_psi.append(ps.to(psi.dtype))
        far = max(far, int((dist > band * c.scale).sum()))
        outside = max(outside, int((dist > 0).sum()))
    if far:
        warnings.warn(
            f"{far} of {points.shape[-2]} points lie farther than {band:g} of the cage's size outside it "
            f"({outside} outside in all): Green coordinates continue them through the nearest faces, exact "
            "at rest but extrapolating those faces' motion; enlarge the cage around them, raise exterior_band "
            "to accept this, or use mean value coordinates (defined everywhere)",
            OutsideCageWarning,
            stacklevel=3,
        )
    return torch.stack(out_phi).reshape(phi.shape), torch.stack(out_psi).reshape(psi.shape)


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
        points: ``(N, D)`` points inside the cage, or outside it: their coordinates are continued
            through the nearest faces (Lipman et al.'s exterior extension, see
            :func:`torchcage.functional.green_coordinates`), exact at rest and continuous across
            the cage. Points farther outside than ``exterior_band`` times the cage's size warn with
            their count (:class:`torchcage.OutsideCageWarning`): there the continuation
            extrapolates the nearest faces' motion.
        chunk_size: points per chunk while computing the coordinates.
        dtype: dtype of the stored coordinates (float64 by default).
        exterior: ``"extend"`` (default) or ``"none"`` (the bare Green integrals, which send outside
            points to nearly the origin; they then warn with their count).
        exterior_band: the distance outside the cage, relative to its size (bounding-box
            diagonal), beyond which extended points warn.
        progress: ``True`` for a progress bar while computing the coordinates, or a callable
            ``progress(done, total)`` (points done so far).

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
        self,
        cage: Cage,
        points: torch.Tensor,
        *,
        chunk_size: int | None = None,
        dtype: torch.dtype = torch.float64,
        exterior: str = "extend",
        exterior_band: float = EXTERIOR_BAND,
        progress: bool | Callable[[int, int], None] = False,
    ) -> None:
        points = module_points(points, cage)
        cage = detached(cage)
        phi, psi = green_coordinates(
            points, cage, chunk_size=chunk_size, dtype=dtype, exterior="none", progress=progress
        )
        super().__init__(cage, points)
        if exterior == "none":
            warn_outside(phi.sum(dim=-1).reshape(-1), "Green coordinates")
        elif exterior == "extend":
            phi, psi = _extend(points, cage, phi, psi, exterior_band)
        else:
            raise ValueError(f"exterior must be 'extend' or 'none', got {exterior!r}")
        self.register_buffer("phi", phi)
        self.register_buffer("psi", psi)
        self.register_buffer("triangles", cage.triangles.clone())
        self.register_buffer("edges", cage.edges.clone())

    def forward(self, vertices: torch.Tensor) -> torch.Tensor:
        """Deformed points ``(*, N, D)`` for deformed cage vertices ``(*, V, D)``."""
        self._check_vertices(vertices, self.phi)
        faces = self.edges if self.dim == 2 else self.triangles
        return green_deformation(self.phi, self.psi, self.rest_vertices, vertices, faces)
