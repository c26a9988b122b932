"""Deform a Gaussian splat scene with a cage: centres, covariances and view-dependent colours.

For a cage deformation ``y = f(x)`` with Jacobian ``J = df/dx`` at a Gaussian's centre (closed form
for mean value and Green coordinates), the Gaussian maps to first order to

- centre ``f(mu)``;
- covariance ``J Sigma J^T`` with ``Sigma = R diag(exp(2 s)) R^T``, computed as ``M M^T`` with
  ``M = J R diag(exp(s))`` (symmetric and positive semi-definite by construction); as scales and a
  rotation, the SVD ``M = U diag(sigma) V^T`` gives ``Sigma' = U diag(sigma^2) U^T``: log-scales
  ``log sigma`` and the rotation ``U`` (a column negated where ``det U < 0``);
- colour ``c'(d) = c(Q^T d)`` with ``Q`` the rotation nearest ``J`` (its polar factor): the
  spherical-harmonic coefficients rotated exactly (:func:`~torchcage.splats.sh.rotate_sh`).

A similarity pose ``V' = a R V + t`` moves every Gaussian exactly: ``J = a R``, covariance
``a^2 R Sigma R^T``, colour rotated by ``R``.

Degenerate Jacobians (a pose that collapses the cage locally): the covariance ``J Sigma J^T`` is
returned as it is (singular, finite); the log-scales are those of ``max(sigma, min_scale * s_max)``,
``s_max`` the Gaussian's largest rest standard deviation (``min_scale = 1e-6`` by default), so they
stay finite; rotations and colour rotations use the decompositions of
:mod:`torchcage.splats.linalg`, whose gradients stay finite where singular values meet.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import nn

from torchcage.cage import Cage
from torchcage.families import family, names
from torchcage.splats.linalg import closest_rotation, matrix_to_quaternion, svd3
from torchcage.splats.scene import GaussianScene, quaternion_to_matrix
from torchcage.splats.sh import rotate_sh

__all__ = ["DeformGaussians", "DeformedGaussians"]

#: The families with a closed-form Jacobian (the registry's ``jacobian``).
METHODS = names(lambda f: f.jacobian)


@dataclass
class DeformedGaussians:
    """The Gaussians at a pose ``(*P)``: ``means (*P, N, 3)``, ``covariances (*P, N, 3, 3)``,
    ``log_scales (*P, N, 3)``, ``rotations (*P, N, 4)`` (quaternions ``w, x, y, z``), ``sh (*P, N, K, 3)``
    and the Jacobians ``(*P, N, 3, 3)``; opacities do not change."""

    means: torch.Tensor
    covariances: torch.Tensor
    log_scales: torch.Tensor
    rotations: torch.Tensor
    sh: torch.Tensor
    jacobians: torch.Tensor


def _coordinates_module(cage: Cage, points: torch.Tensor, method: str, **kwargs) -> nn.Module:
    try:
        fam = family(method, METHODS, stacklevel=4)
    except ValueError as err:
        raise ValueError(f"{err} (a family with a closed-form Jacobian)") from None
    return fam.module()(cage.triangulated(), points, store_derivatives=1, **kwargs)


class DeformGaussians(nn.Module):
    """A splat scene embedded in a cage; ``forward(pose)`` deforms its Gaussians.

    Args:
        cage: the rest cage (3D; quads are split into triangles).
        scene: the Gaussians at rest.
        method: ``"mvc"`` (mean value coordinates) or ``"gc"`` (Green coordinates); or pass a
            ``module`` instead.
        module: a coordinate module over ``scene.means`` with ``forward(pose)`` and
            ``jacobian(pose)`` (e.g. ``MeanValueCoordinates(cage, scene.means, store_derivatives=1)``).
        chunk_size: Gaussians per step of the decompositions (bounds the temporaries).
        min_scale: floor of the deformed standard deviations, relative to each Gaussian's largest
            rest one (the log-scales of collapsed Gaussians stay finite).
        progress: passed to the coordinate module's computation.

    Shape:
        ``forward(pose)``: pose ``(*P, V, 3)`` -> :class:`DeformedGaussians` with ``(*P, N, ...)``.

    Examples:
        >>> import torch, torchcage
        >>> from torchcage.splats import DeformGaussians, GaussianScene
        >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj"))
        >>> scene = GaussianScene.random(50, degree=1, box=(-0.5, 0.5), dtype=torch.float64)
        >>> deform = DeformGaussians(cage, scene)
        >>> out = deform(cage.vertices * 2)  # scale by 2: covariances by 4
        >>> bool(torch.allclose(out.covariances, 4 * scene.covariances(), atol=1e-12))
        True
    """

    def __init__(
        self,
        cage: Cage,
        scene: GaussianScene,
        *,
        method: str = "mvc",
        module: nn.Module | None = None,
        chunk_size: int = 1 << 14,
        min_scale: float = 1e-6,
        progress: bool | Callable[[int, int], None] = False,
    ) -> None:
        super().__init__()
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be positive, got {chunk_size}")
        if not 0 < min_scale < 1:
            raise ValueError(f"min_scale must be in (0, 1), got {min_scale}")
        if cage.dim != 3:
            raise ValueError("Gaussian splats need a 3D cage")
        dtype = torch.float64
        self.coordinates = (
            module
            if module is not None
            else _coordinates_module(cage, scene.means.to(dtype), method, progress=progress)
        )
        if not hasattr(self.coordinates, "jacobian"):
            raise TypeError(f"{type(self.coordinates).__name__} has no jacobian(); use mean value or Green coordinates")
        embedded = getattr(self.coordinates, "num_points", scene.num_gaussians)
        if embedded != scene.num_gaussians:
            raise ValueError(
                f"the module embeds {embedded} points but the scene has {scene.num_gaussians} Gaussians; "
                "build it over scene.means"
            )
        self.chunk_size, self.min_scale = chunk_size, min_scale
        self.register_buffer("log_scales", scene.log_scales.to(dtype).clone())
        self.register_buffer("rest_rotations", quaternion_to_matrix(scene.rotations.to(dtype)))
        self.register_buffer("sh", scene.sh.to(dtype).clone())
        self.register_buffer("opacity_logits", scene.opacity_logits.clone())
        self._extra = dict(scene.extra)
        self._layout = scene.layout

    @property
    def num_gaussians(self) -> int:
        return int(self.log_scales.shape[0])

    def forward(self, pose: torch.Tensor) -> DeformedGaussians:
        # computed in the buffers' float64 (no float32 copies of the (N, V) buffers per call, and the
        # decompositions in full precision), returned in the pose's floating dtype
        out_dtype = pose.dtype if pose.is_floating_point() else torch.float64
        out = self._forward(pose.to(self.log_scales.dtype))
        if out_dtype == out.means.dtype:
            return out
        return DeformedGaussians(*(getattr(out, f).to(out_dtype) for f in DeformedGaussians.__dataclass_fields__))

    def _forward(self, pose: torch.Tensor) -> DeformedGaussians:
        means = self.coordinates(pose)
        J = self.coordinates.jacobian(pose)  # (*P, N, 3, 3)
        parts = [self._chunk(J[..., a : a + self.chunk_size, :, :], a) for a in range(0, J.shape[-3], self.chunk_size)]
        cov, logs, rot, sh = (torch.cat([p[k] for p in parts], dim=d) for k, d in enumerate((-3, -2, -2, -3)))
        return DeformedGaussians(means, cov, logs, rot, sh, J)

    def _chunk(self, J: torch.Tensor, start: int) -> tuple[torch.Tensor, ...]:
        n = J.shape[-3]
        dt = J.dtype
        R = self.rest_rotations[start : start + n].to(dt)
        s = self.log_scales[start : start + n].to(dt)
        M = J @ R * torch.exp(s)[..., None, :]  # J R diag(exp(s))
        cov = M @ M.transpose(-1, -2)
        U, sigma, _ = svd3(M)
        U = U * torch.where(torch.linalg.det(U) < 0, -1.0, 1.0).to(dt)[..., None, None]  # a proper rotation
        floor = self.min_scale * torch.exp(s.amax(dim=-1, keepdim=True))
        logs = torch.log(torch.maximum(sigma, floor))
        Q = closest_rotation(J)
        sh = rotate_sh(self.sh[start : start + n].to(dt), Q)
        return cov, logs, matrix_to_quaternion(U), sh

    def scene(self, pose: torch.Tensor) -> GaussianScene:
        """The deformed scene at one pose ``(V, 3)`` as a :class:`GaussianScene` (to write with
        :func:`~torchcage.splats.write_ply`; the rest scene's file layout and extra fields kept)."""
        if pose.ndim != 2:
            raise ValueError(f"scene() takes one pose (V, 3), got {tuple(pose.shape)}; index a batch of poses first")
        out = self.forward(pose)
        like = self.opacity_logits.dtype if self.opacity_logits.is_floating_point() else torch.float32
        return GaussianScene(
            means=out.means.detach().to(like),
            log_scales=out.log_scales.detach().to(like),
            rotations=out.rotations.detach().to(like),
            opacity_logits=self.opacity_logits,
            sh=out.sh.detach().to(like),
            extra=self._extra,
            layout=self._layout,
        )
