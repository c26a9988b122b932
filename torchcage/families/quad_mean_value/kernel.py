r"""Torch kernel of quad mean value coordinates (QMVC; Thiery, Memari, Boubekeur 2018), chunk by chunk.

For a bilinear quad ``q`` with corners ``q_0..q_3`` and ``p_i = q_i - x``, the unnormalised
weights ``w = (w_0..w_3)`` of its corners satisfy the three equations ``sum_i w_i p_i = m`` (the
quad's mean vector, Eq. 16, from its four straight edges), so ``w = w_bar + lambda kappa`` with
``w_bar = A^+ m`` the least-norm solution (Eq. 28) and ``kappa`` the kernel of ``A = [p_0..p_3]``
(Eq. 26: ``k_i = (-1)^i det(p_{i+1}, p_{i+2}, p_{i+3})``). Linear precision holds for any
``lambda`` (the mean vectors of a closed cage add up to zero). ``lambda`` is estimated by a Riemann
sum ``Omega`` of the defining integrals over a ``(2n+1)^2`` grid of the quad's ``(u, v)`` domain
centred on the smooth projection of ``x`` onto the quad (Algorithm 1, Eqs. 22-24, with the norm
correction ``|w_bar|^2 / (Omega . w_bar)``).

Numerical choices (all thresholds relative to the cage's size):

- ``w_bar`` is computed as ``M m`` with the 4x3 pseudo-inverse ``M`` in Cramer form, followed by one
  step of iterative refinement (``w_bar += M (m - A w_bar)``), so that ``A w_bar = m`` holds to
  rounding even for nearly flat quads seen nearly edge-on.
- The Riemann sum is separable in the bilinear basis: four sums ``S = sum f``, ``S_u = sum u f``,
  ``S_v = sum v f``, ``S_uv = sum u v f`` with ``f = N(u,v).(xi - x) a / |xi - x|^4`` give
  ``Omega = (S - S_u - S_v + S_uv, S_u - S_uv, S_uv, S_v - S_uv)``; ``N(u, v)`` is affine in
  ``u`` and ``v``.
- Projection (Algorithm 1): points inside the quad's tetrahedron are kept; others are averaged
  over the four hull triangles with the absolute values of their mean value weights (computed by
  the stable triangle kernel, so points on a hull face's plane get exactly nothing from it); the
  line through the result along the quad's mean vector there is intersected with the bilinear
  sheet (Appendix B: a quadratic in ``v``, solved in its stable form, then ``u`` in closed form).
- A point within the on-cage tolerance of the sheet (``|xi(P(x)) - x|``) gets the bilinear
  coordinates of its projection; a point on the plane of a planar quad but off the quad (where
  ``kappa`` vanishes) gets no weight from it, the limit of the weights there. The band is
  ``ON_QUAD_BAND`` tolerances: the projection is not the nearest point of a curved sheet.
- Quads seen small (beyond ``10^FAR_QUAD_LOG[0]`` of their size) blend into a tensor Gauss rule
  of the defining integrals (:func:`gauss_weights`, :func:`far_blend`): far away Cramer's mean
  vector cancels. The sheet's edge vectors come from the corners, not from ``corner - x``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchcage._core.quad_quadrature import quad_integrals
from torchcage.families.mean_value.kernel3d import TriangleCageData, _cross, _dot, face_weights, triangle_data

Vec = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


@dataclass(frozen=True)
class QuadData:
    """Per-quad constants of a triquad cage's quads, in the compute dtype (Q quads)."""

    quads: torch.Tensor  # (Q, 4) corner vertex ids
    corners: torch.Tensor  # (3, 4, Q, 1) corner coordinates, components first
    hull: TriangleCageData  # the 4Q triangles of the quads' tetrahedra (4 per quad, quad-major)
    split: TriangleCageData  # the 2Q triangles (q0, q1, q2), (q0, q2, q3) (2 per quad, quad-major)
    size: torch.Tensor  # (Q, 1) longest edge or diagonal
    area2: torch.Tensor  # (Q, 1) sum of the four corner triangles' doubled areas
    tol: float  # absolute on-cage tolerance


#: Refinement steps restoring ``A w = m`` after the kernel term is added (each divides the residual
#: by about ``distance / (eps |x - q|)``).
REFINE = 3

