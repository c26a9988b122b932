"""A 3D Gaussian splat scene as tensors (the fields of the standard 3D Gaussian splatting PLY)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch

__all__ = ["GaussianScene", "quaternion_to_matrix", "sh_degree"]


def sh_degree(num_coefficients: int) -> int:
    """The degree ``l`` of ``(l + 1)^2`` spherical-harmonic coefficients per colour channel.

    Raises:
        ValueError: a count that is not a square of 1..4.
    """
    for degree in range(4):
        if (degree + 1) ** 2 == num_coefficients:
            return degree
    raise ValueError(f"expected 1, 4, 9 or 16 spherical-harmonic coefficients per channel, got {num_coefficients}")


@dataclass
class GaussianScene:
    """Gaussians of a splat scene, as stored by 3D Gaussian splatting.

    Attributes:
        means: ``(N, 3)`` centres.
        log_scales: ``(N, 3)`` logarithms of the standard deviations along the local axes.
        rotations: ``(N, 4)`` quaternions ``(w, x, y, z)``, not necessarily normalised (the
            file's ``rot_0..3``).
        opacity_logits: ``(N,)`` opacities before the sigmoid.
        sh: ``(N, K, 3)`` spherical-harmonic colour coefficients, ``K = (degree + 1)^2``; ``sh[:, 0]``
            is the view-independent term (``f_dc``), ``sh[:, 1:]`` the rest in the order of the
            reference renderer's evaluation (degree 1: ``-y, z, -x`` ...).
        extra: other per-Gaussian fields of the file by name (``nx``, ``ny``, ``nz``, ...), ``(N,)``
            each, kept as read and written back unchanged.
        layout: how the file read stored the fields (written back the same way), or ``None``.

    Examples:
        >>> import torch
        >>> from torchcage.splats import GaussianScene
        >>> scene = GaussianScene.random(100, degree=1, seed=0)
        >>> scene.num_gaussians, scene.degree, tuple(scene.covariances().shape)
        (100, 1, (100, 3, 3))
    """

    means: torch.Tensor
    log_scales: torch.Tensor
    rotations: torch.Tensor
    opacity_logits: torch.Tensor
    sh: torch.Tensor
    extra: dict[str, torch.Tensor] = field(default_factory=dict)
    #: the layout of the file the scene was read from (:class:`~torchcage.splats.ply.PlyLayout`), if any
    layout: object | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        shapes = {
            "means": (self.means, (n, 3)),
            "log_scales": (self.log_scales, (n, 3)),
            "rotations": (self.rotations, (n, 4)),
            "opacity_logits": (self.opacity_logits, (n,)),
        }
        for name, (t, shape) in shapes.items():
            if tuple(t.shape) != shape:
                raise ValueError(f"GaussianScene.{name} must have shape {shape}, got {tuple(t.shape)}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"GaussianScene.sh must have shape ({n}, K, 3), got {tuple(self.sh.shape)}")
        sh_degree(self.sh.shape[1])
        for name, t in self.extra.items():
            if t.shape[0] != n:
                raise ValueError(f"extra field {name!r} has {t.shape[0]} rows for {n} Gaussians")

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    @property
    def degree(self) -> int:
        """The spherical-harmonic degree of the colours, 0..3."""
        return sh_degree(self.sh.shape[1])

    def rotation_matrices(self) -> torch.Tensor:
        """``(N, 3, 3)`` rotations of the normalised quaternions."""
        return quaternion_to_matrix(self.rotations)

    def covariances(self) -> torch.Tensor:
        """``(N, 3, 3)`` covariances ``R diag(exp(2 s)) R^T``."""
        R = self.rotation_matrices()
        return (R * torch.exp(2 * self.log_scales)[:, None, :]) @ R.transpose(-1, -2)

    def replace(self, **changes: torch.Tensor) -> GaussianScene:
        """A copy with some fields replaced (the others shared)."""
        return replace(self, **changes)

    def to(self, *args, **kwargs) -> GaussianScene:
        """Every field through ``Tensor.to`` (dtype and/or device)."""
        return GaussianScene(
            *(
                getattr(self, k).to(*args, **kwargs)
                for k in ("means", "log_scales", "rotations", "opacity_logits", "sh")
            ),
            extra={k: v.to(*args, **kwargs) for k, v in self.extra.items()},
            layout=self.layout,
        )

    @classmethod
    def random(
        cls,
        n: int,
        *,
        degree: int = 3,
        seed: int = 0,
        dtype: torch.dtype = torch.float32,
        box: tuple[float, float] = (-1.0, 1.0),
    ) -> GaussianScene:
        """``n`` random Gaussians in a box (tests, benchmarks, examples)."""
        g = torch.Generator().manual_seed(seed)
        lo, hi = box

        def rnd(*shape: int) -> torch.Tensor:
            return torch.rand(*shape, generator=g, dtype=torch.float64)

        return cls(
            means=(lo + (hi - lo) * rnd(n, 3)).to(dtype),
            log_scales=(torch.log(torch.tensor(0.02)) + 0.5 * torch.randn(n, 3, generator=g, dtype=torch.float64)).to(
                dtype
            ),
            rotations=torch.randn(n, 4, generator=g, dtype=torch.float64).to(dtype),
            opacity_logits=torch.randn(n, generator=g, dtype=torch.float64).to(dtype),
            sh=(0.5 * torch.randn(n, (degree + 1) ** 2, 3, generator=g, dtype=torch.float64)).to(dtype),
        )


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` of quaternions ``(..., 4)`` ``(w, x, y, z)``, normalised
    first (a zero quaternion gives the identity)."""
    n = torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    unit = torch.tensor([1.0, 0, 0, 0], dtype=q.dtype, device=q.device)
    q = torch.where(n > 0, q / n.clamp_min(torch.finfo(q.dtype).tiny), unit)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)
