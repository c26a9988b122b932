"""Independent high-precision references (mpmath) for the coordinate kernels.

Written separately from the library's kernels: the 3D reference uses the half-angle (Floater)
form of the triangle weights, the 2D reference the tangent formula, both at 60 digits.
"""

from __future__ import annotations

import mpmath as mp
import torch

mp.mp.dps = 60


def _mpf(c):
    return c if isinstance(c, mp.mpf) else mp.mpf(float(c))


def _vec(p):
    return mp.matrix([_mpf(c) for c in p])


def _cross(a, b):
    return mp.matrix([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@mp.workdps(60)
def mvc3d_reference(x, vertices, triangles) -> list:
    """Mean value coordinates of one point (mpmath numbers), Floater-Kos-Reimers form:
    w_i += (beta_jk + beta_ij n_ij.n_jk + beta_ki n_ki.n_jk) / (2 e_i . n_jk) / r_i, with unit
    vectors e, beta the angle of each edge seen from x and n the unit normals of the planes
    through x and each edge. Accurate in 60-digit arithmetic wherever x is off the support planes."""
    xv = _vec(x)
    P = [_vec(p) - xv for p in vertices.tolist()]
    r = [mp.sqrt(_dot(p, p)) for p in P]
    e = [p / rr for p, rr in zip(P, r, strict=True)]
    w = [mp.mpf(0)] * len(P)
    for t in triangles.tolist():
        for c in range(3):
            i, j, k = t[c], t[(c + 1) % 3], t[(c + 2) % 3]

            def beta(a, b):
                return 2 * mp.asin(mp.sqrt(_dot(e[a] - e[b], e[a] - e[b])) / 2)

            def nrm(a, b):
                c_ = _cross(e[a], e[b])
                return c_ / mp.sqrt(_dot(c_, c_))

            njk, nij, nki = nrm(j, k), nrm(i, j), nrm(k, i)
            num = beta(j, k) + beta(i, j) * _dot(nij, njk) + beta(k, i) * _dot(nki, njk)
            w[i] += num / (2 * _dot(e[i], njk)) / r[i]
    total = sum(w)
    return [wi / total for wi in w]


@mp.workdps(60)
def mvc2d_reference(x, vertices) -> list:
    """2D mean value coordinates of one point for a counter-clockwise polygon given in order."""
    xv = [_mpf(c) for c in x]
    P = [[mp.mpf(float(a)) - xv[0], mp.mpf(float(b)) - xv[1]] for a, b in vertices.tolist()]
    n = len(P)
    r = [mp.sqrt(p[0] ** 2 + p[1] ** 2) for p in P]
    ang = []
    for i in range(n):
        a, b = P[i], P[(i + 1) % n]
        ang.append(mp.atan2(a[0] * b[1] - a[1] * b[0], a[0] * b[0] + a[1] * b[1]))
    w = [(mp.tan(ang[i - 1] / 2) + mp.tan(ang[i] / 2)) / r[i] for i in range(n)]
    total = sum(w)
    return [wi / total for wi in w]


def to_tensor(values) -> torch.Tensor:
    return torch.tensor([float(v) for v in values], dtype=torch.float64)


@mp.workdps(60)
def mvc_derivatives_reference(x, coordinates, scale: float) -> tuple[list, list]:
    """Gradients ``[i][c]`` and Hessians ``[i][c][d]`` (floats) of ``coordinates(x)`` (a function
    returning a list of mpmath numbers, e.g. a closure over :func:`mvc3d_reference`; ``x`` may hold
    mpmath numbers, to sit closer to a singular plane than float64 can) by central
    differences in 60-digit arithmetic with the step ``1e-12 * scale``: truncation error about
    ``1e-24`` relative to the scale on which the coordinates vary, rounding about ``1e-36``."""
    D = len(x)
    x0 = [c if isinstance(c, mp.mpf) else mp.mpf(float(c)) for c in x]
    step = mp.mpf(scale) * mp.mpf("1e-12")

    def f(offsets):
        y = list(x0)
        for c, s in offsets:
            y[c] += s * step
        return coordinates(y)

    f0 = f([])
    plus = [f([(c, 1)]) for c in range(D)]
    minus = [f([(c, -1)]) for c in range(D)]
    V = len(f0)
    grad = [[float((plus[c][i] - minus[c][i]) / (2 * step)) for c in range(D)] for i in range(V)]
    hess = [[[0.0] * D for _ in range(D)] for _ in range(V)]
    for c in range(D):
        for i in range(V):
            hess[i][c][c] = float((plus[c][i] - 2 * f0[i] + minus[c][i]) / step**2)
        for d in range(c + 1, D):
            pp, pm = f([(c, 1), (d, 1)]), f([(c, 1), (d, -1)])
            mp_, mm = f([(c, -1), (d, 1)]), f([(c, -1), (d, -1)])
            for i in range(V):
                val = float((pp[i] - pm[i] - mp_[i] + mm[i]) / (4 * step**2))
                hess[i][c][d] = hess[i][d][c] = val
    return grad, hess


def distance_to_triangles(points: torch.Tensor, vertices: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    """Euclidean distance ``(N,)`` from each point to a set of triangles (brute force, float64)."""
    p = vertices.to(torch.float64)[triangles]  # (T, 3, 3)
    x = points.to(torch.float64)[:, None, :]  # (N, 1, 3)
    best = torch.full((points.shape[0],), float("inf"), dtype=torch.float64)
    for i in range(3):  # the three edges
        a, b = p[:, i][None], p[:, (i + 1) % 3][None]
        ab = b - a
        t = (((x - a) * ab).sum(-1) / (ab * ab).sum(-1)).clamp(0, 1)
        best = torch.minimum(best, (x - a - t[..., None] * ab).norm(dim=-1).min(dim=1).values)
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True)
    h = ((x - p[:, 0][None]) * n[None]).sum(-1)  # (N, T)
    foot = x - h[..., None] * n[None]
    inside = torch.ones_like(h, dtype=torch.bool)
    for i in range(3):
        a, b = p[:, i][None], p[:, (i + 1) % 3][None]
        inside &= (torch.linalg.cross(b - a, foot - a, dim=-1) * n[None]).sum(-1) >= 0
    plane = torch.where(inside, h.abs(), torch.inf).min(dim=1).values
    return torch.minimum(best, plane)