#: Below this ``|kappa|_1 / (size^2 max_i |p_i|)`` (a point near the plane of a nearly planar quad),
#: the least-norm solution is taken from the split triangles' stable weights instead of Cramer's
#: form, whose mean vector loses its small normal component to cancellation there.
NEAR_FLAT = 1e-3

#: Quads seen from more than ``10^FAR_QUAD_LOG[0]`` times their size blend towards, and beyond
#: ``10^FAR_QUAD_LOG[1]`` take, the Gauss rule of the defining integrals (the mean vector of a quad
#: seen small cancels to ``eps (distance / size)^2`` of itself, which the far field's cancelling total
#: amplified to weights off by their own size at 1e6 cage sizes; the rule's error there is below
#: ``(size / (2 distance))^8``). The blend (a smoothstep in the log of the ratio) keeps the weights
#: continuous: the Riemann estimate differs from the integral by about 1e-5 at the ratio 30.
FAR_QUAD_LOG = (1.5, 2.5)

#: Gauss–Legendre nodes and weights of order 4 on [0, 1] (per direction of the quad's domain).
GAUSS4 = (
    (0.06943184420297371, 0.33000947820757187, 0.6699905217924281, 0.9305681557970262),
    (0.17392742256872679, 0.3260725774312732, 0.3260725774312732, 0.17392742256872679),
)

#: A point whose projection lies within this many on-cage tolerances of it is on the quad.
ON_QUAD_BAND = 4.0

#: Faces of a quad's tetrahedron, as corner indices (Algorithm 1, line 4).
HULL_FACES = ((0, 1, 3), (1, 2, 3), (0, 2, 1), (0, 3, 2))


def quad_sizes(vertices: torch.Tensor, quads: torch.Tensor) -> torch.Tensor:
    """Each quad's longest edge or diagonal: ``(*B, Q)`` for vertices ``(*B, V, 3)`` (one cage or a
    batch with one topology) and quads ``(Q, 4)``.

    Examples:
        >>> v = torch.tensor([[0.0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0]], dtype=torch.float64)
        >>> quad_sizes(v, torch.tensor([[0, 1, 2, 3]])).tolist()  # the diagonal, sqrt(5)
        [2.23606797749979]
    """
    p = vertices[..., quads, :]  # (*B, Q, 4, 3)
    diff = p[..., :, None, :] - p[..., None, :, :]
    return diff.norm(dim=-1).flatten(-2).amax(dim=-1)


def quad_data(vertices: torch.Tensor, quads: torch.Tensor, tol: float) -> QuadData:
    """Constants of the quads ``(Q, 4)`` of a cage with vertices ``(V, 3)`` (in their dtype)."""
    p = vertices[quads]  # (Q, 4, 3)
    hull_tri = torch.stack([quads[:, list(f)] for f in HULL_FACES], dim=1).reshape(-1, 3)
    split_tri = torch.stack([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]], dim=1).reshape(-1, 3)
    size = quad_sizes(vertices, quads)
    corner_tri = [p[:, [(i + 1) % 4, (i + 2) % 4, (i + 3) % 4]] for i in range(4)]
    area2 = sum(torch.linalg.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0], dim=-1).norm(dim=-1) for t in corner_tri)
    return QuadData(
        quads=quads,
        corners=p.permute(2, 1, 0).contiguous()[..., None],
        hull=triangle_data(vertices, hull_tri, tol),
        split=triangle_data(vertices, split_tri, tol),
        size=size[:, None],
        area2=area2[:, None],
        tol=tol,
    )


def _add(a: Vec, b: Vec) -> Vec:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def _sub(a: Vec, b: Vec) -> Vec:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _scale(s: torch.Tensor, a: Vec) -> Vec:
    return (s * a[0], s * a[1], s * a[2])


def _combo(w: list[torch.Tensor], p: list[Vec]) -> Vec:
    """``sum_i w_i p_i`` (``A w``)."""
    return _add(_add(_scale(w[0], p[0]), _scale(w[1], p[1])), _add(_scale(w[2], p[2]), _scale(w[3], p[3])))


