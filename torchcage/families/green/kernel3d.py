r"""Torch kernel of 3D Green coordinates (Lipman, Levin, Cohen-Or 2008) for closed triangle cages.

For :math:`\eta` inside the cage, Green's third identity applied to linear functions gives

.. math::
    \eta = \sum_i \phi_i(\eta)\, v_i + \sum_t \psi_t(\eta)\, n_t,\qquad
    \phi_i = \frac{1}{4\pi}\sum_{t \ni v_i} \int_t \Gamma_i \frac{h}{r^3}\, dA,\quad
    \psi_t = \frac{1}{4\pi}\int_t \frac{dA}{r},

with :math:`r = \|\xi - \eta\|`, :math:`h = (\xi - \eta) \cdot n_t` (constant on the face,
positive on the inner side) and :math:`\Gamma_i` the hat functions. Both integrals are written
here without any ratio that vanishes on the face's plane (the published evaluation divides by a
determinant that does). Writing :math:`\Gamma_i = \alpha_i + g_i \cdot (\rho - \rho_0)`, with
:math:`\alpha_i` the barycentric coordinates of the foot point :math:`\rho_0` of :math:`\eta` on
the plane and :math:`g_i` their in-plane gradients,

.. math::
    \int_t \Gamma_i \frac{h}{r^3} = \alpha_i \Omega_t + h\, g_i \cdot K,\quad
    K = \int_t \frac{\rho - \rho_0}{r^3} = -\sum_e \hat m_e I_e,\quad
    \int_t \frac{1}{r} = \sum_e d_e I_e - h\, \Omega_t,

where :math:`\Omega_t` is the signed solid angle (Van Oosterom–Strackee), :math:`\hat m_e` the
outward in-plane edge normals, :math:`d_e` the signed distances from the foot point to the edge
lines (positive inside) and :math:`I_e = \int_e dl / r` (an ``asinh`` difference, evaluated in the
form that does not cancel). The last two identities follow from the divergence theorem in the
plane: :math:`\nabla \cdot ((\rho - \rho_0)/r) = 1/r + h^2/r^3` and
:math:`\nabla (1/r) = -(\rho - \rho_0)/r^3`.

Points on the cage get the limit from inside: faces through the point contribute their principal
value (no solid angle) and the hat values :math:`\Gamma_i` enter with the weight
:math:`1 - \omega / 4\pi`, :math:`\omega` the solid angle the rest of the cage subtends (the jump of
the double layer potential: 1/2 on a face, more or less at edges and vertices). Outside the cage
the identity gives 0 instead of :math:`\eta`: Green coordinates are defined inside.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcage._core.common import log_ratio, on_cage_tolerance, records_graph, safe_atan2, safe_norm, triangle_geometry
from torchcage._core.thin_triangle import THIN_ASPECT, thin_pairs, thin_triangle_integrals
from torchcage.cage import Cage
from torchcage.families.green.far_triangle import far_nodes, far_pairs, far_triangle_integrals

#: Pairs with ``|h| < PERPENDICULAR_PLANE_RATIO * min R`` or ``min R < PERPENDICULAR_VERTEX_RATIO *
#: max R`` take their distances to the plane and the edge lines from the edges' perpendiculars
#: (the native kernel's fix-up set).
PERPENDICULAR_PLANE_RATIO = 0.01
PERPENDICULAR_VERTEX_RATIO = 1e-3


@dataclass(frozen=True)
class TriangleGreenData:
    """Per-face constants, compute dtype: ``(T, ...)``."""

    p: torch.Tensor  # (T, 3, 3) corners
    normal: torch.Tensor  # (T, 3) unit outward normals
    two_area: torch.Tensor  # (T,)
    edge_dir: torch.Tensor  # (T, 3, 3) unit direction of the edge opposite each corner, p_{i+1} -> p_{i+2}
    edge_out: torch.Tensor  # (T, 3, 3) outward in-plane unit normal of that edge
    grad_bary: torch.Tensor  # (T, 3, 3) in-plane gradient of each corner's hat function
    tri: torch.Tensor  # (T, 3) corners
    tol: float
    # The far-field rule (module _far_triangle); None: closed forms only (a caller's subset of faces)
    longest: torch.Tensor | None = None  # (T,) longest edges
    far_nodes: torch.Tensor | None = None  # (T, Q, 3)
    far_weights: torch.Tensor | None = None  # (T, Q), area included
    far_bary: torch.Tensor | None = None  # (Q, 3)


def triangle_green_data(cage: Cage, dtype: torch.dtype) -> TriangleGreenData:
    p, n, two_area = triangle_geometry(
        cage, dtype, "triangulate it with cage.triangulated() (quad Green coordinates are a separate system)"
    )
    _, _, edge_dir, edge_out, grad_bary = triangle_green_geometry(p)
    longest = (p.roll(-1, dims=1) - p).norm(dim=-1).amax(dim=1)
    nodes, weights, bary = far_nodes(p, two_area)
    tol = on_cage_tolerance(cage)
    return TriangleGreenData(
        p, n, two_area, edge_dir, edge_out, grad_bary, cage.triangles, tol, longest, nodes, weights, bary
    )


def batch_face_tables(
    vertices: torch.Tensor, tri: torch.Tensor
) -> tuple[tuple[torch.Tensor, ...], torch.Tensor, tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    """The per-face tables of a batch of cages with one topology, by one set of tensor operations
    (element by element those of :func:`triangle_green_data`): the native and Triton kernels'
    batched tables start from them.

    Args:
        vertices: ``(B, V, 3)`` vertices (centred), in the compute dtype.
        tri: ``(T, 3)`` the shared triangles, on the vertices' device.

    Returns:
        ``((normal, two_area, edge_dir, edge_out, grad_bary), longest, far)``: each ``(B, T, ...)``,
        the longest edges ``(B, T)`` and the far-field rule ``(nodes (B, T, Q, 3), weights (B, T,
        Q), bary (Q, 3))``.
    """
    p = vertices[:, tri]  # (B, T, 3, 3)
    cross = torch.linalg.cross(p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :], dim=-1)
    two_area = cross.norm(dim=-1)  # (as triangle_geometry)
    _, _, edge_dir, edge_out, grad_bary = triangle_green_geometry(p)
    longest = (p.roll(-1, dims=-2) - p).norm(dim=-1).amax(dim=-1)  # (as triangle_green_data)
    geometry = (cross / two_area[..., None], two_area, edge_dir, edge_out, grad_bary)
    return geometry, longest, far_nodes(p, two_area)


def triangle_green_geometry(p: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """``(normal (..., 3), two_area (...), edge_dir, edge_out, grad_bary (..., 3, 3))`` of triangles
    with corners ``p`` ``(..., 3, 3)``: unit normal, twice the area, and for the edge opposite each
    corner (``p_{i+1} -> p_{i+2}``) its unit direction, its outward in-plane unit normal and the
    in-plane gradient of the corner's hat function. Degenerate triangles get finite placeholders
    (normal (0, 0, 1), zero gradients) and ``two_area = 0``: callers weight them by their area."""
    E = p.roll(-2, dims=-2) - p.roll(-1, dims=-2)  # edge opposite corner i: p_{i+1} -> p_{i+2}
    ell = safe_norm(E, keepdim=True)
    # 2 A n = E_{i+1} x E_{i+2} for every i: take the two shorter edges (the cross product's
    # rounding is eps times the product of the lengths; a needle's two long edges would leave its
    # normal known to eps / width only).
    longest = ell[..., 0].argmax(dim=-1, keepdim=True)  # (..., 1)
    crosses = torch.linalg.cross(E.roll(-1, dims=-2), E.roll(-2, dims=-2), dim=-1)  # E_{i+1} x E_{i+2}
    cross = crosses.gather(-2, longest[..., None].expand(*longest.shape, 3)).squeeze(-2)
    two_area = safe_norm(cross)
    ok = two_area > 0
    n = torch.where(ok[..., None], cross / torch.where(ok, two_area, 1.0)[..., None], cross.new_tensor([0.0, 0.0, 1.0]))
    edge_dir = E / torch.where(ell > 0, ell, 1.0)
    edge_out = torch.linalg.cross(edge_dir, n[..., None, :].expand_as(edge_dir), dim=-1) * ok[..., None, None]
    grad_bary = -edge_out * (ell / torch.where(ok, two_area, 1.0)[..., None, None]) * ok[..., None, None]
    return n, two_area, edge_dir, edge_out, grad_bary


def _edge_integrals(a_j: torch.Tensor, a_k: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """``I = int_e dl / r`` along the edge from ``p_j`` to ``p_k`` (unit direction ``u``), with
    ``a = p - eta``: ``asinh(l_k / R0) - asinh(l_j / R0)``, evaluated as a ratio of sums that
    never cancel. Shapes ``(..., 3)`` -> ``(...)``."""
    l_j, l_k = (a_j * u).sum(-1), (a_k * u).sum(-1)
    R_j, R_k = safe_norm(a_j), safe_norm(a_k)
    # Ahead of the edge (l >= 0): log((R_k + l_k) / (R_j + l_j)); behind it: log((R_j - l_j) / (R_k - l_k));
    # straddling: (R_j + l_j) = R0^2 / (R_j - l_j) with R0^2 = R_j^2 - l_j^2 from the cross product.
    R0sq = torch.linalg.cross(a_j, u.expand_as(a_j), dim=-1).square().sum(-1)
    # Each form is evaluated where its arguments are positive and is 0 elsewhere (a point on the
    # edge, where I is infinite and its callers multiply it by 0), so every branch has finite
    # derivatives.
    ahead = log_ratio(R_k + l_k, R_j + l_j)
    behind = log_ratio(R_j - l_j, R_k - l_k)
    straddle = log_ratio((R_k + l_k) * (R_j - l_j), R0sq)
    return torch.where(l_j >= 0, ahead, torch.where(l_k <= 0, behind, straddle))


def _near_distances(aj, ak, R, normal, edge_dir, edge_out, near, h, d) -> tuple[torch.Tensor, torch.Tensor]:
    """``h`` ``(...)`` and ``d`` ``(..., 3)`` recomputed from the edges' perpendiculars for the pairs
    in ``near`` (near a face's plane or a corner): see :func:`triangle_integrals`."""
    shape = near.shape
    idx = torch.nonzero(near.reshape(-1)).squeeze(1)

    def pick(t: torch.Tensor, tail: int) -> torch.Tensor:
        t = t.expand(*shape, *t.shape[t.dim() - tail :])
        return t.reshape(-1, *t.shape[len(shape) :]).index_select(0, idx)

    Rs = pick(R, 1)
    w = _edge_perpendicular(pick(aj, 2), pick(ak, 2), Rs[:, [1, 2, 0]], Rs[:, [2, 0, 1]], pick(edge_dir, 2))
    h_e = (w * pick(normal, 1)[:, None, :]).sum(-1)  # (k, 3), each = h up to rounding
    hs = h_e.gather(-1, (w * w).sum(-1).argmin(-1, keepdim=True)).squeeze(-1)
    ds = (w * pick(edge_out, 2)).sum(-1)
    h = h.reshape(-1).index_put((idx,), hs).reshape(shape)
    d = d.reshape(-1, 3).index_put((idx,), ds).reshape(*shape, 3)
    return h, d


def _edge_perpendicular(aj: torch.Tensor, ak: torch.Tensor, Rj: torch.Tensor, Rk: torch.Tensor, u: torch.Tensor):
    """The perpendicular ``w`` ``(..., 3)`` from the point to the line of the edge ``p_j p_k`` (unit
    direction ``u``), from the nearer end (accurate near a vertex: its error is ``eps`` times the
    distance to that end), or from the midpoint when both are as near. The same bits whichever way
    a face runs along the edge: both faces of an edge see the point on consistent sides."""
    m = torch.where((Rj < Rk)[..., None], aj, torch.where((Rk < Rj)[..., None], ak, 0.5 * (aj + ak)))
    return m - (m * u).sum(-1, keepdim=True) * u


def _vos_solid_angle(a: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """Signed solid angle ``2 atan2(det, den)`` (Van Oosterom-Strackee) of triangles with corners
    ``a`` ``(..., 3, 3)`` relative to the point and their lengths ``R`` ``(..., 3)``; positive for
    points on the inner side (the sign convention of :func:`triangle_integrals`)."""
    a0, a1, a2 = a[..., 0, :], a[..., 1, :], a[..., 2, :]
    det = (a0 * torch.linalg.cross(a1, a2, dim=-1)).sum(-1)
    R0, R1, R2 = R[..., 0], R[..., 1], R[..., 2]
    den = R0 * R1 * R2 + (a0 * a1).sum(-1) * R2 + (a0 * a2).sum(-1) * R1 + (a1 * a2).sum(-1) * R0
    return 2.0 * safe_atan2(det, den)


def green3d_chunk(x: torch.Tensor, data: TriangleGreenData) -> tuple[torch.Tensor, ...]:
    """Per-face Green integrals of a chunk of points.

    Args:
        x: ``(n, 3)`` points.
        data: the cage constants.

    Returns:
        ``(phi_face (n, T, 3), psi (n, T), omega (n, T), on_face (n, T), alpha (n, T, 3))``: each
        face's contribution to its corners' ``phi``, ``psi``, the solid angles, whether the point
        lies on the face, and the barycentric coordinates of its foot point. Faces seen from far
        (:mod:`.far_triangle`) take the quadrature rule.
    """
    a = data.p[None] - x[:, None, None, :]  # (n, T, 3 corners, 3)
    geometry = (data.normal[None], data.two_area[None], data.edge_dir[None], data.edge_out[None], data.grad_bary[None])
    extras: dict = {}
    phi_face, psi, omega, on_face, alpha = triangle_integrals(a, geometry, data.tol, extras=extras)
    phi_face, psi, omega, _ = put_far(x, a, data, phi_face, psi, omega, extras)
    return phi_face, psi, omega, on_face, alpha


def put_far(
    x: torch.Tensor, a: torch.Tensor, data: TriangleGreenData, phi_face, psi, omega, extras: dict
) -> tuple[torch.Tensor, ...]:
    """The closed forms' ``phi_face (n, T, 3)``, ``psi``, ``omega`` ``(n, T)`` and ``extras["K"]``
    ``(n, T, 3)`` with the pairs seen from far replaced by :func:`._far_triangle.far_triangle_integrals`
    (differentiable); ``x`` ``(n, 3)``, ``a`` ``(n, T, 3, 3)`` the corners minus the points.
    ``extras`` is updated in place (``"K"``, and ``"far"``: the far pairs ``(n, T)``, or None).
    Returns ``(phi_face, psi, omega, far)``."""
    extras["far"] = None
    if data.far_nodes is None or data.longest is None:
        return phi_face, psi, omega, None
    far = far_pairs(extras["R"], data.longest)
    if not bool(far.any()):
        return phi_face, psi, omega, None
    pt, ft = torch.nonzero(far, as_tuple=True)
    h = (a[pt, ft, 0] * data.normal[ft]).sum(-1)
    pf, ps, om, K = far_triangle_integrals(
        x[pt], data.far_nodes[ft], data.far_weights[ft], data.far_bary, data.normal[ft], h
    )
    extras["far"] = far
    if records_graph(a, phi_face, psi, omega, extras["K"], pf):
        extras["K"] = extras["K"].index_put((pt, ft), K)
        return phi_face.index_put((pt, ft), pf), psi.index_put((pt, ft), ps), omega.index_put((pt, ft), om), far
    for t, v in ((phi_face, pf), (psi, ps), (omega, om), (extras["K"], K)):  # (no graph: in place)
        t[pt, ft] = v
    return phi_face, psi, omega, far


def triangle_integrals(
    a: torch.Tensor, geometry: tuple[torch.Tensor, ...], tol: float, thin: bool = True, extras: dict | None = None
) -> tuple[torch.Tensor, ...]:
    """Green integrals of triangles seen from points: ``a`` ``(..., 3, 3)`` holds the corners
    minus the point, ``geometry`` is :func:`triangle_green_geometry` of the corners (broadcastable to
    ``a``'s leading shape). Returns ``(phi_face (..., 3), psi (...), omega (...), on_face (...),
    alpha (..., 3))`` as :func:`green3d_chunk`. ``thin``: thin faces seen from a few widths take
    :func:`._thin_triangle.thin_triangle_integrals` (off for the quad Riemann sums' cells, whose
    estimate only needs the closed forms' solid angles, as the native kernel's). ``extras``: a dict
    that receives ``"K"`` (``(..., 3)``, ``int (rho - rho_0) / r^3`` over the face), ``"thin"``
    (the pairs that took the swept form, or None) and ``"R"`` (``(..., 3)``, the corners' distances), for
    :func:`._green3d_derivatives.green3d_derivatives`."""
    normal, two_area, edge_dir, edge_out, grad_bary = geometry
    R = safe_norm(a)  # (..., 3)
    aj, ak = a[..., [1, 2, 0], :], a[..., [2, 0, 1], :]  # edge e runs from corner e + 1 to e + 2
    # Near a face's plane or a corner, the perpendicular w from the point to each edge's line, the same
    # bits for both faces of an edge (whatever their orientation), so that near an edge two faces see the
    # point on consistent sides (coplanar neighbours split their solid angle without a gap). The
    # distances to the plane and to the edge lines are w's components: d_e = w . eout_e and
    # h = w . n, taken from the nearest edge's w (the most accurate near an edge or a vertex).
    h = (a[..., 0, :] * normal).sum(-1)  # > 0 on the inner side
    d = (aj * edge_out).sum(-1)
    Rmin, Rmax = R.min(dim=-1).values, R.max(dim=-1).values
    near = (h.abs() < PERPENDICULAR_PLANE_RATIO * Rmin) | (h.abs() <= tol) | (Rmin < PERPENDICULAR_VERTEX_RATIO * Rmax)
    if bool(near.any()):  # (the native kernel does the same in its fix-up of these pairs)
        h, d = _near_distances(aj, ak, R, normal, edge_dir, edge_out, near, h, d)
    # Edge integrals and signed foot-to-edge distances (positive inside).
    ok = two_area > 0  # a degenerate triangle integrates to nothing
    I = torch.where(ok[..., None], _edge_integrals(aj, ak, edge_dir), 0.0)  # (..., 3)
    # Signed solid angle as a sum over edges (no ratio that vanishes near an edge or the plane):
    # Omega = sign(h) sum_e [atan(d l_k / (R0^2 + |h| R_k)) - atan(d l_j / (R0^2 + |h| R_j))].
    l_j, l_k = (aj * edge_dir).sum(-1), (ak * edge_dir).sum(-1)
    R_j, R_k = R[..., [1, 2, 0]], R[..., [2, 0, 1]]
    # |h| as sign(h) h with the sign held constant (sign(0) = +1): Omega = sign(h) f(|h|) is smooth
    # across the plane outside the face, and this keeps its derivative there (abs' (0) = 0 lost it).
    sgn = torch.where(h >= 0, 1.0, -1.0)
    habs = (sgn * h)[..., None]
    R0sq = d * d + habs * habs
    beta = safe_atan2(d * l_k, R0sq + habs * R_k) - safe_atan2(d * l_j, R0sq + habs * R_j)
    omega = sgn * beta.sum(-1)
    # Faces that hold the point (within tol) contribute their principal value: no solid angle, no
    # h-term; edges through the point have d = 0 and a log-singular I: their product is 0. A point
    # on a face's plane off the face keeps both (omega is 0 there, its derivative is not).
    on_plane = h.abs() <= tol
    on_face = on_plane & (d >= -tol).all(dim=-1) & ok
    if records_graph(a):
        # Exactly on the plane off the face, omega is 0 but the edge-sum form has no derivative
        # where the point is also on an edge's line (atan2(0, 0) in both of that edge's terms):
        # there the derivative comes from the Van Oosterom-Strackee form, whose denominator is
        # positive off the face; the value stays the edge sum's. (Its value, taken over the whole
        # on-plane band, was wrong by O(1) next to a sliver's edge, where its determinant had
        # cancelled: d(sum phi)/dx of 1e13 / size outside a needle, issue 42 item 2.)
        plane_off = (h == 0) & ~on_face
        if bool(plane_off.any()):
            vos = _vos_solid_angle(a, R)
            omega = torch.where(plane_off, omega.detach() + (vos - vos.detach()), omega)
    omega = torch.where(on_face, 0.0, omega)
    ell = safe_norm(grad_bary) * two_area[..., None]  # |grad| * 2A = edge length
    alpha = d * ell / torch.where(two_area > 0, two_area, 1.0)[..., None]  # barycentric coords of the foot
    K = -(edge_out * torch.where(on_face[..., None], 0.0, I)[..., None]).sum(-2)  # (..., 3)
    gK = (grad_bary * K[..., None, :]).sum(-1)  # (..., 3)
    phi_face = (alpha * omega[..., None] + h[..., None] * gK) / (4 * math.pi)
    dI = d * I  # I is 0 (not infinite) where d = 0 on the edge; d I keeps its derivative where d = 0 off it
    psi = (dI.sum(-1) - h * omega) / (4 * math.pi)
    psi, omega = torch.where(ok, psi, 0.0), torch.where(ok, omega, 0.0)
    phi_face = torch.where(ok[..., None], phi_face, 0.0)
    # Thin faces seen from a few widths: the closed forms above cancel (module _thin_triangle).
    # (faces first, from the constants: most cages have no thin face and pay one reduction)
    thin_face = (grad_bary.square().sum(-1).amax(-1) * two_area > THIN_ASPECT) & ok if thin else None
    thin_mask = thin_face & thin_pairs(a, two_area.expand(a.shape[:-2])) if thin and bool(thin_face.any()) else None
    if thin_mask is not None and bool(thin_mask.any()):
        phi_face, psi, omega = _put_thin(a, h, two_area, thin_mask, phi_face, psi, omega)
    if extras is not None:
        extras["K"], extras["thin"], extras["R"] = K, thin_mask, R
    return phi_face, psi, omega, on_face, alpha


def _put_thin(a, h, two_area, thin, phi_face, psi, omega) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``phi_face``, ``psi`` and ``omega`` with the ``thin`` pairs' entries from
    :func:`thin_triangle_integrals` (differentiable)."""
    shape = thin.shape
    idx = torch.nonzero(thin.reshape(-1)).squeeze(1)
    at = a.expand(*shape, 3, 3).reshape(-1, 3, 3).index_select(0, idx)
    ht = h.expand(shape).reshape(-1).index_select(0, idx)
    At = two_area.expand(shape).reshape(-1).index_select(0, idx)
    pf, ps, om = thin_triangle_integrals(at, ht, At)
    phi_face = phi_face.reshape(-1, 3).index_put((idx,), pf).reshape(*shape, 3)
    psi = psi.reshape(-1).index_put((idx,), ps).reshape(shape)
    omega = omega.reshape(-1).index_put((idx,), om).reshape(shape)
    return phi_face, psi, omega


def green3d_coordinates(
    x: torch.Tensor, data: TriangleGreenData, num_vertices: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(phi (n, V), psi (n, T))`` of a chunk of points, on-cage points included."""
    phi_face, psi, omega, on_face, alpha = green3d_chunk(x, data)
    tri = data.tri
    phi = torch.zeros(x.shape[0], num_vertices, dtype=x.dtype, device=x.device)
    for i in range(3):
        phi.index_add_(1, tri[:, i], phi_face[..., i])
    on_cage = on_face.any(dim=1)
    if bool(on_cage.any()):
        rows = torch.nonzero(on_cage).squeeze(1)
        f = (on_face[rows] * data.two_area).argmax(dim=1)  # the largest face: the best conditioned
        bary = alpha[rows, f].clamp_min(0.0)
        bary = bary / bary.sum(dim=1, keepdim=True)
        jump = 1 - omega[rows].sum(dim=1, keepdim=True) / (4 * math.pi)
        hat = torch.zeros(rows.shape[0], num_vertices, dtype=x.dtype, device=x.device)
        hat.scatter_add_(1, tri[f], bary)
        phi[rows] = phi[rows] + jump * hat
    return phi, psi
