r"""Vector-Jacobian products of 3D mean value coordinates with respect to the points and the rest
cage's vertices in one pass, by hand-derived reverse mode of the direct vector form.

For a face with corners ``p_1, p_2, p_3`` and ``a_i = p_i - x`` (see ``kernel3d``):

.. math::
    N_e = a_{e+1} \times a_{e+2},\; d_e = a_{e+1}\cdot a_{e+2},\; \theta_e = \operatorname{atan2}(|N_e|, d_e),\;
    g_e = \frac{\theta_e}{2|N_e|},\; m = \sum_e g_e N_e,\; \det = a_1 \cdot N_1,\;
    w_i = \frac{N_i \cdot m}{\det},

and ``lam = w / W`` with ``W = sum_v w_v`` (corner weights gathered per vertex). Given the
cotangent ``gbar = dL/dlam`` ``(n, V)``, ``wbar_v = (gbar_v - gbar . lam) / W`` and, per face, the
adjoints run backwards through the lines above:

.. math::
    \bar m = \sum_i \bar w_i N_i / \det,\quad \bar N_i \mathrel{+}= \bar w_i\, m / \det,\quad
    \overline{\det} = -\sum_i \bar w_i w_i / \det,\quad
    \bar N_e \mathrel{+}= g_e \bar m + \bar n_e N_e / |N_e|,\quad \bar g_e = N_e\cdot\bar m,

    \bar\theta_e = \frac{\bar g_e}{2|N_e|},\quad
    \bar n_e = -\frac{\bar g_e \theta_e}{2|N_e|^2} + \bar\theta_e \frac{d_e}{|N_e|^2 + d_e^2},\quad
    \bar d_e = -\bar\theta_e \frac{|N_e|}{|N_e|^2 + d_e^2},

    \bar a_m \mathrel{+}= \overline{\det}\, N_m,\quad
    \bar a_{e+1} \mathrel{+}= \bar d_e a_{e+2} + a_{e+2}\times\bar N_e,\quad
    \bar a_{e+2} \mathrel{+}= \bar d_e a_{e+1} + \bar N_e \times a_{e+1}

(``d det / d a_m = N_m`` by the cyclic symmetry of the triple product). Then
``dL/dp_v = sum of abar over the corners at v`` and ``dL/dx = -sum_m abar_m``. The tests check this
against autograd of the torch kernel and with ``gradcheck``.

The direct form is accurate where the point is away from every face's support plane (its error is
``eps * r / |h|``), where the face weights do not cancel (inside the cage and near it), where no
face is seen very small and no thin face from a few widths (``torchcage._core.thin_triangle``); a point is
*regular* when all of that holds for every face. The caller
handles the other points (near a support plane, on the cage, far outside) with the torch kernel.
"""

from __future__ import annotations

import torch

from torchcage._core.thin_triangle import THIN_ASPECT, thin_pairs
from torchcage.families.mean_value.kernel3d import CANCELLATION_RATIO, FAR_ALWAYS_RATIO, SPLIT_FORM_RATIO, _cross, _dot

__all__ = ["direct_vjp"]

Vec = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def _axpy(acc: list[torch.Tensor], c: torch.Tensor, v: Vec) -> None:
    for k in range(3):
        acc[k] = acc[k] + c * v[k]