def _safe(den: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    return torch.where(ok, den, torch.ones_like(den))


def mean_vector(p: list[Vec]) -> Vec:
    r"""Mean vector of a quad seen from the origin of ``p`` (Eq. 16): ``sum_e theta_e/2 N_e/|N_e|``
    over its edges ``e = (i, i+1)``, ``N_e = p_i x p_{i+1}``, ``theta_e`` the angle between them.
    Edges through the point (``N_e = 0``) contribute nothing."""
    m = None
    for i in range(4):
        c = _cross(p[i], p[(i + 1) % 4])
        c2 = _dot(c, c)
        ok = c2 > 0
        cn = torch.sqrt(_safe(c2, ok))
        g = torch.where(ok, 0.5 * torch.atan2(cn, _dot(p[i], p[(i + 1) % 4])) / cn, torch.zeros_like(cn))
        term = _scale(g, c)
        m = term if m is None else _add(m, term)
    assert m is not None
    return m


def _det(a: Vec, b: Vec, c: Vec) -> torch.Tensor:
    return _dot(a, _cross(b, c))


def kernel_and_pinv(p: list[Vec]) -> tuple[list[torch.Tensor], list[Vec], torch.Tensor]:
    """Kernel ``kappa`` of ``A = [p_0..p_3]`` (Eq. 26) and the rows of ``D A^+`` (Eq. 28, Cramer
    form: ``w_bar_i = M_i . m / D``), with ``D = |kappa|^2``."""
    c = {(a, b): _cross(p[a], p[b]) for a in range(4) for b in range(4) if a < b}

    def cr(a: int, b: int) -> Vec:
        return c[(a, b)] if a < b else tuple(-t for t in c[(b, a)])  # type: ignore[return-value]

    k = [_dot(p[1], cr(2, 3)), -_dot(p[2], cr(3, 0)), _dot(p[3], cr(0, 1)), -_dot(p[0], cr(1, 2))]
    # Cramer's rule on [A; kappa^T] w = [m; 0] (Appendix A), each determinant expanded along the
    # last row: w_i = sum_{j != i} (-1)^j k_j det(A_j with p_i -> m) / |kappa|^2, where A_j drops
    # column j (columns in order; the cofactors of the last row are -k_j). (The extracted Eq. 28 has
    # garbled signs; this form is checked against the pseudo-inverse in the tests.)
    rows: list[Vec] = []
    for i in range(4):
        acc = None
        for j in range(4):
            if j == i:
                continue
            cols = [t for t in range(4) if t != j]
            pos = cols.index(i)
            y, z = cols[(pos + 1) % 3], cols[(pos + 2) % 3]  # det(.., m at pos, ..) = m . (p_y x p_z)
            term = _scale(k[j] * (-1.0 if j % 2 else 1.0), cr(y, z))
            acc = term if acc is None else _add(acc, term)
        assert acc is not None
        rows.append(acc)
    D = k[0] * k[0] + k[1] * k[1] + k[2] * k[2] + k[3] * k[3]
    return k, rows, D


def _solve_v(c0: torch.Tensor, c1: torch.Tensor, c2: torch.Tensor) -> torch.Tensor:
    """Root of ``c0 + c1 v + c2 v^2`` nearest to [0, 1] (stable quadratic formula; linear when
    ``c2`` vanishes), clamped to [0, 1]."""
    disc = (c1 * c1 - 4 * c0 * c2).clamp_min(0.0)
    sgn = torch.where(c1 >= 0, 1.0, -1.0).to(c1.dtype)
    okq = disc > 0
    qq = -0.5 * (c1 + sgn * torch.where(okq, torch.sqrt(_safe(disc, okq)), torch.zeros_like(disc)))
    ok1, ok2 = c2 != 0, qq != 0
    r1 = torch.where(ok1, qq / _safe(c2, ok1), torch.full_like(qq, float("inf")))
    r2 = torch.where(ok2, c0 / _safe(qq, ok2), torch.full_like(qq, float("inf")))

    def badness(r: torch.Tensor) -> torch.Tensor:
        return (-r).clamp_min(0) + (r - 1).clamp_min(0) + 1e-3 * (r - 0.5).abs()

    v = torch.where(badness(r1) <= badness(r2), r1, r2)
    return v.clamp(0.0, 1.0)


def intersect(p: list[Vec], d: Vec) -> tuple[torch.Tensor, torch.Tensor]:
    """``(u, v)`` where the line through the origin of ``p`` along ``d`` meets the bilinear sheet
    of the quad with corners ``p`` (Appendix B), clamped to the unit square."""
    A0, A1 = p[0], _sub(p[3], p[0])  # a(v) = A0 + v A1
    B0, B1 = p[1], _sub(p[2], p[1])  # b(v) = B0 + v B1
    c0 = _dot(_cross(A0, B0), d)
    c1 = _dot(_add(_cross(A0, B1), _cross(A1, B0)), d)
    c2 = _dot(_cross(A1, B1), d)
    v = _solve_v(c0, c1, c2)
    a = _add(A0, _scale(v, A1))
    e = _sub(_add(B0, _scale(v, B1)), a)
    d2 = _dot(d, d)
    okd = d2 > 0
    inv_d2 = torch.where(okd, 1.0 / _safe(d2, okd), torch.zeros_like(d2))
    e_perp = _sub(e, _scale(_dot(e, d) * inv_d2, d))
    a_perp = _sub(a, _scale(_dot(a, d) * inv_d2, d))
    ee = _dot(e_perp, e_perp)
    oke = ee > 0
    u = torch.where(oke, -_dot(a_perp, e_perp) / _safe(ee, oke), torch.full_like(ee, 0.5))
    return u.clamp(0.0, 1.0), v


def sample_grid(t: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The adaptive 1D grid of Sec. 3.4.3 around ``t`` ``(...)``: ``2n + 1`` nodes (``t`` the
    middle one, ``n`` evenly spaced on each side) and their Voronoi lengths, each ``(..., 2n+1)``."""
    k = torch.arange(2 * n + 1, dtype=t.dtype, device=t.device) / n
    t_ = t[..., None]
    nodes = torch.where(k <= 1, k * t_, t_ + (k - 1) * (1 - t_))
    ext = torch.cat([nodes[..., :1], nodes, nodes[..., -1:]], dim=-1)
    lengths = (ext[..., 2:] - ext[..., :-2]) / 2
    return nodes, lengths


def riemann_sums(p0: Vec, b: Vec, c: Vec, dd: Vec, u: torch.Tensor, v: torch.Tensor, n: int) -> list[torch.Tensor]:
    """Riemann estimate ``Omega`` (Eqs. 22-23) of the four corner integrals on the grid around
    ``(u, v)``. Shapes: vectors and ``u, v`` broadcast to the pair shape ``S``; returns four ``S``.

    The sheet is ``xi - x = p0 + u b + v c + u v dd`` and its normal ``N = b x c + u (b x dd) +
    v (dd x c)`` (``xi_u x xi_v``, outward for counter-clockwise quads).
    """
    un, ua = sample_grid(u, n)  # (S, K)
    vn, va = sample_grid(v, n)
    N0, Nu, Nv = _cross(b, c), _cross(b, dd), _cross(dd, c)
    # Per u node: xi - x = P(u) + v Q(u), N = R(u) + v Nv.
    Pu = [p0[i][..., None] + un * b[i][..., None] for i in range(3)]  # (S, K)
    Qu = [c[i][..., None] + un * dd[i][..., None] for i in range(3)]
    Ru = [N0[i][..., None] + un * Nu[i][..., None] for i in range(3)]
    V = vn[..., None, :]  # (S, 1, K): v along the last axis
    dx = [Pu[i][..., :, None] + V * Qu[i][..., :, None] for i in range(3)]  # (S, K, K)
    r2 = dx[0] * dx[0] + dx[1] * dx[1] + dx[2] * dx[2]
    Nd = sum((Ru[i][..., :, None] + V * Nv[i][..., None, None]) * dx[i] for i in range(3))
    f = Nd / (r2 * r2) * (ua[..., :, None] * va[..., None, :])
    fv = f.sum(dim=-2)  # (S, K) summed over u: functions of v
    fu = f.sum(dim=-1)  # (S, K) summed over v
    S = fv.sum(dim=-1)
    Su = (fu * un).sum(dim=-1)
    Sv = (fv * vn).sum(dim=-1)
    Suv = ((f * un[..., :, None]).sum(dim=-2) * vn).sum(dim=-1)
    return [S - Su - Sv + Suv, Su - Suv, Suv, Sv - Suv]


def gauss_weights(p0: Vec, b: Vec, c: Vec, dd: Vec) -> list[torch.Tensor]:
    """The four corner integrals ``int phi_i(u, v) N.(xi - x) / |xi - x|^4 du dv`` by the tensor
    Gauss rule :data:`GAUSS4` (for quads seen small); vectors broadcast to the pair shape ``S``,
    returns four ``S``. The sheet is as in :func:`riemann_sums`."""
    N0, Nu, Nv = _cross(b, c), _cross(b, dd), _cross(dd, c)
    t = torch.tensor(GAUSS4[0], dtype=p0[0].dtype, device=p0[0].device)
    g = torch.tensor(GAUSS4[1], dtype=p0[0].dtype, device=p0[0].device)
    U, V = t[:, None], t[None, :]  # (4, 1), (1, 4): u down, v across
    dx = [p0[i][..., None, None] + U * b[i][..., None, None] + V * c[i][..., None, None] for i in range(3)]
    dx = [dx[i] + (U * V) * dd[i][..., None, None] for i in range(3)]
    N = [N0[i][..., None, None] + U * Nu[i][..., None, None] + V * Nv[i][..., None, None] for i in range(3)]
    Nd = N[0] * dx[0] + N[1] * dx[1] + N[2] * dx[2]
    r2 = dx[0] * dx[0] + dx[1] * dx[1] + dx[2] * dx[2]
    f = Nd / (r2 * r2) * (g[:, None] * g[None, :])
    hats = ((1 - U) * (1 - V), U * (1 - V), U * V, (1 - U) * V)
    return [(f * h).sum(dim=(-2, -1)) for h in hats]


def far_blend(R2: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
    """Weight ``(Q, m)`` of the Gauss rule per pair: 0 below the ratio ``10^FAR_QUAD_LOG[0]`` of the
    nearest corner's distance to the quad's size, 1 above ``10^FAR_QUAD_LOG[1]``, a smoothstep in
    the log between (``R2`` ``(4, Q, m)`` squared corner distances, ``size`` ``(Q, 1)``)."""
    ratio2 = R2.min(dim=0).values / (size * size)
    lo, hi = FAR_QUAD_LOG
    s = ((0.5 * torch.log10(ratio2.clamp_min(1.0)) - lo) / (hi - lo)).clamp(0.0, 1.0)
    return s * s * (3 - 2 * s)


@dataclass
class Projection:
    """Per point–quad quantities of a chunk, each ``(Q, m)`` (lists by corner, ``Vec`` by component)."""

    p: list[Vec]  # corners minus the point
    R2: torch.Tensor  # (4, Q, m) squared distances to the corners
    vertex: torch.Tensor  # the corner the point sits on, or -1
    mvec: Vec  # the quad's mean vector at the point (Eq. 16)
    k: list[torch.Tensor]  # kernel kappa of A (Eq. 26)
    rows: list[Vec]  # rows of |kappa|^2 A^+
    D: torch.Tensor  # |kappa|^2
    kabs: torch.Tensor  # |kappa|_1
    flat: torch.Tensor  # a planar quad and a point on its plane (kappa vanishes)
    inside: torch.Tensor  # the point is inside the quad's tetrahedron
    b: Vec  # q1 - q0: the sheet is xi - x = p0 + u b + v c + u v dd
    c: Vec  # q3 - q0
    dd: Vec  # q0 - q1 + q2 - q3
    nq: Vec  # normal of the sheet at its centre
    u: torch.Tensor  # projection of the point onto the quad (Algorithm 1)
    v: torch.Tensor
    on: torch.Tensor  # the point lies on the quad (or a corner)


def project(x: torch.Tensor, data: QuadData) -> Projection:
    """The smooth projection of every point onto every quad (Algorithm 1) and the per-pair
    quantities it needs (mean vector, kernel); ``x`` is ``(m, 3)``."""
    Q, m = data.quads.shape[0], x.shape[0]
    cq = data.corners  # (3, 4, Q, 1)
    xt = x.T[:, None, :]  # (3, 1, m)
    p: list[Vec] = [tuple(cq[c, i] - xt[c] for c in range(3)) for i in range(4)]  # type: ignore[misc]
    R2 = torch.stack([_dot(pi, pi) for pi in p])  # (4, Q, m)
    tol = data.tol
    vertex = torch.where((R2 <= tol * tol).any(dim=0), R2.argmin(dim=0), -1)

    mvec = mean_vector(p)
    k, rows, D = kernel_and_pinv(p)
    kabs = k[0].abs() + k[1].abs() + k[2].abs() + k[3].abs()
    # kappa vanishes only for a planar quad and a point on its plane: |kappa|_1 = |h| sum_i 2 A_i
    # there (A_i the corner triangles' areas), so this is |h| <= tol: the on-quad tolerance (a
    # looser test left points just above a planar quad, off it by the tolerance, with no weight).
    flat = kabs <= tol * data.area2
    alpha = k[0] + k[1] + k[2] + k[3]  # 6 x signed volume of the tetrahedron (independent of x)
    sgn = torch.where(alpha >= 0, 1.0, -1.0).to(x.dtype)
    inside = (alpha != 0) & (torch.stack(k) * sgn >= -1e-13 * kabs).all(dim=0)
    # The signs of kappa mean nothing at the level of its rounding error (a point on the plane of
    # a nearly planar quad, off it, came out "inside" and got weights of order 1): not inside then.
    Rs = R2.sqrt()
    noise = (16 * torch.finfo(x.dtype).eps) * (
        Rs[1] * Rs[2] * Rs[3] + Rs[0] * Rs[2] * Rs[3] + Rs[0] * Rs[1] * Rs[3] + Rs[0] * Rs[1] * Rs[2]
    )
    inside = inside & (kabs > noise)

    # x' = x inside the tetrahedron, else the |MVC| average over its faces.
    outside = ~inside & ~flat & (vertex < 0)
    xp: list[torch.Tensor] = [xt[c].expand(Q, m) for c in range(3)]
    if bool(outside.any()):
        xp = _hull_average(x, data, outside, xp)
    pp: list[Vec] = [tuple(cq[c, i] - xp[c] for c in range(3)) for i in range(4)]  # type: ignore[misc]
    mp = mean_vector(pp)
    # Planar quad and a point on its plane: project along the quad's normal (inverse bilinear).
    # (from the corners, not from p: differences of p lose eps |x - q| / size far away)
    q: list[Vec] = [tuple(cq[comp, i] for comp in range(3)) for i in range(4)]  # type: ignore[misc]
    b, c, dd = _sub(q[1], q[0]), _sub(q[3], q[0]), _add(_sub(q[0], q[1]), _sub(q[2], q[3]))
    nq = _add(_cross(b, c), _scale(torch.full_like(b[0], 0.5), _add(_cross(b, dd), _cross(dd, c))))
    d = tuple(torch.where(flat, nq[i], torch.where(outside, mp[i], mvec[i])) for i in range(3))
    u, v = intersect(pp, d)  # type: ignore[arg-type]
    # On a corner: its parameters.
    at = vertex >= 0
    corner_u = torch.tensor([0.0, 1.0, 1.0, 0.0], dtype=u.dtype, device=u.device)[vertex.clamp_min(0)]
    corner_v = torch.tensor([0.0, 0.0, 1.0, 1.0], dtype=u.dtype, device=u.device)[vertex.clamp_min(0)]
    u, v = torch.where(at, corner_u, u), torch.where(at, corner_v, v)

    # On the quad: the bilinear coordinates of the projection reproduce the point.
    xi = _add(_add(p[0], _scale(u, b)), _add(_scale(v, c), _scale(u * v, dd)))
    # (A point within tol of a planar quad's plane gets no weight from it off the quad: within tol
    # of its boundary too, it is on the quad, or it would get no weight from either face of an edge.)
    # (the projection is not the nearest point of a curved sheet: |xi - x| can exceed the distance
    # to the sheet, so the band is ON_QUAD_BAND tolerances; a point 1.25 tolerances off a twisted
    # quad's edge by this measure, 0.9 by the true distance, got garbage from the fan: PU off by 0.44)
    on = (_dot(xi, xi) <= torch.where(flat, 2.0, ON_QUAD_BAND**2) * (tol * tol)) | (vertex >= 0)
    return Projection(p, R2, vertex, mvec, k, rows, D, kabs, flat, inside, b, c, dd, nq, u, v, on)  # type: ignore[arg-type]


def qmvc3d_chunk(
    x: torch.Tensor, data: QuadData, n: int, tol: float | None = None
) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Unnormalised QMVC weights of every quad corner for a chunk of points.

    Args:
        x: ``(m, 3)`` points.
        data: the quads' constants.
        n: grid parameter (``(2n+1)^2`` samples per quad).
        tol: if given, the defining integrals are computed to this relative tolerance
            (:mod:`torchcage._core.quad_quadrature`) instead of by the Riemann sum, and the weights are their
            orthogonal projection onto the solutions of ``A w = m`` (``lambda = Omega . kappa / D``:
            no norm correction, which only serves the Riemann sum's bias); far quads take the
            integrals themselves.

    Returns:
        ``(w, on, u, v, vertex)``: ``w`` four ``(Q, m)`` corner weights (zero where the pair is on
        the quad); ``on`` ``(Q, m)`` bool, the point lies on the quad; ``u, v`` ``(Q, m)`` its
        projection's parameters; ``vertex`` ``(Q, m)`` the corner the point sits on, or -1.
    """
    pr = project(x, data)
    p, R2, mvec, k, rows, D, kabs = pr.p, pr.R2, pr.mvec, pr.k, pr.rows, pr.D, pr.kabs
    flat, inside, b, c, dd, nq, u, v, on = pr.flat, pr.inside, pr.b, pr.c, pr.dd, pr.nq, pr.u, pr.v, pr.on
    vertex = pr.vertex

    # --- General case: w = w_bar + lambda kappa (Eqs. 20-24). ---
    okD = ~flat & ~on
    invD = torch.where(okD, 1.0 / _safe(D, okD), torch.zeros_like(D))
    wbar = [_dot(rows[i], mvec) * invD for i in range(4)]
    res = _sub(mvec, _combo(wbar, p))
    wbar = [wbar[i] + _dot(rows[i], res) * invD for i in range(4)]
    # Pairs on the quad are replaced by the caller; keep their samples away from the singularity.
    us = torch.where(okD, u, torch.full_like(u, 0.5))
    vs = torch.where(okD, v, torch.full_like(v, 0.5))
    p0s: Vec = tuple(torch.where(okD, p[0][i], p[0][i] - nq[i]) for i in range(3))  # type: ignore[assignment]
    if tol is None:
        omega = riemann_sums(p0s, b, c, dd, us, vs, n)
    else:
        shape = us.shape
        flat_vec = [tuple(t.expand(shape).reshape(-1) for t in vec) for vec in (p0s, b, c, dd)]
        om = quad_integrals(*flat_vec, us.reshape(-1), vs.reshape(-1), tol)  # type: ignore[arg-type]
        omega = [om[i].reshape(shape) for i in range(4)]
    ok_dot = sum(omega[i] * k[i] for i in range(4))
    if tol is None:
        ow = sum(omega[i] * wbar[i] for i in range(4))
        ww = sum(wbar[i] * wbar[i] for i in range(4))
        ok_ow = ow != 0
        lam = torch.where(ok_ow & okD, ok_dot * invD * ww / _safe(ow, ok_ow), torch.zeros_like(ow))
    else:
        lam = torch.where(okD, ok_dot * invD, torch.zeros_like(ok_dot))
    w = [wbar[i] + lam * k[i] for i in range(4)]
    # kappa carries a relative error of about eps |x - q| / distance(x, quad's corner planes), so
    # A (lambda kappa) drifts off zero where lambda is large (near a quad): restore A w = m.
    for _ in range(REFINE):
        res = _sub(mvec, _combo(w, p))
        w = [w[i] + _dot(rows[i], res) * invD for i in range(4)]
    # Near a flat quad's plane the Cramer mean vector is the inaccurate part: use the split form.
    near_flat = okD & ~inside & (kabs < NEAR_FLAT * data.size * data.size * R2.max(dim=0).values.sqrt())
    if bool(near_flat.any()):
        w = _near_flat_weights(x, data, near_flat, w, k, D, omega, p, rows, exact=tol is not None)
    beta = far_blend(R2, data.size)
    far = torch.nonzero((beta > 0).reshape(-1)).squeeze(1)
    if far.numel():  # (only the pairs seen small: the rule on every pair cost 30% under autograd)

        def pick(t: torch.Tensor) -> torch.Tensor:
            return t.expand_as(beta).reshape(-1).index_select(0, far)

        if tol is None:
            wg = gauss_weights(*(tuple(pick(t) for t in vec) for vec in (p[0], b, c, dd)))  # type: ignore[arg-type]
        else:
            wg = [pick(omega[i]) for i in range(4)]
        bf = beta.reshape(-1).index_select(0, far)
        w = [
            w[i]
            .reshape(-1)
            .index_put((far,), (1 - bf) * w[i].reshape(-1).index_select(0, far) + bf * wg[i])
            .reshape(beta.shape)
            for i in range(4)
        ]
    w = [torch.where(okD, w[i], torch.zeros_like(w[i])) for i in range(4)]
    return w, on, u, v, vertex


def _hull_average(x: torch.Tensor, data: QuadData, outside: torch.Tensor, xp: list[torch.Tensor]) -> list[torch.Tensor]:
    """First step of the projection for the pairs in ``outside`` ``(Q, m)``: the average of the
    tetrahedron's corners with the absolute mean value weights of its four faces (Eq. 25)."""
    Q, m = outside.shape
    hw, _ = face_weights(x, data.hull, far_field=False)  # three (4Q, m)
    hv = data.hull.vertices  # (3, V)
    tri = data.hull.tri  # (4Q, 3)
    num = [torch.zeros((Q, m), dtype=x.dtype, device=x.device) for _ in range(3)]
    den = torch.zeros((Q, m), dtype=x.dtype, device=x.device)
    for i in range(3):
        a = hw[i].abs()
        a = torch.where(torch.isfinite(a), a, torch.zeros_like(a)).reshape(Q, 4, m)
        den = den + a.sum(dim=1)
        for comp in range(3):
            coord = hv[comp].index_select(0, tri[:, i]).reshape(Q, 4, 1)
            num[comp] = num[comp] + (a * coord).sum(dim=1)
    okd = outside & (den > 0)
    safe_den = _safe(den, okd)
    return [torch.where(okd, num[c] / safe_den, xp[c]) for c in range(3)]


def _near_flat_weights(
    x: torch.Tensor,
    data: QuadData,
    sel: torch.Tensor,
    w: list[torch.Tensor],
    k: list[torch.Tensor],
    D: torch.Tensor,
    omega: list[torch.Tensor],
    p: list[Vec],
    rows: list[Vec],
    exact: bool = False,
) -> list[torch.Tensor]:
    """Weights for the pairs in ``sel`` ``(Q, m)`` from a particular solution that stays accurate
    near a flat quad's plane: the split triangles' mean value weights ``w_p`` (``A w_p = m``), made
    least-norm by removing their ``kappa`` part, plus the estimated ``lambda kappa`` (Eq. 24; with
    ``exact`` integrals ``omega``, ``lambda = omega . kappa_hat``, no norm correction)."""
    Q, m = sel.shape
    tw, _ = face_weights(x, data.split, far_field=False)  # three (2Q, m)
    t = [a.reshape(Q, 2, m) for a in tw]
    wp = [t[0][:, 0] + t[0][:, 1], t[1][:, 0], t[2][:, 0] + t[1][:, 1], t[2][:, 1]]
    finite = torch.isfinite(wp[0] + wp[1] + wp[2] + wp[3])
    use = sel & finite
    wp = [torch.where(use, a, torch.zeros_like(a)) for a in wp]
    invn = torch.where(use, torch.rsqrt(_safe(D, use)), torch.zeros_like(D))
    kh = [a * invn for a in k]
    pk = sum(wp[i] * kh[i] for i in range(4))
    wbar = [wp[i] - pk * kh[i] for i in range(4)]
    ok = sum(omega[i] * kh[i] for i in range(4))
    ow = sum(omega[i] * wbar[i] for i in range(4))
    ww = sum(wbar[i] * wbar[i] for i in range(4))
    if exact:
        lam = torch.where(use, ok, torch.zeros_like(ok))
    else:
        good = use & (ow != 0)
        lam = torch.where(good, ok * ww / _safe(ow, good), torch.zeros_like(ow))
    wn = [wbar[i] + lam * kh[i] for i in range(4)]
    # As in the general case, restore A w = A w_p (= m) against kappa's rounding error.
    invD = torch.where(use, 1.0 / _safe(D, use), torch.zeros_like(D))
    for _ in range(REFINE):
        res = _combo([wp[i] - wn[i] for i in range(4)], p)
        wn = [wn[i] + _dot(rows[i], res) * invD for i in range(4)]
    return [torch.where(use, wn[i], w[i]) for i in range(4)]
