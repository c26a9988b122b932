"""The Green coordinates module: quasi-conformal, detail-preserving cage deformation."""

from __future__ import annotations

import warnings
from collections.abc import Callable

import torch

from torchcage._core.module import CageModule, detached, module_points
from torchcage.cage import Cage
from torchcage.errors import OutsideCageWarning, warn_outside
from torchcage.families.green.api import green_coordinates
from torchcage.families.green.deformation import green_deformation
from torchcage.families.green.derivatives import green_derivatives
from torchcage.families.green.exterior import extend_outside
from torchcage.families.green.stretch import (
    conformal_stretch,
    stretched_normals,
    stretched_triangle_normals,
    triangle_frames,
)

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


# The stretch helpers live in families/green/stretch.py; they are re-exported here for existing imports.
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
        store_derivatives: 0 (default), 1 or 2: also store the coordinates' gradients with respect
            to the points (buffers ``phi_gradients`` ``(N, V, D)``, ``psi_gradients`` ``(N, T, D)``)
            and, for 2, their Hessians (``phi_hessians``, ``psi_hessians``), so that
            :meth:`jacobian` / :meth:`hessian` of every pose cost a matrix product. Otherwise they
            are computed (:func:`torchcage.functional.green_derivatives`) on each call.

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
        >>> J = gc.jacobian(3 * cage.vertices + 1)  # deformation gradient at every point
        >>> torch.allclose(J, 3 * torch.eye(3, dtype=torch.float64).expand(50, 3, 3))
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
        store_derivatives: int = 0,
    ) -> None:
        if store_derivatives not in (0, 1, 2):
            raise ValueError(f"store_derivatives must be 0, 1 or 2, got {store_derivatives}")
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
        self.exterior = exterior
        stored = self._compute_derivatives(store_derivatives, dtype) if store_derivatives else (None,) * 4
        for name, t in zip(("phi_gradients", "psi_gradients", "phi_hessians", "psi_hessians"), stored, strict=True):
            self.register_buffer(name, t)

    def _compute_derivatives(self, order: int, dtype: torch.dtype) -> tuple[torch.Tensor | None, ...]:
        """``(grad_phi (*B, N, V, D), grad_psi (*B, N, T, D), hess_phi, hess_psi)`` at the points
        (Hessians None for ``order=1``), from the rest cage, one batch element at a time."""
        faces = self.edges if self.dim == 2 else self.triangles
        rest = Cage._from_faces(self.rest_vertices.to(torch.float64), faces)
        cages = rest.unbind() if rest.is_batched else [rest]
        pts = self.points.expand(*self.batch_shape, *self.points.shape[-2:]).reshape(len(cages), self.num_points, -1)
        parts = [green_derivatives(pts[b], c, order, exterior=self.exterior)[2:] for b, c in enumerate(cages)]
        out = [
            torch.stack(list(col)).reshape(*self.batch_shape, *col[0].shape).to(dtype)
            for col in zip(*parts, strict=True)
        ]
        return (*out, None, None) if order == 1 else tuple(out)

    def _derivatives(self, order: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """The stored gradients (order 1) or Hessians (order 2) of ``phi`` and ``psi``, else computed."""
        stored = (self.phi_gradients, self.psi_gradients) if order == 1 else (self.phi_hessians, self.psi_hessians)
        if stored[0] is None:
            stored = self._compute_derivatives(order, torch.float64)[2 * (order - 1) : 2 * order]
        return stored[0].to(dtype), stored[1].to(dtype)

    def _stretched_normals(self, vertices: torch.Tensor) -> torch.Tensor:
        """``s_t n'_t`` ``(*, T, D)``: the deformed faces' normals scaled by their stretch factors."""
        if self.dim == 2:
            return stretched_normals(self.rest_vertices, vertices, self.edges)
        return stretched_triangle_normals(self.rest_vertices, vertices, self.triangles)

    def jacobian(self, vertices: torch.Tensor) -> torch.Tensor:
        """Jacobian of the deformation at the embedded points, ``J[..., n, a, c] = d y_a / d x_c``:
        ``(*, N, D, D)`` for deformed vertices ``(*, V, D)``; differentiable with respect to them.

        The deformation is ``y = sum_i phi_i(x) v'_i + sum_t psi_t(x) s_t n'_t`` with the stretch
        factors and normals functions of the cage alone, so ``J = sum_i v'_i grad phi_i^T + sum_t
        s_t n'_t grad psi_t^T`` is exact (the closed-form gradients inside the cage; outside, the
        derivative of the exterior extension). The identity at rest; a similarity's rotation times
        its scale.
        """
        self._check_vertices(vertices, self.phi)
        gp, gs = self._derivatives(1, vertices.dtype)
        sn = self._stretched_normals(vertices)
        return torch.einsum("...nvc,...va->...nac", gp, vertices) + torch.einsum("...ntc,...ta->...nac", gs, sn)

    def hessian(self, vertices: torch.Tensor) -> torch.Tensor:
        """Hessian of the deformation at the embedded points, ``H[..., n, a, c, d] =
        d^2 y_a / d x_c d x_d``: ``(*, N, D, D, D)`` for deformed vertices ``(*, V, D)``;
        differentiable with respect to them. Zero (to rounding) for similarities of the cage."""
        self._check_vertices(vertices, self.phi)
        hp, hs = self._derivatives(2, vertices.dtype)
        sn = self._stretched_normals(vertices)
        return torch.einsum("...nvcd,...va->...nacd", hp, vertices) + torch.einsum("...ntcd,...ta->...nacd", hs, sn)

    def forward(self, vertices: torch.Tensor) -> torch.Tensor:
        """Deformed points ``(*, N, D)`` for deformed cage vertices ``(*, V, D)``."""
        self._check_vertices(vertices, self.phi)
        faces = self.edges if self.dim == 2 else self.triangles
        return green_deformation(self.phi, self.psi, self.rest_vertices, vertices, faces)
