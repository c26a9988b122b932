"""Batched 3 x 3 decompositions with gradients that stay finite where the textbook ones are not.

- :func:`svd3`: ``M = U diag(S) V^T``. The usual backward divides by ``s_j^2 - s_i^2``, infinite for
  repeated singular values (an isotropic Gaussian, a similarity pose). Here ``1 / d`` becomes
  ``d / (d^2 + eps^2)`` with ``eps = 1e-10 s_max^2``: exact to 1e-20 relative wherever singular values
  differ by more than about ``1e-5 s_max``; finite (and the consistent gauge choice) where they meet.
- :func:`closest_rotation`: the rotation nearest ``J`` (the polar factor, with the reflection
  removed for ``det J < 0``), whose derivative ``U X V^T``, ``X_ij = (A_ij - A_ji) / (s_i + s_j)`` with
  signed singular values, only divides by sums; regularised the same way where two of them cancel
  (``J`` of rank 1 or 0: no rotation is nearer than another, and the gradient there is 0).
- :func:`matrix_to_quaternion`: ``(w, x, y, z)`` with ``w >= 0``, by the largest of four
  well-conditioned forms (no square root of a value near 0).
"""

from __future__ import annotations

from typing import Any

import torch

__all__ = ["closest_rotation", "matrix_to_quaternion", "svd3"]

_REL = 1e-10


def _svd(M: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    U, S, Vh = torch.linalg.svd(M)
    return U, S, Vh.transpose(-1, -2)


class _SVD3(torch.autograd.Function):
    @staticmethod
    def forward(M: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return _svd(M)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple, output: tuple) -> None:
        ctx.save_for_backward(*output)

    @staticmethod
    def backward(ctx: Any, gU: torch.Tensor, gS: torch.Tensor, gV: torch.Tensor) -> torch.Tensor:
        # Townsend's real SVD backward (square M): U [F o (U^T gU - gU^T U) S + diag(gS)
        # + S F o (V^T gV - gV^T V)] V^T, F_ij = 1 / (s_j^2 - s_i^2), regularised
        U, S, V = ctx.saved_tensors
        s2 = S * S
        d = s2[..., None, :] - s2[..., :, None]  # d_ij = s_j^2 - s_i^2
        eps = (_REL * s2.amax(dim=-1)[..., None, None]).clamp_min(torch.finfo(S.dtype).tiny)
        F = d / (d * d + eps * eps).clamp_min(torch.finfo(S.dtype).tiny)  # 0 where all vanish
        Sd = torch.diag_embed(S)
        inner = torch.diag_embed(gS if gS is not None else torch.zeros_like(S))
        if gU is not None:
            a = U.transpose(-1, -2) @ gU
            inner = inner + (F * (a - a.transpose(-1, -2))) @ Sd
        if gV is not None:
            b = V.transpose(-1, -2) @ gV
            inner = inner + Sd @ (F * (b - b.transpose(-1, -2)))
        return U @ inner @ V.transpose(-1, -2)


def svd3(M: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``U, S, V`` (not ``V^T``) of ``M`` ``(..., 3, 3)``, singular values descending, with a
    backward that is finite for repeated singular values.

    Examples:
        >>> import torch
        >>> from torchcage.splats.linalg import svd3
        >>> U, S, V = svd3(2 * torch.eye(3, dtype=torch.float64))
        >>> S.tolist()
        [2.0, 2.0, 2.0]
    """
    return _SVD3.apply(M)


class _ClosestRotation(torch.autograd.Function):
    @staticmethod
    def forward(J: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        U, S, V = _svd(J)
        # the nearest rotation: flip the direction of the smallest singular value when U V^T reflects
        flip = torch.linalg.det(U) * torch.linalg.det(V) < 0
        sign = torch.ones_like(S)
        sign[..., -1] = torch.where(flip, -1.0, 1.0).to(S.dtype)
        U = U * sign[..., None, :]
        return U @ V.transpose(-1, -2), U, S * sign, V

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple, output: tuple) -> None:
        _, U, S, V = output
        ctx.save_for_backward(U, S, V)
        ctx.mark_non_differentiable(U, S, V)

    @staticmethod
    def backward(ctx: Any, gQ: torch.Tensor, *_: Any) -> torch.Tensor:
        U, S, V = ctx.saved_tensors  # J = U diag(S) V^T with signed S, Q = U V^T
        B = U.transpose(-1, -2) @ gQ @ V
        den = S[..., :, None] + S[..., None, :]
        eps = _REL * S.abs().amax(dim=-1)[..., None, None]
        C = (B - B.transpose(-1, -2)) * den / (den * den + eps * eps).clamp_min(torch.finfo(S.dtype).tiny)
        return U @ C @ V.transpose(-1, -2)


def closest_rotation(J: torch.Tensor) -> torch.Tensor:
    """The rotation ``(..., 3, 3)`` nearest ``J`` ``(..., 3, 3)`` in the Frobenius norm: the polar
    factor ``U V^T`` of a proper ``J``, with the reflection removed otherwise. Differentiable, with a
    finite gradient wherever it is defined and a bounded one where ``J`` loses rank.

    Examples:
        >>> import math, torch
        >>> from torchcage.splats.linalg import closest_rotation
        >>> c, s = math.cos(0.4), math.sin(0.4)
        >>> R = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=torch.float64)
        >>> J = 3 * R @ torch.diag(torch.tensor([1.0, 2, 3], dtype=R.dtype))  # rotation times a stretch
        >>> bool(torch.allclose(closest_rotation(J @ R.T), torch.eye(3, dtype=R.dtype)))
        True
    """
    return _ClosestRotation.apply(J)[0]


def matrix_to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """Quaternions ``(..., 4)`` ``(w, x, y, z)``, ``w >= 0``, of rotation matrices ``(..., 3, 3)``."""
    m = R
    t = [
        1 + m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2],
        1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
        1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
        1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
    ]
    t = torch.stack(t, dim=-1)  # 4 w^2, 4 x^2, 4 y^2, 4 z^2
    r = torch.sqrt(t.clamp_min(0.25))  # only the largest is used, and it is >= 1
    a = m[..., 2, 1] - m[..., 1, 2]  # 4 w x
    b = m[..., 0, 2] - m[..., 2, 0]  # 4 w y
    c = m[..., 1, 0] - m[..., 0, 1]  # 4 w z
    d = m[..., 0, 1] + m[..., 1, 0]  # 4 x y
    e = m[..., 0, 2] + m[..., 2, 0]  # 4 x z
    f = m[..., 1, 2] + m[..., 2, 1]  # 4 y z
    cands = torch.stack(
        [
            torch.stack([r[..., 0] * r[..., 0], a, b, c], dim=-1) / (2 * r[..., 0:1]),
            torch.stack([a, r[..., 1] * r[..., 1], d, e], dim=-1) / (2 * r[..., 1:2]),
            torch.stack([b, d, r[..., 2] * r[..., 2], f], dim=-1) / (2 * r[..., 2:3]),
            torch.stack([c, e, f, r[..., 3] * r[..., 3]], dim=-1) / (2 * r[..., 3:4]),
        ],
        dim=-2,
    )  # (..., 4 candidates, 4)
    best = t.argmax(dim=-1)
    q = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4))[..., 0, :]
    return q * torch.where(q[..., :1] < 0, -1.0, 1.0).to(q.dtype)
