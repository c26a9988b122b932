r"""Torch kernel of 3D mean value coordinates (closed triangle cages), chunk by chunk.

3D (Floater, Kós, Reimers 2005; Ju, Schaefer, Warren 2005; vector form of Thiery et al. 2014,
Sec. 2.2). For a triangle ``T`` with corners ``p_1, p_2, p_3`` and ``a_i = p_i - x``,

.. math::
    m^T = \sum_e \tfrac{\theta_e}{2} \frac{N_e}{|N_e|},\quad N_e = a_{e+1} \times a_{e+2},\quad
    w_i^T = \frac{N_i \cdot m^T}{\det(a_1, a_2, a_3)},

where :math:`\theta_e` is the angle between :math:`a_{e+1}` and :math:`a_{e+2}`. Evaluated as
written, this is a ratio of two quantities that vanish on the face's support plane, and it loses
all precision for points near the plane but outside the face (an error of about
``eps * size / distance``). torchcage splits every cross product into its normal and in-plane
parts, ``N_e = s_e n + h t_e`` (``h`` the distance to the plane, ``s_e`` twice the signed area of
the foot point and edge ``e``, ``t_e`` a rotated edge vector), so that

.. math::
    w_i^T = \frac{s_i S + h^2 \sum_e \theta_e\, t_i\cdot t_e / |N_e|}{4 A h},\qquad
    S = \sum_e \theta_e \frac{s_e}{|N_e|} = 2\pi\,\mathrm{wind} + h^2 \sum_e \sigma_e
        \Big(\frac{\delta_e}{h^2} - \theta_e\frac{\varepsilon_e}{h^2}\Big),

with :math:`\sigma_e = \mathrm{sign}(s_e)`, :math:`\theta_e = \theta_e^0 + \delta_e` (``\theta^0``
the planar angle at the foot point, ``\delta`` computed from its sine and cosine, both
:math:`O(h^2)` in closed form) and :math:`\varepsilon_e = 1 - |s_e|/|N_e|`. The winding number of
the face around the foot point is exact, and every remaining term carries its power of ``h``
explicitly, so a face's contribution is accurate to rounding at any distance from its plane; a
point exactly on the plane outside the face gets exactly no contribution. This stable form is used
for point–face pairs with ``|h| < 0.01 min_i |a_i|`` (where the direct form has lost less than
two digits).

Faces that are small seen from the point suffer a different cancellation in the vector form (a
relative error of about ``eps (r / edge)^3``, worse for slivers). It is harmless where the face
weights add up (inside the cage), but far outside the total weight is much smaller than its parts
and the error is amplified. For points whose face weights cancel (absolute sum over four times the
total), torchcage integrates the defining integral ``w_i^T = h \int_T \phi_i / |p - x|^4 dA``
on every face whose longest edge is shorter than its distance, with a collapsed 14x14
Gauss–Legendre rule (error about ``(edge / 4r)^28``). The direct form serves all other pairs.

Points on the cage (within ``ON_CAGE_TOLERANCE`` times the cage size) get the interpolating values:
barycentric on the face, linear on the edge, Lagrange at a vertex.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import torch

from torchcage._core.common import (
    collapsed_gauss,
    nearest_where,
    on_cage_tolerance,
    records_graph,
    safe_atan2,
    safe_div,
    safe_sqrt,
    triangle_geometry,
)
from torchcage._core.thin_triangle import THIN_ASPECT, thin_pairs, thin_triangle_mvc
from torchcage.cage import Cage

#: Point–face pairs with ``|h| < SPLIT_FORM_RATIO * min_i |p_i - x|`` use the stable form.
SPLIT_FORM_RATIO = 0.01
#: Points whose face weights sum, in absolute value, to more than ``CANCELLATION_RATIO`` times their
#: total get the far-field rule on every face whose longest edge is below ``FAR_FIELD_RATIO * min_i
#: |p_i - x|``.
CANCELLATION_RATIO = 4.0
FAR_FIELD_RATIO = 1.0
#: Triangles that are part of a closed cage (``far_field="always"``) take the far-field rule when
#: seen from more than ``1 / PART_FAR_FIELD_RATIO`` times their longest edge (nearer, the vector
#: form's error ``eps (r / edge)^3`` is below 1e-13, and the quadrature for every pair cost 20%).
PART_FAR_FIELD_RATIO = 0.1
#: Faces seen from more than ``FAR_ALWAYS_RATIO`` times their longest edge always take the far-field rule.
FAR_ALWAYS_RATIO = 1e3
#: A point on the cage (an edge: two faces) takes the barycentric interpolant of the largest face
#: holding it; of faces whose areas are within this relative margin of the largest, the first (the
#: native kernels' areas differ from these in their last digits, and a triangulated quad's two halves
#: often tie; ``TC_AREA_TIE`` in ``backends/native/native.h``).
AREA_TIE = 1e-9
#: Gauss–Legendre order (per direction of the collapsed square) of the far-field rule: its error
#: decays like ``(FAR_FIELD_RATIO / 4)^(2 * order)``.
FAR_FIELD_ORDER = 14


@dataclass(frozen=True)
class TriangleCageData:
    """Per-face constants of a triangle cage, in the compute dtype. Shapes use T faces, V vertices."""

    vertices: torch.Tensor  # (3, V)   coordinates, components first
    tri: torch.Tensor  # (T, 3)   corners
    normal: torch.Tensor  # (3, T, 1) unit outward normals
    two_area: torch.Tensor  # (T, 1)   twice the face area
    edge_len: torch.Tensor  # (3, T, 1) length of the edge opposite each corner
    gram: torch.Tensor  # (T, 3, 3) E_i . E_e for the edges E_e = p_{e+1} - p_{e+2}
    tol: float  # absolute on-cage tolerance
    longest: torch.Tensor  # (T, 1)   longest edge
    far_nodes: torch.Tensor  # (T, Q, 3) far-field quadrature nodes
    far_coef: torch.Tensor  # (T, Q, 3) their weights times the corners' hat functions (area included)
    thin: torch.Tensor  # (k,) the faces THIN_ASPECT times longer than wide (module _thin_triangle)


#: The end of the error for a cage with quads.
TRIANGLE_CAGE_HINT = "use quad_mean_value_coordinates for quad/triquad cages, or cage.triangulated() to split quads"


def triangle_cage_data(cage: Cage, dtype: torch.dtype) -> TriangleCageData:
    triangle_geometry(cage, dtype, TRIANGLE_CAGE_HINT)  # checks: a 3D triangle cage
    return triangle_data(cage.vertices.to(dtype), cage.triangles, on_cage_tolerance(cage))


def triangle_data(v: torch.Tensor, tri: torch.Tensor, tol: float) -> TriangleCageData:
    """Per-face constants of any set of triangles ``tri`` ``(T, 3)`` over vertices ``v`` ``(V, 3)``
    (a whole cage, the triangles of a triquad cage, the faces of a quad's hull), in ``v.dtype``;
    ``tol`` is the absolute on-face tolerance."""
    c = face_constants(v[tri])
    two_area, edge_len = c["two_area"], c["edge_len"]
    return TriangleCageData(
        vertices=v.T.contiguous(),
        tri=tri,
        normal=c["normal"].T.contiguous()[:, :, None],
        two_area=two_area[:, None],
        edge_len=edge_len.T.contiguous()[:, :, None],
        gram=c["gram"],
        tol=tol,
        longest=c["longest"][:, None],
        far_nodes=c["far_nodes"],
        far_coef=c["far_coef"],
        thin=torch.nonzero((c["edges"].square().sum(-1).amax(-1) > THIN_ASPECT * two_area) & (two_area > 0)).flatten(),
    )


def face_constants(p: torch.Tensor, far: bool = True) -> dict[str, torch.Tensor]:
    """Per-face constants of triangles with corners ``p`` ``(*B, T, 3, 3)`` (``*B``: none, or a batch
    of cages with one topology, computed at once with the same operations element by element).

    Returns:
        ``two_area`` ``(*B, T)``, ``normal`` ``(*B, T, 3)`` (unit), ``edges`` ``(*B, T, 3, 3)`` (the
        edge ``E_e = p_{e+1} - p_{e+2}`` opposite each corner), ``edge_len`` ``(*B, T, 3)``,
        ``gram`` ``(*B, T, 3, 3)`` (``E_i . E_e``), ``longest`` ``(*B, T)``, and the far-field rule's
        nodes ``far_nodes`` and their weights times the corners' hat functions (area included)
        ``far_coef``, both ``(*B, T, Q, 3)`` (left out with ``far=False``: the native kernel places
        the nodes itself).
    """
    cross = torch.linalg.cross(p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :], dim=-1)
    two_area = cross.norm(dim=-1)
    edges = p.roll(-1, dims=-2) - p.roll(-2, dims=-2)  # E_e = p_{e+1} - p_{e+2}, (*B, T, 3, 3)
    edge_len = edges.norm(dim=-1)
    out = {
        "two_area": two_area,
        "normal": cross / two_area[..., None],
        "edges": edges,
        "edge_len": edge_len,
        "gram": edges @ edges.transpose(-1, -2),
        "longest": edge_len.amax(dim=-1),  # (amax: max(dim).values cost milliseconds on 2 busy cores)
    }
    if far:
        bary, qw = collapsed_gauss(FAR_FIELD_ORDER, p.dtype, p.device)
        out["far_nodes"] = bary @ p  # (*B, T, Q, 3), sum_i bary[q, i] p[t, i]: contiguous (an einsum's was not)
        out["far_coef"] = (two_area[..., None, None] * qw[:, None]) * bary
    return out


def _cross(a: tuple[torch.Tensor, ...], b: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, ...]:
    ax, ay, az = a
    bx, by, bz = b
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


def _dot(a: tuple[torch.Tensor, ...], b: tuple[torch.Tensor, ...]) -> torch.Tensor:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _stable_face_weights(
    h: torch.Tensor,
    s: list[torch.Tensor],
    dots: list[torch.Tensor],
    R: list[torch.Tensor],
    ell: list[torch.Tensor],
    gram: list[list[torch.Tensor]],
    two_area: torch.Tensor,
    singular: list[torch.Tensor] | None = None,
) -> list[torch.Tensor]:
    """Face weights ``w_i^T`` in the stable split form, for pairs near the face's support plane.

    With a list ``singular`` given, the weights returned leave out the term ``c_i / h`` of a
    face around the point's foot (``wind != 0``) and ``singular`` receives the three ``c_i``
    (zero elsewhere): the caller can then divide ``h`` out before differentiating.

    All inputs are tensors of one broadcastable shape over point–face pairs (``(M,)`` for a
    selection); ``gram[i][e] = E_i . E_e``, ``s[e] = n . N_e``, ``dots[e] = a_{e+1} . a_{e+2}``,
    ``R[i] = |a_i|``, ``ell[e]`` the length of edge ``e``. Requires ``|h| < min R`` so that the
    foot point of ``x`` is apart from every corner (points on a vertex are handled by the caller).
    """
    h2 = h * h
    wind_angle = torch.zeros_like(h)
    S_rest = torch.zeros_like(h)
    theta_over_N = []
    for e in range(3):
        j, k = (e + 1) % 3, (e + 2) % 3
        sigma = torch.where(s[e] >= 0, 1.0, -1.0).to(h.dtype)
        # |s| as sigma * s, not abs(): the weights are smooth where s crosses 0 (the foot point on
        # an edge's line), and this keeps autograd's one-sided derivative there instead of 0.
        s_abs = sigma * s[e] + 0.0  # + 0.0 turns -0.0 into +0.0 (atan2 tells them apart)
        qq = dots[e] - h2  # q_j . q_k
        N2 = s[e] * s[e] + (h * ell[e]) ** 2  # |N_e|^2 = |a_j x a_k|^2, consistent with s and h
        N = torch.sqrt(torch.where(N2 > 0, N2, 1.0)) * (N2 > 0)  # (no NaN gradient where N = 0)
        theta0 = torch.atan2(s_abs, qq)  # planar angle at the foot point
        wind_angle = wind_angle + sigma * theta0
        Nps = N + s_abs
        safe_Nps = torch.where(Nps > 0, Nps, 1.0)
        X = qq * ell[e] ** 2 / safe_Nps - s_abs  # sin(delta) R_j R_k rho_j rho_k / h^2
        Y = dots[e] * qq + N * s_abs  # cos(delta) R_j R_k rho_j rho_k
        delta = torch.atan2(h2 * X, Y)
        safe_h2 = torch.where(h2 > 0, h2, 1.0)
        delta_h2 = torch.where(h2 > 0, delta / safe_h2, X / Y)  # delta / h^2
        theta = theta0 + delta
        safe_N = torch.where(N > 0, N, 1.0)
        t_over_N = torch.where(N > 0, theta / safe_N, 1.0 / (R[j] * R[k]))  # theta / |N| (theta -> 0)
        eps_h2 = ell[e] ** 2 / (safe_N * safe_Nps)  # epsilon_e / h^2
        S_rest = S_rest + sigma * (delta_h2 - theta * eps_h2)
        theta_over_N.append(t_over_N)
    wind = torch.round(wind_angle / (2 * math.pi))
    safe_h = torch.where(h != 0, h, 1.0)
    inv4A = 1.0 / (2.0 * two_area)
    out = []
    for i in range(3):
        B = s[i] * S_rest + theta_over_N[0] * gram[i][0] + theta_over_N[1] * gram[i][1] + theta_over_N[2] * gram[i][2]
        w = h * B * inv4A
        c = torch.where(wind != 0, s[i] * (2 * math.pi) * wind * inv4A, 0.0)
        if singular is not None:
            singular.append(c)
        else:
            w = w + c / safe_h
        # h = 0 outside the face: w = h B / (4A) = 0, kept as that product so that autograd sees
        # its derivative B dh / (4A) (a constant 0 here lost the rest vertices' gradients on planes)
        out.append(w)
    return out


def _pair_terms(x: torch.Tensor, data: TriangleCageData) -> dict[str, list[torch.Tensor] | torch.Tensor]:
    """Per point–face quantities, each ``(T, n)`` (lists are indexed by corner or edge).

    ``a[i]`` = ``p_i - x`` as three component tensors, ``R[i] = |a_i|``, ``h = n . a_0`` (signed
    distance to the support plane, positive on the inner side), ``N[e] = a_{e+1} x a_{e+2}``,
    ``Nn[e] = |N_e|``, ``dots[e] = a_{e+1} . a_{e+2}``, ``s[e] = n . N_e``.
    """
    xt = x.T[:, None, :]  # (3, 1, n)
    a_all = data.vertices[:, :, None] - xt  # (3, V, n)
    R_all = safe_sqrt((a_all * a_all).sum(dim=0))  # (V, n); derivative 0 (not NaN) at a vertex
    tri = data.tri
    a = [tuple(a_all[c].index_select(0, tri[:, i]) for c in range(3)) for i in range(3)]
    R = [R_all.index_select(0, tri[:, i]) for i in range(3)]
    nrm = (data.normal[0], data.normal[1], data.normal[2])
    N, Nn, dots, s = [], [], [], []
    for e in range(3):
        j, k = (e + 1) % 3, (e + 2) % 3
        Ne = _cross(a[j], a[k])
        N.append(Ne)
        Nn2 = _dot(Ne, Ne)
        Nn.append(torch.sqrt(torch.where(Nn2 > 0, Nn2, 1.0)) * (Nn2 > 0))  # (no NaN gradient at 0)
        dots.append(_dot(a[j], a[k]))
        s.append(_dot(Ne, nrm))
    return {"R": R, "h": _dot(a[0], nrm), "N": N, "Nn": Nn, "dots": dots, "s": s}


def _direct_face_weights(q: dict, two_area: torch.Tensor) -> list[torch.Tensor]:
    """Face weights ``w_i^T = N_i . m / det`` in the direct vector form, ``(T, n)`` each."""
    R, N, Nn, dots = q["R"], q["N"], q["Nn"], q["dots"]
    m = [torch.zeros_like(q["h"]) for _ in range(3)]
    for e in range(3):
        j, k = (e + 1) % 3, (e + 2) % 3
        theta = safe_atan2(Nn[e], dots[e])  # (finite derivatives at a corner of the face: R = 0)
        RR = R[j] * R[k]
        g = torch.where(Nn[e] > 0, safe_div(theta, Nn[e], Nn[e] > 0), safe_div(torch.ones_like(RR), RR, RR > 0)) * 0.5
        for c in range(3):
            m[c] = m[c] + g * N[e][c]
    det = two_area * q["h"]
    safe_det = torch.where(det != 0, det, 1.0)
    return [_dot(N[i], m) / safe_det for i in range(3)]


def _near_plane(q: dict) -> torch.Tensor:
    R = q["R"]
    return q["h"].abs() < SPLIT_FORM_RATIO * torch.minimum(torch.minimum(R[0], R[1]), R[2])


def _on_cage(q: dict, data: TriangleCageData) -> torch.Tensor:
    """``(T, n)`` mask: the point lies on the (closed) face, within the on-cage tolerance."""
    tol, s, R = data.tol, q["s"], q["R"]
    inside = (s[0] >= -tol * data.edge_len[0]) & (s[1] >= -tol * data.edge_len[1]) & (s[2] >= -tol * data.edge_len[2])
    near_vertex = torch.minimum(torch.minimum(R[0], R[1]), R[2]) <= tol
    return ((q["h"].abs() <= tol) & inside) | near_vertex


def _far_field_weights(x: torch.Tensor, h: torch.Tensor, face: torch.Tensor, data: TriangleCageData) -> torch.Tensor:
    """Face weights ``h * sum_q c_qi / |p_q - x|^4`` by quadrature, for ``M`` point–face pairs.

    Args:
        x: ``(M, 3)`` points; h: ``(M,)`` their distances to the faces' planes; face: ``(M,)`` face ids.

    Returns:
        ``(M, 3)`` weights of the faces' corners.
    """
    d = data.far_nodes.index_select(0, face) - x[:, None, :]  # (M, Q, 3)
    r2 = (d * d).sum(dim=-1)
    return h[:, None] * torch.einsum("mq,mqi->mi", 1.0 / (r2 * r2), data.far_coef.index_select(0, face))


def face_weights(
    x: torch.Tensor,
    data: TriangleCageData,
    far_field: bool | str = True,
    q: dict | None = None,
    singular: list[torch.Tensor] | None = None,
) -> tuple[list[torch.Tensor], dict]:
    """Per-face corner weights ``w_i^T`` of a chunk of points (eager: the stable form is evaluated
    only on the point–face pairs that need it). Points on a face get non-finite values there: the
    caller handles them (``mvc3d_chunk`` replaces them by the interpolating values).

    Args:
        x: ``(n, 3)`` points.
        data: the triangles' constants.
        far_field: redo faces seen small by quadrature where the face weights cancel (only
            meaningful when the triangles form a closed cage); ``"always"``: for every point
            (the triangles are part of a closed cage, such as a triquad cage's triangles, whose
            own sum does not show the cancellation).
        q: the pair terms of ``x`` when the caller has them (:func:`_pair_terms`).
        singular: an empty list to receive, as three ``(T, n)`` tensors, the coefficients ``c_i``
            of the ``c_i / h`` terms of faces around the points' feet, which the weights returned
            then leave out (see :func:`_stable_face_weights`).

    Returns:
        ``(w, q)``: three ``(T, n)`` tensors (corner ``i`` of every face) and the pair terms.
    """
    T, n = data.tri.shape[0], x.shape[0]
    q = _pair_terms(x, data) if q is None else q
    w = _direct_face_weights(q, data.two_area)
    near = _near_plane(q)
    if singular is not None:
        singular.extend(torch.zeros_like(q["h"]) for _ in range(3))
    if bool(near.any()):
        idx = torch.nonzero(near.reshape(-1)).squeeze(1)
        face = torch.div(idx, n, rounding_mode="floor")

        def pick(t: torch.Tensor) -> torch.Tensor:
            return t.reshape(-1).index_select(0, idx)

        gram = data.gram.index_select(0, face)
        ws = _stable_face_weights(
            pick(q["h"]),
            [pick(t) for t in q["s"]],
            [pick(t) for t in q["dots"]],
            [pick(t) for t in q["R"]],
            [data.edge_len[e, :, 0].index_select(0, face) for e in range(3)],
            [[gram[:, i, e] for e in range(3)] for i in range(3)],
            data.two_area[:, 0].index_select(0, face),
            sing := ([] if singular is not None else None),
        )
        for i in range(3):
            w[i] = w[i].reshape(-1).index_put((idx,), ws[i]).reshape(T, n)
            if singular is not None:
                singular[i] = singular[i].reshape(-1).index_put((idx,), sing[i]).reshape(T, n)
    # Where the total weight is much smaller than its parts (far outside the cage), the rounding
    # errors of the vector form on faces seen small are amplified: integrate those by quadrature.
    if not far_field:
        return w, q
    total = w[0] + w[1] + w[2]
    if singular is not None:
        h = torch.where(q["h"] != 0, q["h"], 1.0)
        total = total + (singular[0] + singular[1] + singular[2]) / h
    cancels = total.abs().sum(dim=0) > (0.0 if far_field == "always" else CANCELLATION_RATIO) * total.sum(dim=0).abs()
    R = q["R"]
    rmin = torch.minimum(torch.minimum(R[0], R[1]), R[2])
    # (faces seen below 1/FAR_ALWAYS_RATIO of their distance: the vector form's error eps (r / edge)^3 can
    # hide the cancellation from the test above, so they always take the rule)
    ratio = PART_FAR_FIELD_RATIO if far_field == "always" else FAR_FIELD_RATIO
    far = (data.longest < ratio * rmin) & (cancels | (data.longest * FAR_ALWAYS_RATIO < rmin))
    if bool(far.any()):
        idx = torch.nonzero(far.reshape(-1)).squeeze(1)
        face, col = torch.div(idx, n, rounding_mode="floor"), idx % n
        wf = _far_field_weights(x.index_select(0, col), q["h"].reshape(-1).index_select(0, idx), face, data)
        for i in range(3):
            w[i] = w[i].reshape(-1).index_put((idx,), wf[:, i]).reshape(T, n)
    return _thin_face_weights(x, data, w, q, singular), q


def _thin_face_weights(
    x: torch.Tensor, data: TriangleCageData, w: list[torch.Tensor], q: dict, singular: list[torch.Tensor] | None
) -> list[torch.Tensor]:
    """``w`` with the pairs of thin faces seen from a few widths (:func:`._thin_triangle.thin_pairs`)
    replaced by the swept form of ``h int Gamma_i / r^4`` (:func:`._thin_triangle.thin_triangle_mvc`):
    the vector form's terms there are ``length / width`` times the face's share and cancel, and its
    derivatives with respect to the corners lost ``eps (length / width)^2``."""
    if data.thin.numel() == 0:
        return w
    T, n = data.tri.shape[0], x.shape[0]
    p = data.vertices.T[data.tri[data.thin]]  # (k, 3, 3)
    a = p[:, None] - x[None, :, None, :]  # (k, n, 3, 3)
    sel = thin_pairs(a, data.two_area[data.thin].expand(-1, n))
    if not bool(sel.any()):
        return w
    kf, col = torch.nonzero(sel, as_tuple=True)
    face = data.thin[kf]
    idx = face * n + col
    wt = thin_triangle_mvc(a[kf, col], q["h"][face, col], data.two_area[face, 0])
    for i in range(3):
        w[i] = w[i].reshape(-1).index_put((idx,), wt[:, i]).reshape(T, n)
        if singular is not None:
            singular[i] = singular[i].reshape(-1).index_put((idx,), torch.zeros_like(wt[:, i])).reshape(T, n)
    return w


def _divide_h_out(w: list[torch.Tensor], sing: list[torch.Tensor], h: torch.Tensor) -> list[torch.Tensor]:
    """``h* (w_i + c_i / h)`` per point–face pair, with ``h*`` each point's ``h`` at the face of
    smallest ``|h|`` among those with ``c != 0`` (1 where none), the ``c_i / h`` terms of that face
    taken as ``c_i`` (no division, so no cancellation under autograd); shapes ``(T, n)``."""
    hstar, is_best = nearest_where((sing[0] != 0) | (sing[1] != 0) | (sing[2] != 0), h)
    safe_h = torch.where(h != 0, h, 1.0)
    ratio = torch.where(is_best, 1.0, hstar / safe_h)
    return [hstar * w[i] + sing[i] * ratio for i in range(3)]


def _gathered_weights(
    x: torch.Tensor, data: TriangleCageData, far: bool | str, scaled: bool, q: dict | None = None
) -> torch.Tensor:
    """Unnormalised weights ``(V, n)`` of points ``x`` ``(n, 3)`` (their non-finite columns where a
    point is on a face: the caller replaces them), :func:`face_weights` gathered per vertex."""
    sing: list[torch.Tensor] | None = [] if scaled else None
    w, qw = face_weights(x, data, far_field=far, q=q, singular=sing)
    if sing is not None:
        w = _divide_h_out(w, sing, qw["h"])
    W = torch.zeros((data.vertices.shape[1], x.shape[0]), dtype=x.dtype, device=x.device)
    for i in range(3):
        W.index_add_(0, data.tri[:, i], w[i])
    return W


def mvc3d_chunk(
    x: torch.Tensor, data: TriangleCageData, scaled: bool = False, part: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """Unnormalised mean value weights of a chunk of points.

    Args:
        x: ``(n, 3)`` points.
        data: the cage constants.
        scaled: return the weights of each point times ``h``, its distance to the plane of the
            face around its foot point nearest to it (where there is one within the split form's
            range), with that face's ``c_i / h`` terms taken as ``c_i``: the same coordinates
            once normalised, but their derivatives no longer cancel next to a face (the weights
            and their total both grow like ``1 / h`` there; autograd of the ratio lost ``eps / h``).
        part: the triangles are part of a closed cage (a triquad cage's): faces seen small take
            the far-field rule for every point (``face_weights(far_field="always")``).

    Returns:
        ``(W, on_cage)``: weights ``(V, n)`` (not yet normalised) and a ``(n,)`` bool mask of the
        points on the cage, whose columns of ``W`` hold their final (interpolating) coordinates.
    """
    V, n = data.vertices.shape[1], x.shape[0]
    far = "always" if part else True
    graph = records_graph(x, data.vertices)
    with torch.no_grad() if graph else contextlib.nullcontext():
        q = _pair_terms(x, data)
        # Points on the cage: barycentric coordinates in a face that contains them.
        on_face = _on_cage(q, data)
        on_cage = on_face.any(dim=0)
    any_on = bool(on_cage.any())
    if graph:
        # The pair terms above, of every face, carry no graph: the weights are recomputed with it,
        # and the interpolant of a point on the cage from its own face. The regular formula is
        # singular on the cage: it is evaluated on the points off the cage only, so that no
        # discarded value carries a non-finite derivative (NaN through torch.where) and the points
        # on the cage cost only their interpolant. (Evaluating it at a stand-in point far outside,
        # as before, took the far-field quadrature on every face: 100 times an ordinary point's
        # cost.)
        if not any_on:
            W = _gathered_weights(x, data, far, scaled)
        else:
            off = torch.nonzero(~on_cage).squeeze(1)
            W = torch.zeros((V, n), dtype=x.dtype, device=x.device)
            if off.numel():
                W = W.index_copy(1, off, _gathered_weights(x.index_select(0, off), data, far, scaled))
    else:
        W = _gathered_weights(x, data, far, scaled, q)
    if any_on:
        cols = torch.nonzero(on_cage).squeeze(1)
        # the largest face holding each point: its barycentric values are the best conditioned (of
        # areas within AREA_TIE, the first: argmax of the boolean takes the first True)
        area = on_face[:, cols] * data.two_area  # (T, m)
        f = (area >= area.amax(dim=0) * (1 - AREA_TIE)).to(torch.uint8).argmax(dim=0)
        if graph:  # (s of that face alone, as _pair_terms computes it: n . (a_j x a_k))
            xt = x.index_select(0, cols).T  # (3, m)
            a = [tuple(data.vertices[c].index_select(0, data.tri[f, i]) - xt[c] for c in range(3)) for i in range(3)]
            nrm = tuple(data.normal[c].reshape(-1).index_select(0, f) for c in range(3))
            s_on = [_dot(_cross(a[(e + 1) % 3], a[(e + 2) % 3]), nrm) for e in range(3)]
        else:
            s_on = [q["s"][i][f, cols] for i in range(3)]
        s_face = torch.stack(s_on)  # (3, m)
        # (clamped at 0 for the values; the derivatives are the face's interpolant's whatever the sign
        # of a coordinate that rounds to either side of 0 on an edge, as the native kernels' are)
        bary = s_face + (s_face.clamp_min(0.0) - s_face).detach() if graph else s_face.clamp_min(0.0)
        at_vertex = torch.stack([q["R"][i][f, cols] for i in range(3)]) <= data.tol
        bary = torch.where(at_vertex.any(dim=0, keepdim=True), at_vertex.to(bary.dtype), bary)
        bary = bary / bary.sum(dim=0, keepdim=True)
        Wc = torch.zeros((V, cols.shape[0]), dtype=x.dtype, device=x.device)
        Wc = Wc.scatter(0, data.tri[f].T, bary)
        W = W.index_copy(1, cols, Wc)
    return W, on_cage
