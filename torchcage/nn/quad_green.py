"""The Green coordinates module for triquad cages."""

from __future__ import annotations

import torch

from ..cage import Cage
from ..errors import warn_outside
from ..functional._common import safe_norm
from ..functional._qgc3d import corner_normals
from ..functional._stretch import conformal_stretch, stretched_triangle_normals
from ..functional.quad_green import quad_green_coordinates
from .base import CageModule, module_points

__all__ = ["QuadGreenCoordinates", "quad_corner_factors"]

#: The regular (u, v) pattern of Eq. 22's averages: 5 x 5 cell centres.
_PATTERN = (torch.arange(5, dtype=torch.float64) + 0.5) / 5


def quad_corner_factors(rest: torch.Tensor, deformed: torch.Tensor) -> torch.Tensor:
    """Per-corner correction factors of quads (Thiery and Boubekeur 2022, Eq. 22):
    ``sigma_k = sum_s b_k(s) sigma_L(s) |N(s)| / sum_s b_k(s) |N'(s)|`` over a 5 x 5 pattern of the
    (u, v) square, ``sigma_L`` Lipman's stretch of the sheet's tangent map and ``N`` (``N'``) the
    rest (deformed) sheet normal. For a similarity of scale ``s`` every factor is ``1 / s``, so that
    ``sigma_k N'_k`` is ``s R N_k``. A quad collapsed to zero area gets factors 0 (its corner
    normals are zero anyway).

    Args:
        rest: ``(Q, 4, 3)`` rest quad corners.
        deformed: ``(*, Q, 4, 3)`` deformed quad corners.

    Returns:
        ``(*, Q, 4)``.
    """
    t = _PATTERN.to(deformed)
    u, v = (g.reshape(-1) for g in torch.meshgrid(t, t, indexing="ij"))  # (S,)
    b = torch.stack([(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v], dim=-1)  # (S, 4)

    def tangents(q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        q0, q1, q2, q3 = (q[..., None, i, :] for i in range(4))  # (*, Q, 1, 3)
        du = (1 - v)[:, None] * (q1 - q0) + v[:, None] * (q2 - q3)
        dv = (1 - u)[:, None] * (q3 - q0) + u[:, None] * (q2 - q1)
        return du, dv  # (*, Q, S, 3)

    du0, dv0 = tangents(rest.to(deformed.dtype))
    du1, dv1 = tangents(deformed)
    area0 = safe_norm(torch.linalg.cross(du0, dv0, dim=-1))
    area1 = safe_norm(torch.linalg.cross(du1, dv1, dim=-1))
    num = torch.einsum("...s,sk->...k", conformal_stretch(du0, dv0, du1, dv1) * area0, b)
    den = torch.einsum("...s,sk->...k", area1, b)
    return torch.where(den > 0, num / torch.where(den > 0, den, 1.0), 0.0)


class QuadGreenCoordinates(CageModule):
    """Deform points inside a triquad cage with Green coordinates for triquad cages (QGC).

    Quads stay bilinear patches (no triangulation, so symmetric edits stay symmetric) and the
    deformation is quasi-conformal like triangle Green coordinates. ``phi`` ``(N, V)`` and ``psi``
    ``(N, T + 4Q)`` are computed once at rest (buffers). ``forward`` returns
    ``phi @ V' + psi[:, :T] @ (s_t n'_t) + sum_{q,k} psi[:, T+4q+k] sigma_{q,k} N'_{q,k}`` with
    Lipman's stretch ``s_t`` on triangles, the deformed corner normals ``N'_{q,k}`` and the
    per-corner factors ``sigma`` (Eq. 23), all differentiable with respect to the deformed vertices.

    Args:
        cage: a closed 3D cage of triangles and/or valid quads.
        points: ``(N, 3)`` points inside the cage (points outside it warn with their count
            (:class:`torchcage.OutsideCageWarning`)).
        n: tessellation parameter of the coordinates (see
            :func:`torchcage.functional.quad_green_coordinates`).
        correction: ``"conformal"`` (default): the corner factors of Eq. 22, which mimic Lipman's
            stretch; rotations, uniform scalings and translations are reproduced. ``"area"``: the
            area-based Neumann condition (factors 1): rigid motions are reproduced, scalings not.
        chunk_size: points per chunk while computing the coordinates.
        dtype: dtype of the stored coordinates (float64 by default).
        allow_invalid: compute even if some quads fail the validity predicate (with a warning).

    Shape:
        - Input: ``(*, V, 3)`` deformed cage vertices.
        - Output: ``(*, N, 3)`` deformed points.

    Example:
        >>> import torch, torchcage
        >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj"))
        >>> pts = torch.rand(20, 3, dtype=torch.float64) * 1.6 - 0.8
        >>> qgc = torchcage.QuadGreenCoordinates(cage, pts)
        >>> torch.allclose(qgc(cage.vertices), pts)
        True
        >>> torch.allclose(qgc(2 * cage.vertices + 1), 2 * pts + 1)
        True
    """

    phi: torch.Tensor
    psi: torch.Tensor
    triangles: torch.Tensor
    quads: torch.Tensor

    def __init__(
        self,
        cage: Cage,
        points: torch.Tensor,
        n: int = 2,
        *,
        correction: str = "conformal",
        chunk_size: int | None = None,
        dtype: torch.dtype = torch.float64,
        allow_invalid: bool = False,
    ) -> None:
        if correction not in ("conformal", "area"):
            raise ValueError(f"correction must be 'conformal' or 'area', got {correction!r}")
        pts = module_points(points, cage).detach()
        phi, psi = quad_green_coordinates(pts, cage, n, chunk_size=chunk_size, dtype=dtype, allow_invalid=allow_invalid)
        super().__init__(cage, pts)
        self.correction = correction
        warn_outside(phi.reshape(-1, cage.num_vertices).sum(dim=1), "quad Green coordinates")
        self.register_buffer("phi", phi.reshape(-1, cage.num_vertices))
        self.register_buffer("psi", psi.reshape(self.phi.shape[0], psi.shape[-1]))
        self.register_buffer("triangles", cage.triangles.clone())
        self.register_buffer("quads", cage.quads.clone())

    def forward(self, vertices: torch.Tensor) -> torch.Tensor:
        """Deformed points ``(*, N, 3)`` for deformed cage vertices ``(*, V, 3)``."""
        self._check_vertices(vertices, self.phi)
        dt = vertices.dtype
        T = self.triangles.shape[0]
        out = torch.matmul(self.phi.to(dt), vertices)
        if T:
            sn = stretched_triangle_normals(self.rest_vertices, vertices, self.triangles)
            out = out + torch.matmul(self.psi[:, :T].to(dt), sn)
        if self.quads.shape[0]:
            q1 = vertices[..., self.quads, :]  # (*, Q, 4, 3)
            N1 = corner_normals(q1)
            if self.correction == "conformal":
                N1 = quad_corner_factors(self.rest_vertices[self.quads], q1)[..., None] * N1
            out = out + torch.matmul(self.psi[:, T:].to(dt), N1.flatten(-3, -2))
        return out

    def extra_repr(self) -> str:
        return super().extra_repr() + f", correction={self.correction!r}"
