"""Real spherical harmonics of degrees 0-3 as 3D Gaussian splatting evaluates them, and their exact
rotation.

A Gaussian's view-dependent colour is ``c(d) = sum_k sh_k Y_k(d)`` for unit view directions ``d``
(from the camera to the Gaussian), with the basis ``Y_k`` of the reference renderer (its constants,
signs and order: degree 1 is ``-C1 y, C1 z, -C1 x``). A deformation whose local rotation is ``R``
turns the colour function into ``c'(d) = c(R^T d)``. Each degree ``l`` spans a space that rotations
map to itself, so ``Y_l(R^T d) = X_l(R)^T Y_l(d)`` for a ``(2l+1) x (2l+1)`` matrix and the rotated
coefficients are ``sh'_l = X_l(R) sh_l``: exact, no resampling. ``X_l`` is found from 12 fixed
directions ``d_a`` (a Fibonacci set; the blocks' condition numbers are 1.03, 1.3 and 3.2): with
``B = Y_l(d_a)`` and ``T = Y_l(R^T d_a)``, ``X_l = B^+ T``, polynomial (and so differentiable) in ``R``.
"""

from __future__ import annotations

import math

import torch

__all__ = ["eval_sh", "rotate_sh", "sh_basis"]

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """The basis ``Y_k(d)``, ``(..., (degree + 1)^2)``, at unit directions ``dirs`` ``(..., 3)``.

    Examples:
        >>> import torch
        >>> from torchcage.splats.sh import sh_basis
        >>> sh_basis(torch.tensor([[0.0, 0.0, 1.0]]), 1)
        tensor([[0.2821, -0.0000, 0.4886, -0.0000]])
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"spherical-harmonic degree must be 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * x * y * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """The colour function ``sum_k sh_k Y_k(d)``: ``sh`` ``(..., K, C)``, ``dirs`` ``(..., 3)`` unit
    -> ``(..., C)`` (without the renderer's ``+ 0.5`` offset and clamp)."""
    from torchcage.splats.scene import sh_degree

    degree = sh_degree(sh.shape[-2])  # (raises on a count that is not (l + 1)^2)
    return (sh_basis(dirs, degree)[..., :, None] * sh).sum(dim=-2)


def _fibonacci(n: int) -> torch.Tensor:
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    r = torch.sqrt(1 - z * z)
    phi = math.pi * (3 - math.sqrt(5)) * i
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


_DIRECTIONS = 12  # Fibonacci directions shared by every degree: blocks conditioned 1.03, 1.3, 3.2
_PINV: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}


def _directions(degree: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The fixed directions ``(m, 3)`` and the pseudo-inverse ``(2l+1, m)`` of the degree's basis there."""
    if degree not in _PINV:
        d = _fibonacci(_DIRECTIONS)
        B = sh_basis(d, degree)[:, degree * degree :]
        _PINV[degree] = (d, torch.linalg.pinv(B))
    return _PINV[degree]


def rotation_blocks(R: torch.Tensor, degree: int) -> list[torch.Tensor]:
    """The matrices ``X_l(R)`` ``(..., 2l+1, 2l+1)`` for ``l = 1..degree`` of rotations ``R``
    ``(..., 3, 3)``: ``sh'_l = X_l sh_l`` gives ``c'(d) = c(R^T d)``. One basis evaluation at the
    rotated directions serves every degree."""
    d = _directions(1)[0].to(R.dtype).to(R.device)
    rotated = torch.einsum("ac,...cb->...ab", d, R)  # rows: (R^T d_a)^T = d_a^T R
    T = sh_basis(rotated, degree)  # (..., m, (degree + 1)^2)
    blocks = []
    for lvl in range(1, degree + 1):
        pinv = _directions(lvl)[1].to(R.dtype).to(R.device)
        blocks.append(torch.einsum("ia,...aj->...ij", pinv, T[..., lvl * lvl : (lvl + 1) ** 2]))
    return blocks


def rotate_sh(sh: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """Spherical-harmonic colours rotated by ``R``: ``c'(d) = c(R^T d)``, exactly.

    Args:
        sh: ``(..., N, K, C)`` coefficients, ``K = (degree + 1)^2`` (the 3D Gaussian splatting basis).
        R: ``(..., N, 3, 3)`` rotations (broadcast with ``sh``'s leading dimensions).

    Returns:
        ``(..., N, K, C)``; the degree-0 term is unchanged. Differentiable in ``sh`` and ``R``.

    Examples:
        >>> import math, torch
        >>> from torchcage.splats.sh import eval_sh, rotate_sh
        >>> sh = torch.randn(1, 16, 3, dtype=torch.float64)
        >>> c, s = math.cos(0.3), math.sin(0.3)
        >>> R = torch.tensor([[[c, -s, 0], [s, c, 0], [0, 0, 1]]], dtype=torch.float64)
        >>> d = torch.nn.functional.normalize(torch.randn(1, 3, dtype=torch.float64), dim=-1)
        >>> bool(torch.allclose(eval_sh(rotate_sh(sh, R), d), eval_sh(sh, d @ R), atol=1e-12))
        True
    """
    degree = math.isqrt(sh.shape[-2]) - 1
    if (degree + 1) ** 2 != sh.shape[-2] or degree > 3:
        raise ValueError(f"sh must have 1, 4, 9 or 16 coefficients on its second-to-last axis, got {sh.shape[-2]}")
    if degree == 0:
        return sh.expand(*torch.broadcast_shapes(sh.shape[:-2], R.shape[:-2]), *sh.shape[-2:])
    parts = [sh[..., :1, :].expand(*torch.broadcast_shapes(sh.shape[:-2], R.shape[:-2]), 1, sh.shape[-1])]
    for lvl, X in enumerate(rotation_blocks(R.to(sh.dtype), degree), start=1):
        parts.append(X @ sh[..., lvl * lvl : (lvl + 1) ** 2, :])
    return torch.cat(parts, dim=-2)
