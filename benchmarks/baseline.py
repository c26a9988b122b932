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
