"""A small CPU splat renderer for pictures and tests: project, sort, alpha-composite.

It follows the reference rasteriser's model in a few dozen lines of torch (16 x 16 pixel tiles,
each compositing the Gaussians whose 3-sigma footprint touches it): a pinhole camera; each
Gaussian's 2D covariance ``W J Sigma J^T W^T`` from the perspective Jacobian, dilated by 0.3
pixel^2; colour ``max(0, c(d) + 1/2)`` with ``d`` the direction from the camera to the centre;
opacity ``sigmoid(logit) exp(-q / 2)`` capped at 0.99; front-to-back compositing
``C = sum_i c_i a_i prod_{j<i} (1 - a_j)`` over a background. Meant for a few thousand Gaussians and
images of a few hundred pixels (docs pictures, examples); use a real rasteriser for scenes.
"""

from __future__ import annotations

import math

import torch

from torchcage.splats.sh import eval_sh

__all__ = ["Camera", "render"]


class Camera:
    """A pinhole camera looking from ``eye`` at ``target`` (``up`` roughly up), ``fov`` degrees
    vertically, ``width x height`` pixels.

    Examples:
        >>> from torchcage.splats.render import Camera
        >>> cam = Camera(eye=(0, 0, 5), target=(0, 0, 0), width=64, height=48)
        >>> cam.focal > 0
        True
    """

    def __init__(
        self,
        eye: tuple[float, float, float],
        target: tuple[float, float, float] = (0.0, 0.0, 0.0),
        up: tuple[float, float, float] = (0.0, 1.0, 0.0),
        *,
        fov: float = 40.0,
        width: int = 256,
        height: int = 192,
    ) -> None:
        e, t, u = (torch.tensor(a, dtype=torch.float64) for a in (eye, target, up))
        fwd = torch.nn.functional.normalize(t - e, dim=0)
        right = torch.nn.functional.normalize(torch.linalg.cross(fwd, u), dim=0)
        down = torch.linalg.cross(fwd, right)
        self.eye = e
        self.rotation = torch.stack([right, down, fwd])  # world -> camera (x right, y down, z forward)
        self.width, self.height = width, height
        self.focal = 0.5 * height / math.tan(math.radians(fov) / 2)

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Camera-space points ``(N, 3)`` and pixel coordinates ``(N, 2)`` of world points ``(N, 3)``."""
        cam = (points.to(torch.float64) - self.eye) @ self.rotation.T
        z = cam[:, 2].clamp_min(1e-9)
        px = torch.stack(
            [self.focal * cam[:, 0] / z + self.width / 2, self.focal * cam[:, 1] / z + self.height / 2], dim=-1
        )
        return cam, px


def render(
    means: torch.Tensor,
    covariances: torch.Tensor,
    sh: torch.Tensor,
    opacity_logits: torch.Tensor,
    camera: Camera,
    *,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    tile: int = 16,
) -> torch.Tensor:
    """An image ``(H, W, 3)`` in [0, 1] of Gaussians ``means (N, 3)``, ``covariances (N, 3, 3)``,
    ``sh (N, K, 3)``, ``opacity_logits (N,)``.

    Examples:
        >>> import torch
        >>> from torchcage.splats import GaussianScene
        >>> from torchcage.splats.render import Camera, render
        >>> s = GaussianScene.random(200, degree=1)
        >>> img = render(s.means, s.covariances(), s.sh, s.opacity_logits, Camera((0, 0, 4), width=32, height=24))
        >>> tuple(img.shape)
        (24, 32, 3)
    """
    with torch.no_grad():
        cam, px = camera.project(means)
        keep = cam[:, 2] > 1e-3 * camera.focal / max(camera.width, camera.height)
        cam, px = cam[keep], px[keep]
        cov = camera.rotation @ covariances[keep].to(torch.float64) @ camera.rotation.T
        x, y, z = cam.unbind(-1)
        f = camera.focal
        Jp = torch.zeros(cam.shape[0], 2, 3, dtype=torch.float64)
        Jp[:, 0, 0], Jp[:, 0, 2] = f / z, -f * x / (z * z)
        Jp[:, 1, 1], Jp[:, 1, 2] = f / z, -f * y / (z * z)
        cov2 = Jp @ cov @ Jp.transpose(-1, -2) + 0.3 * torch.eye(2, dtype=torch.float64)
        det = cov2[:, 0, 0] * cov2[:, 1, 1] - cov2[:, 0, 1] ** 2
        inv = torch.stack([cov2[:, 1, 1], -cov2[:, 0, 1], cov2[:, 0, 0]], dim=-1) / det[:, None]  # a, b, c
        dirs = torch.nn.functional.normalize(means[keep].to(torch.float64) - camera.eye, dim=-1)
        colour = (eval_sh(sh[keep].to(torch.float64), dirs) + 0.5).clamp_min(0.0)
        opacity = torch.sigmoid(opacity_logits[keep].to(torch.float64))
        order = torch.argsort(z)  # front to back
        px, inv, colour, opacity = px[order], inv[order], colour[order], opacity[order]
        # 3-sigma footprints, and 16 x 16 pixel tiles that composite only the Gaussians touching them
        mid = 0.5 * (cov2[:, 0, 0] + cov2[:, 1, 1])
        lam = mid + torch.sqrt((mid * mid - det).clamp_min(0.0))
        radius = 3.0 * torch.sqrt(lam)
        H, W = camera.height, camera.width
        bg = torch.tensor(background, dtype=torch.float64)
        out = bg.expand(H, W, 3).clone()
        for y0 in range(0, H, tile):
            for x0 in range(0, W, tile):
                y1, x1 = min(y0 + tile, H), min(x0 + tile, W)
                hit = (
                    (px[:, 0] + radius > x0)
                    & (px[:, 0] - radius < x1)
                    & (px[:, 1] + radius > y0)
                    & (px[:, 1] - radius < y1)
                )
                if not bool(hit.any()):
                    continue
                vv, uu = torch.meshgrid(
                    torch.arange(y0, y1, dtype=torch.float64) + 0.5,
                    torch.arange(x0, x1, dtype=torch.float64) + 0.5,
                    indexing="ij",
                )
                d = torch.stack([uu, vv], dim=-1).reshape(-1, 1, 2) - px[hit][None]  # (P, n, 2)
                a, b, c = inv[hit].unbind(-1)
                q = a * d[..., 0] ** 2 + 2 * b * d[..., 0] * d[..., 1] + c * d[..., 1] ** 2
                alpha = (opacity[hit] * torch.exp(-0.5 * q)).clamp(max=0.99)
                alpha = torch.where(alpha < 1 / 255, 0.0, alpha)
                T = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], dim=1), dim=1)
                w = alpha * T
                img = w @ colour[hit] + (1 - w.sum(dim=1, keepdim=True)) * bg
                out[y0:y1, x0:x1] = img.reshape(y1 - y0, x1 - x0, 3)
        return out.clamp(0, 1).to(means.dtype if means.is_floating_point() else torch.float32)
