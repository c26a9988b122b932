r"""Stretch factors and stretched normals of deformed cages (the Neumann terms of Green deformations).

Lipman's stretch factor of a triangle is the root mean square of the two singular values of the
linear map ``J`` taking the rest triangle's tangent pair ``(u0, v0)`` to the deformed pair
``(u1, v1)``: :math:`s = \lVert J \rVert_F / \sqrt 2`. The published closed form,
``sqrt(|u1|^2 |v0|^2 - 2 (u1.v1)(u0.v0) + |v1|^2 |u0|^2) / (sqrt 2 |u0 x v0|)``, is a difference of
products that cancels completely on sliver triangles (at rest it computes ``2 |u0 x v0|^2`` as
``2 (|u0|^2 |v0|^2 - (u0.v0)^2)``) and can come out negative. Here ``J`` is applied to an
orthonormal frame of the rest triangle (``e1 = u0 / a``, ``e2`` the in-plane normal to it, with
``u0 = a e1`` and ``v0 = b e1 + c e2``):

.. math::
    \lVert J \rVert_F^2 = \frac{|u_1|^2}{a^2} + \frac{|v_1 - (b/a)\, u_1|^2}{c^2},

a sum of squares: never negative, 0 only when the deformed triangle collapses to a point.

Derivatives are finite everywhere: where ``s = 0`` (a deformed triangle collapsed to a point, or a
rest triangle of zero area, which contributes nothing) the stretch's derivative is taken as 0 (a
subgradient of the norm), and the normal of a collapsed deformed triangle as 0 with derivative 0.
"""

from __future__ import annotations

import torch

from torchcage._core.common import safe_norm, safe_sqrt

__all__ = ["conformal_stretch", "stretched_normals", "stretched_triangle_normals", "triangle_frames", "unit_normal"]


def unit_normal(v: torch.Tensor) -> torch.Tensor:
    """``v / |v|`` over the last dimension, ``0`` (with derivative 0) where ``v = 0``."""
    n = safe_norm(v, keepdim=True)
    return torch.where(n > 0, v / torch.where(n > 0, n, 1.0), 0.0)


def stretched_normals(rest: torch.Tensor, deformed: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Outward edge normals of a deformed polygon scaled by the edge stretch ``|a'| / |a|``
    (the 2D Green deformation's ``s_j n'_j``), differentiable in ``deformed``.

    Args:
        rest: ``(V, 2)`` rest vertices (or ``(*B, V, 2)``, broadcast with ``deformed``).
        deformed: ``(*, V, 2)`` deformed vertices.
        edges: ``(E, 2)`` counter-clockwise edges.

    Returns:
        ``(*, E, 2)``.

    Examples:
        >>> import torch
        >>> sq = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
        >>> e = torch.tensor([[0, 1], [1, 2], [2, 3], [3, 0]])
        >>> stretched_normals(sq, 2 * sq, e)[0]
        tensor([ 0., -2.])
    """
    a0 = rest[..., edges[:, 1], :] - rest[..., edges[:, 0], :]
    a1 = deformed[..., edges[:, 1], :] - deformed[..., edges[:, 0], :]
    return torch.stack([a1[..., 1], -a1[..., 0]], dim=-1) / a0.norm(dim=-1).to(deformed.dtype)[..., None]


def triangle_frames(vertices: torch.Tensor, triangles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Edge vectors ``u = p1 - p0``, ``v = p2 - p0`` and unit normals (0 for a triangle collapsed
    to a segment or a point) of triangles, for vertices ``(*, V, 3)`` and triangles ``(T, 3)``:
    each ``(*, T, 3)``.

    Examples:
        >>> import torch
        >>> p = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        >>> triangle_frames(p, torch.tensor([[0, 1, 2]]))[2]
        tensor([[0., 0., 1.]])
    """
    p = vertices[..., triangles, :]  # (*, T, 3, 3)
    u, v = p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :]
    return u, v, unit_normal(torch.linalg.cross(u, v, dim=-1))


def conformal_stretch(u0: torch.Tensor, v0: torch.Tensor, u1: torch.Tensor, v1: torch.Tensor) -> torch.Tensor:
    """Lipman's stretch factor of the linear map taking the tangent pair ``(u0, v0)`` to ``(u1, v1)``
    (all ``(..., 3)``): the root mean square of its two singular values (``s`` for a similarity of
    scale ``s``), as a sum of squares (see the module docstring). A rest pair of zero area gets 0.

    Examples:
        >>> import torch
        >>> u0, v0 = torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.3, 1.0, 0.0])
        >>> R = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        >>> float(conformal_stretch(u0, v0, 2 * R @ u0, 2 * R @ v0))
        2.0
    """
    a = safe_norm(u0)
    ok = a > 0
    inv_a = torch.where(ok, 1.0 / torch.where(ok, a, 1.0), 0.0)
    b_over_a = (u0 * v0).sum(-1) * inv_a * inv_a
    c = safe_norm(torch.linalg.cross(u0, v0, dim=-1)) * inv_a  # the height of v0 over u0
    okc = c > 0
    inv_c = torch.where(okc, 1.0 / torch.where(okc, c, 1.0), 0.0)
    w = v1 - b_over_a[..., None] * u1
    frob2 = (u1 * u1).sum(-1) * (inv_a * inv_a) + (w * w).sum(-1) * (inv_c * inv_c)
    return torch.where(okc, safe_sqrt(0.5 * frob2), 0.0)


def stretched_triangle_normals(rest: torch.Tensor, deformed: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    """Unit outward normals of deformed triangles times Lipman's stretch factors (the 3D Green
    deformation's ``s_t n'_t``), ``(*, T, 3)`` for vertices ``(V, 3)`` / ``(*, V, 3)``.

    Examples:
        >>> import torch
        >>> p = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        >>> stretched_triangle_normals(p, 3 * p, torch.tensor([[0, 1, 2]]))
        tensor([[0., 0., 3.]])
    """
    u0, v0, _ = triangle_frames(rest.to(deformed.dtype), triangles)
    u1, v1, n1 = triangle_frames(deformed, triangles)
    return conformal_stretch(u0, v0, u1, v1)[..., None] * n1
