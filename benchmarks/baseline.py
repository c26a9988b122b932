"""A naive baseline for the benchmark: textbook mean value coordinates in eager torch.

The formula of Ju, Schaefer and Warren (2005) evaluated for every point-face pair at once, with
no chunking, no special cases and no care for precision: what a straightforward port looks like.
"""

from __future__ import annotations

import math

import torch


def naive_mean_value_coordinates(points: torch.Tensor, vertices: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    """``(N, 3)`` points, ``(V, 3)`` vertices, ``(T, 3)`` triangles -> ``(N, V)`` coordinates."""
    d = vertices[None] - points[:, None]  # (N, V, 3)
    r = d.norm(dim=-1)
    u = d / r[..., None]
    ut = u[:, triangles]  # (N, T, 3, 3)
    rt = r[:, triangles]
    l = torch.stack([(ut[:, :, (i + 1) % 3] - ut[:, :, (i + 2) % 3]).norm(dim=-1) for i in range(3)], -1)
    theta = 2 * torch.asin((l / 2).clamp(max=1))
    h = theta.sum(-1, keepdim=True) / 2
    c = torch.stack(
        [
            2 * torch.sin(h[..., 0]) * torch.sin(h[..., 0] - theta[..., i])
            / (torch.sin(theta[..., (i + 1) % 3]) * torch.sin(theta[..., (i + 2) % 3])) - 1
            for i in range(3)
        ],
        -1,
    )  # fmt: skip
    sign = torch.sign(torch.linalg.det(ut)).unsqueeze(-1)
    s = sign * torch.sqrt((1 - c * c).clamp(min=0))
    ws = []
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        num = theta[..., i] - c[..., j] * theta[..., k] - c[..., k] * theta[..., j]
        ws.append(num / (rt[..., i] * torch.sin(theta[..., j]) * s[..., k]))
    w = torch.stack(ws, -1)
    skip = (s.abs() < 1e-8).any(-1, keepdim=True) | (math.pi - h < 1e-8)
    w = torch.where(skip, 0.0, w)
    W = torch.zeros(points.shape[0], vertices.shape[0], dtype=points.dtype)
    for i in range(3):
        W.index_add_(1, triangles[:, i], w[..., i])
    return W / W.sum(-1, keepdim=True)


def textbook_vector_form(points: torch.Tensor, vertices: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    """The vector form of the same coordinates (``w_i = N_i . m / det``, Ju et al. / Thiery et al.
    Sec. 2.2) in plain torch ops, smooth off the faces' support planes: the formula that automatic
    differentiation differentiates in the derivative benchmark. ``(N, 3)`` -> ``(N, V)``."""
    a = vertices[triangles][None] - points[:, None, None, :]  # (N, T, 3, 3)
    N = [torch.linalg.cross(a[:, :, (e + 1) % 3], a[:, :, (e + 2) % 3], dim=-1) for e in range(3)]
    m = torch.zeros_like(N[0])
    for e in range(3):
        nn = N[e].norm(dim=-1, keepdim=True)
        theta = torch.atan2(nn, (a[:, :, (e + 1) % 3] * a[:, :, (e + 2) % 3]).sum(-1, keepdim=True))
        m = m + theta / (2 * nn) * N[e]
    det = (a[:, :, 0] * N[0]).sum(-1)
    w = torch.stack([(N[i] * m).sum(-1) / det for i in range(3)], -1).reshape(points.shape[0], -1)
    W = torch.zeros(points.shape[0], vertices.shape[0], dtype=points.dtype).index_add(1, triangles.reshape(-1), w)
    return W / W.sum(-1, keepdim=True)


def dense_batched_mean_value_coordinates(x: torch.Tensor, P: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """The batched dense formulation common in learning code (the Neural Cages pattern): the
    half-angle formula of Ju, Schaefer and Warren (2005) on every (shape, point, face) triple at
    once, differentiable by plain autograd with respect to points and rest cages.

    ``x`` ``(B, N, 3)``, ``P`` ``(B, V, 3)``, ``faces`` ``(F, 3)`` -> ``(B, N, V)``. Written here
    from the published formula (no special cases beyond a clamp that keeps ``sqrt`` real).
    """
    d = P[:, None] - x[:, :, None]  # (B, N, V, 3)
    r = d.norm(dim=-1)
    u = d / r[..., None]
    uf = u[:, :, faces]  # (B, N, F, 3, 3)
    rf = r[:, :, faces]
    nxt, prv = [1, 2, 0], [2, 0, 1]
    l = (uf[..., nxt, :] - uf[..., prv, :]).norm(dim=-1)  # edge opposite each corner, on the sphere
    th = 2 * torch.asin((l / 2).clamp(max=1))
    h = th.sum(-1, keepdim=True) / 2
    c = 2 * torch.sin(h) * torch.sin(h - th) / (torch.sin(th[..., nxt]) * torch.sin(th[..., prv])) - 1
    s = torch.sign(torch.linalg.det(uf))[..., None] * torch.sqrt((1 - c * c).clamp(min=1e-12))
    w = (th - c[..., nxt] * th[..., prv] - c[..., prv] * th[..., nxt]) / (rf * torch.sin(th[..., nxt]) * s[..., prv])
    W = torch.zeros(*x.shape[:2], P.shape[1], dtype=x.dtype, device=x.device)
    W = W.index_add(2, faces.reshape(-1), w.reshape(*w.shape[:2], -1))
    return W / W.sum(-1, keepdim=True)
