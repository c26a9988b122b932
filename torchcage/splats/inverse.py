"""Map points of the deformed space back to the rest space: the inverse of a cage deformation.

A radiance field trained at rest is queried in the deformed space through ``x = f^{-1}(y)``, with
``f(x) = sum_v w_v(x) v'_v`` (mean value coordinates) or the Green deformation. :func:`rest_points`
solves ``f(x) = y`` by Newton's method with the closed-form Jacobian ``J(x)``:

1. start: a coarse grid of rest points inside the cage (and the cage's vertices pulled slightly
   inwards) is mapped forward once per pose; each query starts at the rest point whose image is
   nearest, and, where Newton stops short (a fold of the deformation traps it in a local minimum
   of the residual), again from the next nearest ones;
2. iterate ``x <- x - a J^{-1} (f(x) - y)``, the step at most a quarter of the cage's size, ``a`` halved
   (up to 6 times) until the residual decreases; only unconverged points are evaluated;
3. stop at ``|f(x) - y| <= tol * size``; points that do not get there are reported, not hidden.

Derivatives (implicit function theorem): at the solution ``dx/dy = J^{-1}`` and ``dx/dV' = -J^{-1}
df/dV'``. They are attached by one Newton step taken with autograd on, of which only the derivatives
are kept (``x - (d - d.detach())``): the returned points are the same with and without a graph.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch

from torchcage.cage import Cage
from torchcage.geometry import inside_cage

__all__ = ["RestPoints", "rest_points"]


@dataclass
class RestPoints:
    """The result of :func:`rest_points` for queries ``(*P, M, 3)``.

    Attributes:
        points: ``(*P, M, 3)`` rest-space points (differentiable in the queries and the pose).
        converged: ``(*P, M)`` whether ``|f(x) - y| <= tol * size``.
        residual: ``(*P, M)`` ``|f(x) - y|`` relative to the cage's size.
        inside: ``(*P, M)`` whether the query lies inside the deformed cage (outside, ``f^{-1}`` is
            the continuation of the coordinates, not a point of the rest shape's interior).
        iterations: ``(*P, M)`` Newton iterations of the run that reached each point's answer.
    """

    points: torch.Tensor
    converged: torch.Tensor
    residual: torch.Tensor
    inside: torch.Tensor
    iterations: torch.Tensor


def _map(x: torch.Tensor, rest: Cage, pose: torch.Tensor, method: str, jacobian: bool = True):
    """``f(x)`` ``(M, 3)`` and (``jacobian``) ``J(x)`` ``(M, 3, 3)``; the coordinates are detached,
    ``f`` stays differentiable in ``pose``."""
    from torchcage.families.green.api import green_coordinates
    from torchcage.families.green.derivatives import green_derivatives
    from torchcage.families.mean_value.api import mean_value_coordinates
    from torchcage.families.mean_value.derivatives import mean_value_derivatives

    if method == "mvc":
        if not jacobian:
            return mean_value_coordinates(x, rest) @ pose, None
        lam, grad, _ = mean_value_derivatives(x, rest, order=1)
        return lam @ pose, torch.einsum("mvc,va->mac", grad, pose)
    from torchcage.families.green.stretch import stretched_triangle_normals

    sn = stretched_triangle_normals(rest.vertices, pose, rest.triangles)
    if not jacobian:
        phi, psi = green_coordinates(x, rest)
        return phi @ pose + psi @ sn, None
    phi, psi, gphi, gpsi = green_derivatives(x, rest, order=1)
    y = phi @ pose + psi @ sn
    J = torch.einsum("mvc,va->mac", gphi, pose) + torch.einsum("mtc,ta->mac", gpsi, sn)
    return y, J


def _start_samples(rest: Cage, grid: int) -> torch.Tensor:
    """Rest points inside the cage: a ``grid^3`` lattice in its box, and its vertices pulled 2% of
    the way to the centroid (``(S, 3)``)."""
    v = rest.vertices
    lo, hi = v.amin(dim=0), v.amax(dim=0)
    t = (torch.arange(grid, dtype=v.dtype, device=v.device) + 0.5) / grid
    g = torch.stack(torch.meshgrid(t, t, t, indexing="ij"), dim=-1).reshape(-1, 3) * (hi - lo) + lo
    g = g[inside_cage(g, rest)]
    pulled = v + 0.02 * (v.mean(dim=0) - v)
    return torch.cat([g, pulled[inside_cage(pulled, rest)]])


def _solve(J: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """``J^{-1} r`` per point, the pseudo-inverse where ``J`` is singular."""
    sol, info = torch.linalg.solve_ex(J, r[..., None])
    bad = (info != 0) | ~torch.isfinite(sol).all(dim=(-2, -1))
    if bool(bad.any()):
        sol = sol.clone()
        sol[bad] = torch.linalg.pinv(J[bad]) @ r[bad][..., None]
    return sol[..., 0]


def _newton(x: torch.Tensor, y: torch.Tensor, rest: Cage, pose: torch.Tensor, method: str, tol: float, max_iter: int):
    """Damped Newton from starts ``x`` ``(M, 3)`` towards ``f(x) = y``: ``(x, residual / size,
    iterations (M,))``; the iterations count where each point converged (or stopped)."""
    size = rest.scale
    x = x.clone()
    fx, J = _map(x, rest, pose, method)
    r = fx - y
    res = r.norm(dim=-1)
    iters = torch.zeros(x.shape[0], dtype=torch.long, device=x.device)
    active = res > tol * size
    it = 0
    while bool(active.any()) and it < max_iter:
        it += 1
        idx = torch.nonzero(active).flatten()
        iters[idx] = it
        step = _solve(J[idx], r[idx])
        length = step.norm(dim=-1, keepdim=True)
        step = step * (0.25 * size / length.clamp_min(1e-300)).clamp(max=1.0)
        alpha = torch.ones(idx.shape[0], 1, dtype=x.dtype, device=x.device)
        todo = torch.arange(idx.shape[0], device=x.device)
        for _ in range(7):  # a = 1, 1/2, ..., 1/64: accept where the residual decreases
            cand = x[idx[todo]] - alpha[todo] * step[todo]
            f_c, J_c = _map(cand, rest, pose, method)
            r_c = f_c - y[idx[todo]]
            better = r_c.norm(dim=-1) < res[idx[todo]]
            ok = idx[todo][better]
            x[ok], r[ok], J[ok], res[ok] = cand[better], r_c[better], J_c[better], r_c[better].norm(dim=-1)
            todo = todo[~better]
            if todo.numel() == 0:
                break
            alpha[todo] *= 0.5
        stuck = torch.zeros_like(active)
        stuck[idx[todo]] = True  # no decrease along the damped step: a fold's local minimum
        active = (res > tol * size) & ~stuck
    return x, res / size, iters


def _solve_pose(y: torch.Tensor, rest: Cage, pose: torch.Tensor, method: str, tol: float, max_iter: int,
                grid: int, restarts: int):  # fmt: skip
    """Newton from the rest sample whose image is nearest; points that stop short (a fold of the
    deformation traps them) start again from the next nearest samples, up to ``restarts`` times."""
    samples = _start_samples(rest, grid)
    images, _ = _map(samples, rest, pose, method, jacobian=False)
    k = min(restarts + 1, samples.shape[0])
    near = torch.cat([torch.cdist(c, images).topk(k, dim=1, largest=False).indices for c in y.split(8192)])
    x, res, iters = _newton(samples[near[:, 0]], y, rest, pose, method, tol, max_iter)
    for j in range(1, k):
        again = torch.nonzero(res > tol).flatten()
        if again.numel() == 0:
            break
        x2, res2, it2 = _newton(samples[near[again, j]], y[again], rest, pose, method, tol, max_iter)
        better = res2 < res[again]
        sel = again[better]
        x[sel], res[sel], iters[sel] = x2[better], res2[better], it2[better]
    return x, res, iters


def rest_points(
    deformed_points: torch.Tensor,
    cage: Cage,
    pose: torch.Tensor,
    *,
    method: str = "mvc",
    tol: float = 1e-10,
    max_iter: int = 20,
    grid: int = 16,
    restarts: int = 4,
    warn: bool = True,
) -> RestPoints:
    """Rest-space points ``x`` with ``f(x) = y`` for deformed-space points ``y``.

    Args:
        deformed_points: ``(*P, M, 3)`` or ``(M, 3)`` (shared by every pose) query points ``y``.
        cage: the rest cage (3D; quads are split into triangles).
        pose: ``(*P, V, 3)`` deformed cage vertices.
        method: ``"mvc"`` (mean value coordinates) or ``"gc"`` (Green coordinates): the deformation
            to invert, as :class:`~torchcage.MeanValueCoordinates` / :class:`~torchcage.GreenCoordinates`.
        tol: residual target relative to the rest cage's size.
        max_iter: Newton iterations at most.
        grid: lattice points per axis of the starting samples.
        restarts: for queries where Newton stops short (a fold of the deformation: a local minimum
            of the residual), new starts from the next nearest samples, at most this many.
        warn: warn with the counts of unconverged queries and of queries outside the deformed cage.

    Returns:
        :class:`RestPoints`; its ``points`` are differentiable with respect to ``deformed_points`` and
        ``pose`` (implicit function theorem).

    Examples:
        >>> import torch, torchcage
        >>> from torchcage.splats import rest_points
        >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj")).to(torch.float64)
        >>> pose = cage.vertices * torch.tensor([2.0, 1.0, 1.0], dtype=torch.float64)
        >>> out = rest_points(torch.tensor([[0.4, 0.1, 0.2]], dtype=torch.float64), cage, pose)
        >>> out.points.round(decimals=12).tolist(), bool(out.converged.all())
        ([[0.2, 0.1, 0.2]], True)
    """
    if method not in ("mvc", "gc"):
        raise ValueError(f"method must be 'mvc' or 'gc', got {method!r}")
    if cage.dim != 3 or cage.is_batched:
        raise ValueError("rest_points takes one 3D rest cage (its poses may be batched)")
    y_all = torch.as_tensor(deformed_points)
    if pose.device != cage.device or y_all.device != cage.device:
        raise ValueError(
            f"cage ({cage.device}), pose ({pose.device}) and deformed_points ({y_all.device}) must be on one device; "
            "move them with .to(device)"
        )
    rest = cage.triangulated().to(torch.float64)
    if pose.shape[-2:] != rest.vertices.shape:
        raise ValueError(f"pose must have shape (*P, {rest.num_vertices}, 3), got {tuple(pose.shape)}")
    if y_all.ndim < 2 or y_all.shape[-1] != 3:
        raise ValueError(f"deformed_points must have shape (*P, M, 3) or (M, 3), got {tuple(y_all.shape)}")
    batch = torch.broadcast_shapes(pose.shape[:-2], y_all.shape[:-2])
    poses = pose.expand(*batch, *pose.shape[-2:]).reshape(-1, *pose.shape[-2:])
    ys = y_all.expand(*batch, *y_all.shape[-2:]).reshape(-1, *y_all.shape[-2:])
    out = {k: [] for k in ("points", "converged", "residual", "inside", "iterations")}
    for P, y in zip(poses.unbind(0), ys.unbind(0), strict=True):
        P64, y64 = P.to(torch.float64), y.to(torch.float64)
        with torch.no_grad():
            x, res, it = _solve_pose(y64.detach(), rest, P64.detach(), method, tol, max_iter, grid, restarts)
            inside = inside_cage(y64.detach(), rest.with_vertices(P64.detach()))
        if torch.is_grad_enabled() and (P.requires_grad or y.requires_grad):
            # one Newton step with autograd on: the value stays (to the residual), the derivatives are
            # the implicit function theorem's
            fx, J = _map(x, rest, P64, method)
            d = _solve(J.detach(), fx - y64)
            x = x - (d - d.detach())  # the derivatives of that step, its value kept (unconverged points too)
        out["points"].append(x.to(y.dtype) if y.is_floating_point() else x)
        out["converged"].append(res <= tol)
        out["residual"].append(res)
        out["inside"].append(inside)
        out["iterations"].append(it)
    result = RestPoints(
        points=torch.stack(out["points"]).reshape(*batch, *y_all.shape[-2:]),
        converged=torch.stack(out["converged"]).reshape(*batch, y_all.shape[-2]),
        residual=torch.stack(out["residual"]).reshape(*batch, y_all.shape[-2]),
        inside=torch.stack(out["inside"]).reshape(*batch, y_all.shape[-2]),
        iterations=torch.stack(out["iterations"]).reshape(*batch, y_all.shape[-2]),
    )
    if warn:
        failed, outside = int((~result.converged).sum()), int((~result.inside).sum())
        total = result.converged.numel()
        if failed:
            warnings.warn(
                f"{failed} of {total} points did not converge to tol={tol:g} in {max_iter} Newton iterations "
                f"(worst residual {float(result.residual.max()):.2g} of the size); see RestPoints.converged",
                stacklevel=2,
            )
        if outside:
            warnings.warn(
                f"{outside} of {total} points lie outside the deformed cage: their rest points continue the "
                "coordinates outside the rest cage (see RestPoints.inside)",
                stacklevel=2,
            )
    return result
