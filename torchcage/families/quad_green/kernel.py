r"""Torch kernel of Green coordinates for triquad cages (QGC; Thiery and Boubekeur 2022).

Each quad ``q`` contributes to its corners' ``phi`` and has four normal coordinates ``psi_k``
multiplying its unnormalised corner normals ``N_k = (q_{k+1} - q_k) x (q_{k+3} - q_k)``. The eight
unknowns ``Phi = (phi_0..3, psi_0..3)`` of a point obey four linear equations (Eqs. 13-16)

.. math::
    \sum_k \phi_k q_k + \psi_k N_k = \sum_{t} \Big(\sum_j \phi^t_j t_j + \psi^t n_t\Big),\qquad
    \sum_k \phi_k = \sum_t \sum_j \phi^t_j,

whose right-hand sides are invariants of the quad's boundary (the flux of divergence-free fields):
they are computed exactly with triangle Green coordinates on any tessellation the point does not
cross; torchcage uses the fan of four triangles from the point's projection onto the sheet (the
projection operator of QMVC) to the quad's edges. ``A_q`` depends on the rest quad only: its
pseudo-inverse and an orthonormal basis ``kappa_1..4`` of its null space are computed once. The
null-space part is estimated by the adaptive Riemann sum of Algorithm 1 (a ``(2K+1)^2`` grid,
``K = n + 1``, concentrated around the projection with Eq. 19, ``m = 3``, tiled by ``4 K^2``
triangles), on whose sub-triangles the triangle Green integrals give ``omega_t`` and ``psi_t``
(Eqs. 17-18), with the norm correction of QMVC: ``lambda_i = (Phi~ . kappa_i) |Phi_bar|^2 /
(Phi~ . Phi_bar)``. Linear precision is exact by construction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcage._core.common import records_graph, safe_norm
from torchcage._core.quad_quadrature import quad_integrals
from torchcage.families.green.kernel3d import triangle_green_geometry, triangle_integrals
from torchcage.families.mean_value.kernel3d import _cross
from torchcage.families.quad_mean_value.kernel import Projection, QuadData, Vec, project, quad_data


@dataclass(frozen=True)
class QuadGreenData:
    """Per-quad constants (Q quads) in the compute dtype."""

    quads: torch.Tensor  # (Q, 4)
    origin: torch.Tensor  # (3,) the cage's centre: A_q is built on corners relative to it
    pinv: torch.Tensor  # (Q, 8, 4) pseudo-inverse of A_q
    null: torch.Tensor  # (Q, 8, 4) orthonormal basis of A_q's null space (columns), detached
    null_proj: torch.Tensor | None  # (Q, 8, 8) projector onto the null space, when differentiated
    proj: QuadData  # the projection operator's constants
    pattern: torch.Tensor  # (P, 3, 2) sub-triangles of the Riemann sum as (u index, v index)
    K: int
    tol: float


def corner_normals(p: torch.Tensor) -> torch.Tensor:
    """``N_k = (q_{k+1} - q_k) x (q_{k+3} - q_k)`` of quads ``(..., 4, 3)`` -> ``(..., 4, 3)``."""
    return torch.linalg.cross(p.roll(-1, dims=-2) - p, p.roll(1, dims=-2) - p, dim=-1)


def tessellation_pattern(K: int) -> torch.Tensor:
    """Algorithm 1's tiling of a ``(2K+1) x (2K+1)`` grid of nodes by ``4 K^2`` triangles in
    concentric rings around the middle node, as ``(P, 3, 2)`` (u index, v index), counter-clockwise
    in the (u, v) plane."""
    N = 2 * K
    tris = []

    def proc(u1: int, u2: int, u3: int, v1: int, v2: int, v3: int) -> None:
        tris.append([(u1, v1), (u2, v2), (u3, v3)])

    for vi in range(K):
        for ui in range(vi, N - 1 - vi):
            if (ui + vi) % 2 == 0:
                proc(ui, ui + 2, ui + 1, vi, vi, vi + 1)
                proc(ui, ui + 1, ui + 2, N - vi, N - vi - 1, N - vi)
                proc(vi, vi + 1, vi, ui, ui + 1, ui + 2)
                proc(N - vi, N - vi, N - vi - 1, ui, ui + 2, ui + 1)
            else:
                proc(ui, ui + 1, ui + 2, vi + 1, vi, vi + 1)
                proc(ui, ui + 2, ui + 1, N - vi - 1, N - vi - 1, N - vi)
                proc(vi + 1, vi + 1, vi, ui, ui + 2, ui + 1)
                proc(N - vi - 1, N - vi, N - vi - 1, ui, ui + 1, ui + 2)
    t = torch.tensor(tris, dtype=torch.long)
    # Orient every triangle counter-clockwise in index space (the node maps are monotone).
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    flip = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] < 0
    t[flip] = t[flip][:, [0, 2, 1]]
    return t


def grid_nodes(t: torch.Tensor, K: int, m: int = 3) -> torch.Tensor:
    """Eq. 19: ``2K + 1`` nodes in [0, 1] concentrated around ``t`` ``(...)`` -> ``(..., 2K+1)``."""
    i = torch.arange(2 * K + 1, dtype=t.dtype, device=t.device)
    t_ = t[..., None]
    below = (1 - ((K - i) / K).clamp_min(0) ** m) * t_
    above = (t_ - 1) * (1 - ((i - K) / K).clamp_min(0) ** m) + 1
    return torch.where(i < K, below, torch.where(i > K, above, t_))


def quad_systems(vertices: torch.Tensor, quads: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Each quad's linear system ``A_q`` ``(*B, Q, 4, 8)`` (its corners relative to ``origin``, the
    middle of the cage's bounding box, then its corner normals, over a row of ones), the least-norm
    solution's pseudo-inverse ``(*B, Q, 8, 4)`` and a null-space basis ``(*B, Q, 8, 4)`` (columns),
    from the SVD of ``A_q`` (no graph); for vertices ``(*B, V, 3)`` (one cage, or a batch with one
    topology: element by element the same numbers).

    Returns:
        ``(origin (*B, 3), A, pinv, null)``.
    """
    origin = (vertices.amax(dim=-2) + vertices.amin(dim=-2)) / 2
    p = vertices[..., quads, :] - origin[..., None, None, :]  # (*B, Q, 4, 3)
    A = torch.zeros(*p.shape[:-2], 4, 8, dtype=vertices.dtype, device=vertices.device)
    A[..., :3, :4] = p.transpose(-1, -2)
    A[..., :3, 4:] = corner_normals(p).transpose(-1, -2)
    A[..., 3, :4] = 1.0
    U, S, Vh = torch.linalg.svd(A.detach(), full_matrices=True)
    pinv = Vh[..., :4, :].transpose(-1, -2) @ (U.transpose(-1, -2) / S[..., None])
    null = Vh[..., 4:, :].transpose(-1, -2)
    return origin, A, pinv, null


