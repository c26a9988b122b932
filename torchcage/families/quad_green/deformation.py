"""Quad Green deformation: coordinates and a deformed triquad cage to deformed points, with the
per-corner correction factors of quads (the module's ``forward`` and :func:`torchcage.deform`)."""

from __future__ import annotations

import torch

from torchcage._core.common import safe_norm
from torchcage.families.green.stretch import conformal_stretch, stretched_triangle_normals
from torchcage.families.quad_green.kernel import corner_normals

__all__ = ["quad_corner_factors", "quad_green_deformation"]

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


def quad_green_deformation(
    phi: torch.Tensor,
    psi: torch.Tensor,
    rest: torch.Tensor,
    deformed: torch.Tensor,
    triangles: torch.Tensor,
    quads: torch.Tensor,
    correction: str = "conformal",
) -> torch.Tensor:
    """Quad Green deformation: ``phi @ V' + psi[:T] @ (s_t n'_t) + sum psi[T+4q+k] sigma_qk N'_qk``.

    Args:
        phi: ``(*B, N, V)``; psi: ``(*B, N, T + 4Q)``.
        rest: ``(*B, V, 3)``; deformed: ``(*, *B, V, 3)``.
        triangles: ``(T, 3)``; quads: ``(Q, 4)``.
        correction: ``"conformal"`` (corner factors, Eq. 22) or ``"area"`` (factors 1).

    Returns:
        ``(*, *B, N, 3)`` deformed points.
    """
    dt = deformed.dtype
    T = triangles.shape[0]
    out = torch.matmul(phi.to(dt), deformed)
    if T:
        sn = stretched_triangle_normals(rest, deformed, triangles)
        out = out + torch.matmul(psi[..., :T].to(dt), sn)
    if quads.shape[0]:
        q1 = deformed[..., quads, :]  # (*, Q, 4, 3)
        N1 = corner_normals(q1)
        if correction == "conformal":
            N1 = quad_corner_factors(rest[..., quads, :], q1)[..., None] * N1
        out = out + torch.matmul(psi[..., T:].to(dt), N1.flatten(-3, -2))
    return out