def direct_vjp(
    x: torch.Tensor, vertices: torch.Tensor, tri: torch.Tensor, gbar: torch.Tensor, tol: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``dL/dx`` and ``dL/dvertices`` of ``L = sum gbar * lam(x; vertices)`` for a chunk of points.

    Args:
        x: ``(n, 3)`` points.
        vertices: ``(V, 3)`` rest cage vertices (same dtype).
        tri: ``(T, 3)`` triangles of a closed, outward-oriented cage.
        gbar: ``(n, V)`` cotangent of the coordinates.
        tol: absolute on-cage tolerance (points closer to a vertex are not regular).

    Returns:
        ``(gx (n, 3), gP (V, 3), regular (n,) bool)``: the products over the regular points only
        (rows of ``gx`` of the other points are zero and they contribute nothing to ``gP``).

    Examples:
        >>> import torch, torchcage
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> x = torch.tensor([[0.1, 0.2, -0.3]], dtype=torch.float64)
        >>> gx, gP, ok = direct_vjp(x, cube.vertices, cube.triangles, torch.ones(1, 8, dtype=torch.float64), 1e-12)
        >>> bool(ok.all()), float(gx.abs().max()) < 1e-12  # the coordinates sum to one
        (True, True)
    """
    V, n = vertices.shape[0], x.shape[0]
    P = vertices.T[:, None, :]  # (3, 1, V)
    xt = x.T[:, :, None]  # (3, n, 1)
    a_all = P - xt  # (3, n, V)
    R_all = (a_all * a_all).sum(dim=0).sqrt()  # (n, V)
    # corner c of every face: (T, n) tensors
    a = [tuple(a_all[k].index_select(1, tri[:, i]).T for k in range(3)) for i in range(3)]
    R = [R_all.index_select(1, tri[:, i]).T for i in range(3)]
    N, nn, d, theta, g = [], [], [], [], []
    for e in range(3):
        j, k = (e + 1) % 3, (e + 2) % 3
        Ne = _cross(a[j], a[k])
        N.append(Ne)
        nn_e = _dot(Ne, Ne).sqrt()
        nn.append(nn_e)
        d_e = _dot(a[j], a[k])
        d.append(d_e)
        th = torch.atan2(nn_e, d_e)
        theta.append(th)
        g.append(th / (2 * torch.where(nn_e > 0, nn_e, 1.0)))
    m = [torch.zeros_like(R[0]) for _ in range(3)]
    for e in range(3):
        _axpy(m, g[e], N[e])
    det = _dot(a[0], N[0])
    p = vertices[tri]
    two_area = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1).norm(dim=-1)[:, None]  # (T, 1)
    longest = (p.roll(-1, dims=1) - p).norm(dim=-1).max(dim=1).values[:, None]
    rmin = torch.minimum(torch.minimum(R[0], R[1]), R[2])
    # regular pairs: away from the support plane (|h| >= SPLIT_FORM_RATIO rmin, h = det / 2A) and the corners
    ok = (det.abs() >= SPLIT_FORM_RATIO * rmin * two_area) & (rmin > tol) & (longest * FAR_ALWAYS_RATIO >= rmin)
    thin = torch.nonzero((longest[:, 0] ** 2 > THIN_ASPECT * two_area[:, 0]) & (two_area[:, 0] > 0)).flatten()
    if thin.numel():  # thin faces seen from a few widths: the direct form cancels (module _thin_triangle)
        at = p[thin][:, None] - x[None, :, None, :]  # (k, n, 3, 3)
        ok = ok.index_put((thin,), ok[thin] & ~thin_pairs(at, two_area[thin].expand(-1, n)))
    safe_det = torch.where(ok, det, 1.0)
    mt = tuple(m)
    w = [torch.where(ok, _dot(N[i], mt) / safe_det, 0.0) for i in range(3)]
    W = torch.zeros((V, n), dtype=x.dtype, device=x.device)
    for i in range(3):
        W.index_add_(0, tri[:, i], w[i])
    total = W.sum(dim=0)  # (n,)
    face_sum = w[0] + w[1] + w[2]
    regular = ok.all(dim=0) & (face_sum.abs().sum(dim=0) <= CANCELLATION_RATIO * total.abs()) & (total != 0)
    safe_total = torch.where(regular, total, 1.0)
    lam = W / safe_total  # (V, n)
    gT = gbar.T.to(x.dtype)  # (V, n)
    wbar_v = torch.where(regular, (gT - (gT * lam).sum(dim=0)) / safe_total, 0.0)  # (V, n)
    wbar = [wbar_v.index_select(0, tri[:, i]) * ok for i in range(3)]  # (T, n)
    inv_det = 1.0 / safe_det
    mbar = [torch.zeros_like(det) for _ in range(3)]
    for i in range(3):
        _axpy(mbar, wbar[i] * inv_det, N[i])
    mbar_t = tuple(mbar)
    det_bar = -(wbar[0] * w[0] + wbar[1] * w[1] + wbar[2] * w[2]) * inv_det
    Nbar = [[wbar[i] * inv_det * m[k] for k in range(3)] for i in range(3)]
    abar = [[det_bar * N[i][k] for k in range(3)] for i in range(3)]
    for e in range(3):
        j, k = (e + 1) % 3, (e + 2) % 3
        safe_nn = torch.where(nn[e] > 0, nn[e], 1.0)
        gbar_e = _dot(N[e], mbar_t)
        th_bar = gbar_e / (2 * safe_nn)
        r2 = nn[e] * nn[e] + d[e] * d[e]
        safe_r2 = torch.where(r2 > 0, r2, 1.0)
        n_bar = -gbar_e * theta[e] / (2 * safe_nn * safe_nn) + th_bar * d[e] / safe_r2
        d_bar = -th_bar * nn[e] / safe_r2
        coef = n_bar / safe_nn
        for c in range(3):
            Nbar[e][c] = Nbar[e][c] + g[e] * mbar[c] + coef * N[e][c]
        Nb = tuple(Nbar[e])
        cj, ck = _cross(a[k], Nb), _cross(Nb, a[j])
        for c in range(3):
            abar[j][c] = abar[j][c] + d_bar * a[k][c] + cj[c]
            abar[k][c] = abar[k][c] + d_bar * a[j][c] + ck[c]
    gP = torch.zeros((V, 3), dtype=x.dtype, device=x.device)
    gx = torch.zeros((n, 3), dtype=x.dtype, device=x.device)
    for i in range(3):
        ab = torch.stack(abar[i], dim=-1)  # (T, n, 3)
        gP.index_add_(0, tri[:, i], ab.sum(dim=1))
        gx = gx - ab.sum(dim=0)
    return gx, gP, regular