def quad_green_data(vertices: torch.Tensor, quads: torch.Tensor, tol: float, n: int) -> QuadGreenData:
    """Constants of the quads ``(Q, 4)`` of a cage with vertices ``(V, 3)``."""
    origin, A, pinv, null = quad_systems(vertices, quads)
    null_proj = None
    if records_graph(A):
        # The null-space basis is not unique (the SVD's backward is NaN there): differentiate the
        # unique objects instead, A^+ = A^T (A A^T)^-1 and the projector I - A^+ A onto the null
        # space, with the SVD's values and the closed forms' derivatives.
        At = A.transpose(1, 2)
        pinv_f = At @ torch.linalg.inv(A @ At)
        proj_f = -pinv_f @ A
        pinv = pinv + (pinv_f - pinv_f.detach())
        null_proj = null @ null.transpose(1, 2) + (proj_f - proj_f.detach())
    K = n + 1
    return QuadGreenData(
        quads=quads,
        origin=origin,
        pinv=pinv,
        null=null,
        null_proj=null_proj,
        proj=quad_data(vertices, quads, tol),
        pattern=tessellation_pattern(K).to(vertices.device),
        K=K,
        tol=tol,
    )


def _sheet(p0: Vec, b: Vec, c: Vec, dd: Vec, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Points of the sheet minus the point, ``xi(u, v) - x``, stacked on a last axis of 3."""
    return torch.stack([p0[i] + u * b[i] + v * c[i] + u * v * dd[i] for i in range(3)], dim=-1)


def _bilinear(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return torch.stack([(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v], dim=-1)


#: Where the projection lies within this fraction of the quad's parameter range from an edge, the
#: fan's apex moves along the projection's ruling to this distance from the edge (or to the
#: distance of the nearest perpendicular edge, if smaller).
FAN_APEX_BAND = 0.25


def fan_apex(
    u: torch.Tensor, v: torch.Tensor, on: torch.Tensor, band: float = FAN_APEX_BAND
) -> tuple[torch.Tensor, torch.Tensor]:
    """The parameters ``(u', v')`` of the fan's apex for projections ``(u, v)`` (any shape).

    The fan from the projection to the quad's edges has a sliver over an edge the projection is
    near: its plane is known only to ``eps |x - q| / width``, and a point near that edge sees it
    from close by (partition of unity lost ``1e-18 / distance``). The sheet is ruled: ``xi(u, t)``
    is a straight line in ``t`` (and ``xi(t, v)`` in ``t``), so the apex can move along the ruling
    through the projection, away from the nearest edge: the fan triangle over that edge still holds
    the projection (the segment from the edge to the apex is that ruling), its plane is the sheet's
    tangent plane along the ruling's foot, and it is no longer thin. The move stops at ``band`` or at
    the distance of the nearest perpendicular edge, so near a corner the fan stays as it was, and
    it is continuous in ``(u, v)`` (the two moves agree where the nearest edge changes). Points on
    the quad keep the projection as apex (their principal values drop the empty triangle)."""
    mu, mv = torch.minimum(u, 1 - u), torch.minimum(v, 1 - v)
    tv = mu.clamp(max=band)
    tu = mv.clamp(max=band)
    v_new = torch.where(v <= 0.5, torch.maximum(v, tv), torch.minimum(v, 1 - tv))
    u_new = torch.where(u <= 0.5, torch.maximum(u, tu), torch.minimum(u, 1 - tu))
    along_u = mv <= mu  # nearest edge v = 0 or 1: move v along the u-ruling
    ua = torch.where(on | along_u, u, u_new)
    va = torch.where(on | ~along_u, v, v_new)
    return ua, va


def qgc3d_chunk(
    x: torch.Tensor, data: QuadGreenData, quad_tol: float | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-quad Green coordinates of a chunk of points.

    Args:
        x: ``(m, 3)`` points.
        data: the quads' constants.
        quad_tol: if given, the null-space part from the defining integrals to this relative tolerance
            (:mod:`torchcage._core.quad_quadrature`): ``Phi = Phi_bar + sum_i (Omega . kappa_i) kappa_i``, the
            orthogonal projection of the integrals onto the solutions of the invariants (no norm
            correction, which serves the Riemann sum's bias).

    Returns:
        ``(Phi (Q, m, 8), on (Q, m), hat (Q, m, 4))``: each quad's ``(phi_0..3, psi_0..3)`` for
        every point (principal values for points on the quad), whether the point lies on the quad,
        and the bilinear coordinates of its projection.
    """
    pr = project(x, data.proj)
    p0, b, c, dd, u, v = pr.p[0], pr.b, pr.c, pr.dd, pr.u, pr.v
    tol = data.tol
    # --- Invariants (right-hand side) on the fan from the projection to the edges. ---
    # The fan's geometry (normals, edge directions) from the corners themselves: a quad edge then
    # has the same bits as in the neighbouring quad's fan or triangle face (cage data), so near the
    # edge the two see the point on consistent sides; its corners relative to the point are those
    # of the projection (corner - x).
    ua, va = fan_apex(u, v, pr.on, FAN_APEX_BAND)
    ring = data.proj.corners[..., 0].permute(2, 1, 0)  # (Q, 4, 3)
    apex = torch.einsum("qmk,qkc->qmc", _bilinear(ua, va), ring)  # (Q, m, 3)
    ring = ring[:, None].expand(-1, x.shape[0], -1, -1)  # (Q, m, 4, 3)
    fan_abs = torch.stack(
        [torch.stack([ring[..., k, :], ring[..., (k + 1) % 4, :], apex], dim=-2) for k in range(4)], dim=-3
    )  # (Q, m, 4 triangles, 3 corners, 3)
    frame = triangle_green_geometry(fan_abs)
    fan = fan_abs - x[None, :, None, None, :]
    phi_f, psi_f, _, _, _ = triangle_integrals(fan, frame, tol)
    # The apex on a quad edge (a point on the quad's boundary): that fan triangle is empty, up to
    # rounding that would make it a sliver seen from its own edge (garbage solid angle): drop it.
    base = safe_norm(fan[..., 1, :] - fan[..., 0, :])
    live = frame[1] > tol * base  # (Q, m, 4)
    phi_f, psi_f = torch.where(live[..., None], phi_f, 0.0), torch.where(live, psi_f, 0.0)
    normal_f = frame[0]
    rhs_pos = (phi_f[..., None] * (fan_abs - data.origin)).sum(dim=(-2, -3)) + (psi_f[..., None] * normal_f).sum(dim=-2)
    rhs = torch.cat([rhs_pos, phi_f.sum(dim=(-1, -2))[..., None]], dim=-1)  # (Q, m, 4)
    phi_bar = torch.einsum("qij,qmj->qmi", data.pinv, rhs)  # (Q, m, 8)

    if quad_tol is not None:
        shape = u.shape
        flat_vec = [tuple(t.expand(shape).reshape(-1) for t in vec) for vec in (p0, b, c, dd)]
        # (on the quad too: both integrands are O(1 / r) there, the principal value is the integral)
        om = quad_integrals(*flat_vec, u.reshape(-1), v.reshape(-1), quad_tol, green=True, on=pr.on.reshape(-1))  # type: ignore[arg-type]
        est = (om / (4 * math.pi)).T.reshape(*shape, 8)
        return _null_space_part(data, pr, phi_bar, est, exact=True)
    # --- Riemann estimate of the null-space part (Algorithm 1). ---
    K = data.K
    un, vn = grid_nodes(u, K), grid_nodes(v, K)  # (Q, m, 2K+1)
    pat = data.pattern  # (P, 3, 2)
    uu, vv = un[..., pat[..., 0]], vn[..., pat[..., 1]]  # (Q, m, P, 3)
    sub = _sheet(*(tuple(t[..., None, None] for t in vec) for vec in (p0, b, c, dd)), uu, vv)  # (Q, m, P, 3, 3)
    _, psi_t, omega_t, _, _ = triangle_integrals(sub, triangle_green_geometry(sub), tol, thin=False)
    uc, vc = uu.mean(-1), vv.mean(-1)  # sub-triangle centres (Q, m, P)
    bc = _bilinear(uc, vc)  # (Q, m, P, 4)
    N0, Nu, Nv = _cross(b, c), _cross(b, dd), _cross(dd, c)
    Nc = torch.stack([N0[i][..., None] + uc * Nu[i][..., None] + vc * Nv[i][..., None] for i in range(3)], dim=-1)
    Nn = safe_norm(Nc)
    est_phi = (bc * (omega_t / (4 * math.pi))[..., None]).sum(dim=-2)
    est_psi = (bc * torch.where(Nn > 0, psi_t / torch.where(Nn > 0, Nn, 1.0), 0.0)[..., None]).sum(dim=-2)
    est = torch.cat([est_phi, est_psi], dim=-1)  # (Q, m, 8)

    return _null_space_part(data, pr, phi_bar, est, exact=False)


def _null_space_part(
    data: QuadGreenData, pr: Projection, phi_bar: torch.Tensor, est: torch.Tensor, exact: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``Phi = Phi_bar + sum_i lambda_i kappa_i`` from the estimate ``est`` ``(Q, m, 8)`` of the
    integrals: ``lambda_i = est . kappa_i``, with the norm correction unless ``exact``; and the
    outputs of :func:`qgc3d_chunk`."""
    if exact:
        scale = torch.ones_like(est[..., 0])
    else:
        eb = (est * phi_bar).sum(-1)
        bb = (phi_bar * phi_bar).sum(-1)
        ok = eb != 0
        scale = torch.where(ok, bb / torch.where(ok, eb, 1.0), 0.0)
    if data.null_proj is None:
        coef = torch.einsum("qji,qmj->qmi", data.null, est)  # est . kappa_i
        Phi = phi_bar + torch.einsum("qij,qmj->qmi", data.null, coef * scale[..., None])
    else:
        Phi = phi_bar + torch.einsum("qij,qmj->qmi", data.null_proj, est) * scale[..., None]
    hat = _bilinear(pr.u, pr.v)
    corner = torch.nn.functional.one_hot(pr.vertex.clamp_min(0), 4).to(hat.dtype)
    return Phi, pr.on, torch.where((pr.vertex >= 0)[..., None], corner, hat)
