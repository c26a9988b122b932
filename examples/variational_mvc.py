"""Pictures of the analytic MVC derivatives at work (2D, so that every panel is a plain plot).

1. ``variational_pose.png``: a bar-shaped polygon cage and a shape sampled inside it, posed from
   five positional constraints with fitted rotations and Hessian smoothness
   (:class:`torchcage.variational.VariationalMVC`): rest, constraints, result.
2. ``scalar_field.png``: a scalar field designed inside the cage from two value constraints, and
   the same with gradient constraints added (:func:`torchcage.variational.design_scalar_field`).
3. ``jacobian_field.png``: the local rotation and stretch of the posed deformation, from its
   Jacobian (:meth:`torchcage.MeanValueCoordinates.jacobian`): each small circle's image under
   ``J`` at a grid point, coloured by the rotation angle of ``J``'s polar decomposition.

Needs matplotlib (``pip install torchcage[examples]``).
Usage: ``python examples/variational_mvc.py [out_dir]`` (default: docs/images)
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import torch

import torchcage
from torchcage import functional as F
from torchcage.geometry import inside_polygon
from torchcage.variational import VariationalMVC, design_scalar_field

f64 = torch.float64


def bar_cage() -> torchcage.Cage:
    """A 4 x 1 bar polygon, counter-clockwise, with a vertex every 0.5 along the long sides."""
    xs = torch.arange(0, 4.01, 0.5, dtype=f64)
    bottom = torch.stack([xs, torch.zeros_like(xs)], 1)
    top = torch.stack([xs.flip(0), torch.ones_like(xs)], 1)
    return torchcage.Cage(torch.cat([bottom, top]))


def shape_points(cage: torchcage.Cage, step: float = 0.05) -> torch.Tensor:
    """A 'fish' inside the bar: points of an ellipse body with a tail, on a grid."""
    xs = torch.arange(0.1, 3.9, step, dtype=f64)
    ys = torch.arange(0.1, 0.9, step, dtype=f64)
    g = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)
    body = ((g[:, 0] - 2.2) / 1.6) ** 2 + ((g[:, 1] - 0.5) / 0.32) ** 2 < 1
    tail = (g[:, 0] < 0.8) & ((g[:, 1] - 0.5).abs() < 0.45 * (0.8 - g[:, 0]) + 0.05)
    return g[(body | tail) & inside_polygon(g, cage.vertices, cage.edges)]


def draw_cage(ax, v: torch.Tensor, **kw) -> None:
    c = torch.cat([v, v[:1]])
    ax.plot(c[:, 0], c[:, 1], "-o", ms=3, lw=1, **kw)


def pose(cage: torchcage.Cage):
    handles = torch.tensor([[0.3, 0.3], [0.3, 0.7], [3.7, 0.3], [3.7, 0.7], [2.0, 0.5]], dtype=f64)
    angle = torch.tensor(0.6, dtype=f64)
    rot = torch.stack([torch.stack([angle.cos(), -angle.sin()]), torch.stack([angle.sin(), angle.cos()])])
    targets = handles.clone()
    centre = torch.tensor([2.0, 0.5], dtype=f64)  # bend the right half about the middle, lift the middle a bit
    targets[2:4] = (handles[2:4] - centre) @ rot.T + centre + torch.tensor([-0.1, 0.3], dtype=f64)
    targets[4] = centre + torch.tensor([0.0, 0.15], dtype=f64)
    g = torch.Generator().manual_seed(0)
    inner = torch.rand(400, 2, generator=g, dtype=f64) * torch.tensor([3.8, 0.8], dtype=f64) + 0.1
    solver = VariationalMVC(cage, handles, inner[:40], inner[40:100], position_weight=1000.0, smoothness_weight=0.01)
    res = solver.solve(targets, rotations="fit", max_iter=300, tol=1e-8)
    print(f"pose: {res.iterations} solves, converged={res.converged}, largest handle residual "
          f"{float(res.positional_residual):.2e}")  # fmt: skip
    return handles, targets, res


def picture_pose(cage, pts, handles, targets, res, out: Path) -> None:
    mvc = torchcage.MeanValueCoordinates(cage, pts)
    moved = mvc(res.vertices)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, v, p, title in ((axes[0], cage.vertices, pts, "rest"), (axes[1], res.vertices, moved, "result")):
        ax.scatter(p[:, 0], p[:, 1], s=2, c="0.45")
        draw_cage(ax, v, color="tab:blue")
        ax.set_title(title)
        ax.set_aspect("equal")
    axes[0].scatter(handles[:, 0], handles[:, 1], c="tab:red", s=30, zorder=3, label="handles")
    axes[1].scatter(targets[:, 0], targets[:, 1], c="tab:red", s=30, zorder=3, label="targets")
    for ax in axes:
        ax.legend(loc="upper left", fontsize=8)
    fig.suptitle("Variational MVC: cage solved from 5 positional constraints, fitted rotations, Hessian smoothness")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def picture_field(cage, out: Path) -> None:
    xv = torch.tensor([[0.5, 0.5], [3.5, 0.5]], dtype=f64)
    values = torch.tensor([0.0, 1.0], dtype=f64)
    xg = torch.tensor([[1.5, 0.5], [2.5, 0.5]], dtype=f64)
    grads = torch.tensor([[0.0, 1.5], [0.0, -1.5]], dtype=f64)
    plain = design_scalar_field(cage, xv, values, smoothness_weight=1e-3)
    steered = design_scalar_field(cage, xv, values, xg, grads, gradient_weight=1.0, smoothness_weight=1e-3)
    xs = torch.linspace(0.0, 4.0, 400, dtype=f64)
    ys = torch.linspace(0.0, 1.0, 100, dtype=f64)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)
    inside = inside_polygon(grid, cage.vertices, cage.edges)
    lam = F.mean_value_coordinates(grid[inside], cage)
    fig, axes = plt.subplots(2, 1, figsize=(9, 5.2))
    for ax, res, title in ((axes[0], plain, "values only"), (axes[1], steered, "values + gradient constraints")):
        img = torch.full((grid.shape[0],), float("nan"), dtype=f64)
        img[inside] = lam @ res.values
        img = img.reshape(100, 400)
        ax.imshow(img, origin="lower", extent=(0, 4, 0, 1), cmap="viridis")
        ax.contour(xs, ys, img, levels=12, colors="w", linewidths=0.6)
        draw_cage(ax, cage.vertices, color="k")
        ax.scatter(xv[:, 0], xv[:, 1], c="tab:red", s=30, zorder=3)
        if res is steered:
            ax.quiver(xg[:, 0], xg[:, 1], grads[:, 0], grads[:, 1], color="tab:orange", scale=8, zorder=3)
        ax.set_title(f"{title}: value residual {float(res.value_residual):.1e}, "
                     f"gradient residual {float(res.gradient_residual):.2f}")  # fmt: skip
        ax.set_aspect("equal")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def picture_jacobian(cage, res, out: Path) -> None:
    xs = torch.arange(0.2, 3.85, 0.25, dtype=f64)
    ys = torch.arange(0.2, 0.85, 0.2, dtype=f64)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)
    mvc = torchcage.MeanValueCoordinates(cage, grid, store_derivatives=1)
    J = mvc.jacobian(res.vertices)  # (N, 2, 2)
    centre = mvc(res.vertices)
    U, S, Vh = torch.linalg.svd(J)
    Rot = U @ Vh
    angle = torch.atan2(Rot[:, 1, 0], Rot[:, 0, 0])
    t = torch.linspace(0, 2 * torch.pi, 40, dtype=f64)
    circle = 0.08 * torch.stack([t.cos(), t.sin()])  # (2, 40)
    fig, ax = plt.subplots(figsize=(8, 5))
    draw_cage(ax, res.vertices, color="0.6")
    cmap = plt.get_cmap("coolwarm")
    lo, hi = float(angle.min()), float(angle.max())
    for k in range(grid.shape[0]):
        e = J[k] @ circle + centre[k][:, None]
        ax.plot(e[0], e[1], color=cmap((float(angle[k]) - lo) / max(hi - lo, 1e-9)), lw=1.2)
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(lo * 57.3, hi * 57.3))
    fig.colorbar(sm, ax=ax, label="local rotation (degrees)", shrink=0.7)
    stretch = f"{float(S.min()):.2f}..{float(S.max()):.2f}"
    ax.set_title(f"Jacobian of the posed deformation: image of a circle; stretch {stretch}")
    ax.set_aspect("equal")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(out_dir: str = "docs/images") -> None:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cage = bar_cage()
    pts = shape_points(cage)
    handles, targets, res = pose(cage)
    picture_pose(cage, pts, handles, targets, res, out / "variational_pose.png")
    picture_field(cage, out / "scalar_field.png")
    picture_jacobian(cage, res, out / "jacobian_field.png")
    print(f"wrote {out / 'variational_pose.png'}, {out / 'scalar_field.png'}, {out / 'jacobian_field.png'}")


if __name__ == "__main__":
    main(*sys.argv[1:2])
