r"""Variational MVC: cage vertices and scalar fields from sparse constraints (Thiery, Tierny,
Boubekeur 2014, Sec. 8.2–8.3), built on the analytic gradients and Hessians of mean value
coordinates.

**Deformation** (:class:`VariationalMVC`). The deformation ``f(x) = sum_j lam_j(x) c_j`` of a cage
with unknown vertices ``C`` ``(V, D)`` has, at any point, the Jacobian ``C^T grad lam`` and the
Hessians ``sum_j H lam_j c_j``: all linear in ``C``. The energy

.. math::
    E(C) = w_P \sum_{i\in P} \|\lambda(x_i) C - \bar v_i\|^2
         + w_J \sum_{i\in J} \|C^T \nabla\lambda(x_i) - R_i\|_F^2
         + w_H \sum_{i\in H} \sum_a \|\textstyle\sum_j H\lambda_j(x_i)\, c_{ja}\|_F^2

is a linear least-squares problem whose matrix is the same for every coordinate and every
constraint set: it is factored once (Cholesky of the normal matrix) and every solve is a pair of
triangular solves, batched over constraint sets. Rotations ``R_i`` may be given, or fitted
(``rotations="fit"``): alternate the linear solve with the projection of each Jacobian onto the
nearest rotation (SVD, ``det = +1``), the local/global iteration of as-rigid-as-possible
methods, until the energy stops decreasing.

**Scalar fields** (:func:`design_scalar_field`, Sec. 8.2): values ``f`` at the cage vertices, from
value constraints ``sum_j lam_j(x_i) f_j = v_i`` and gradient constraints
``sum_j grad lam_j(x_i) f_j = g_i`` inside, with a smoothness term ``|L f|^2`` on the cage
(``L`` the cotangent Laplacian of a triangle cage, the second difference along a polygon, both
divided by the vertex areas / lengths). The field anywhere is then ``mean_value_coordinates(x) @ f``.

Both solvers add ``1e-12`` of the normal matrix's mean diagonal to it (``regularization``), so
that under-constrained problems still have a solution; the bias this causes is of that order.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from torchcage.cage import Cage
from torchcage.errors import PointsError
from torchcage.families.mean_value.api import mean_value_coordinates
from torchcage.families.mean_value.derivatives import mean_value_derivatives

__all__ = ["ScalarFieldResult", "VariationalMVC", "VariationalResult", "cotangent_laplacian", "design_scalar_field"]


@dataclass
class VariationalResult:
    """Result of :meth:`VariationalMVC.solve`. Shapes: ``B`` constraint sets (absent when the
    targets had no batch dimension), ``V`` cage vertices, ``K`` rotation points, ``D`` dims."""

    vertices: torch.Tensor  #: (*B, V, D) the solved cage
    rotations: torch.Tensor | None  #: (*B, K, D, D) the rotations used at the rotation points
    energy: torch.Tensor  #: (*B,) final energy
    positional_residual: torch.Tensor  #: (*B,) largest distance between a constrained point and its target
    iterations: int  #: linear solves done (1 without fitted rotations)
    converged: bool  #: every set's relative energy decrease fell below ``tol`` (True without fitting)
    history: list[torch.Tensor] = field(default_factory=list)  #: energies after each solve


def _normal_solver(M: torch.Tensor, regularization: float):
    """Factor ``M^T M + eps I`` once; returns ``solve(b (*, rows, k)) -> (*, V, k)``."""
    A = M.T @ M
    eps = regularization * float(A.diagonal().mean())
    A = A + eps * torch.eye(A.shape[0], dtype=A.dtype, device=A.device)
    L, info = torch.linalg.cholesky_ex(A)
    if int(info) != 0:
        raise RuntimeError("the constraint system is singular even after regularization; add constraints")

    def solve(b: torch.Tensor) -> torch.Tensor:
        return torch.cholesky_solve(M.T @ b, L)

    return solve


class VariationalMVC:
    """Solve for deformed cage vertices from positional, rotation and smoothness constraints.

    Args:
        cage: the rest cage (3D triangle cage or 2D polygon).
        handles: ``(P, D)`` points whose deformed positions will be prescribed.
        rotation_points: ``(K, D)`` points where the deformation should be a rotation (its
            Jacobian ``J`` close to ``R``: given, or fitted).
        smoothness_points: ``(S, D)`` points where the deformation's Hessians should vanish.
        position_weight: ``w_P``, the weight of the positional constraints.
        rotation_weight: ``w_J``, the weight of the rotation (Jacobian) constraints.
        smoothness_weight: ``w_H``; it multiplies the squared Hessians times the cage size
            squared, so that the three terms have the same units.
        regularization: relative Tikhonov term of the normal matrix (see the module docstring).

    All points must be off the cage; they are embedded once (analytic gradients and Hessians,
    float64), and the normal matrix is factored once.

    Examples:
        >>> import torch, torchcage
        >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> g = torch.Generator().manual_seed(0)
        >>> inside = lambda n: (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 1.6
        >>> solver = torchcage.variational.VariationalMVC(cage, inside(8), inside(12), inside(12))
        >>> R = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64)
        >>> res = solver.solve(solver.handles @ R.T + 1.0, rotations="fit")
        >>> bool((res.vertices - (cage.vertices @ R.T + 1.0)).abs().max() < 1e-8), res.converged
        (True, True)
    """

    def __init__(
        self,
        cage: Cage,
        handles: torch.Tensor,
        rotation_points: torch.Tensor | None = None,
        smoothness_points: torch.Tensor | None = None,
        *,
        position_weight: float = 1.0,
        rotation_weight: float = 1.0,
        smoothness_weight: float = 0.01,
        regularization: float = 1e-12,
    ) -> None:
        D = cage.dim
        dev, f64 = cage.device, torch.float64
        self.cage = cage
        self.dim = D
        self.handles = torch.as_tensor(handles, dtype=f64, device=dev).reshape(-1, D)
        if self.handles.shape[0] == 0:
            raise PointsError("VariationalMVC needs at least one handle (positional constraint)")
        empty = torch.zeros((0, D), dtype=f64, device=dev)
        rp = empty if rotation_points is None else torch.as_tensor(rotation_points, dtype=f64, device=dev)
        sp = empty if smoothness_points is None else torch.as_tensor(smoothness_points, dtype=f64, device=dev)
        self.rotation_points, self.smoothness_points = rp.reshape(-1, D), sp.reshape(-1, D)
        size = cage.scale
        self.weights = (position_weight, rotation_weight, smoothness_weight)
        self.A = mean_value_coordinates(self.handles, cage, dtype=f64)  # (P, V)
        V = cage.num_vertices
        self.G = (
            mean_value_derivatives(self.rotation_points, cage, 1)[1] if rp.numel() else torch.zeros(0, V, D, dtype=f64)
        )  # (K, V, D)
        self.H = (
            mean_value_derivatives(self.smoothness_points, cage, 2)[2]
            if sp.numel()
            else torch.zeros(0, V, D, D, dtype=f64)
        )  # (S, V, D, D)
        pos = position_weight**0.5 * self.A
        # rows (K * D, V): row (i, c) = d lam / d x_c at rotation point i
        rot = rotation_weight**0.5 * self.G.permute(0, 2, 1).reshape(-1, V)
        # rows (S * D * D, V): second derivatives, scaled to the units of positions
        smooth = smoothness_weight**0.5 * size * self.H.permute(0, 2, 3, 1).reshape(-1, V)
        self._M = torch.cat([pos, rot, smooth]).to(dev)
        self._solve = _normal_solver(self._M, regularization)
        # The first estimate of fitted rotations comes from a solve without the rotation rows.
        self._M0 = torch.cat([pos, smooth]).to(dev)
        self._solve0 = _normal_solver(self._M0, regularization)

    def _rhs(self, targets: torch.Tensor, rotations: torch.Tensor | None) -> torch.Tensor:
        """Right-hand sides ``(B, rows, D)`` for targets ``(B, P, D)`` and rotations ``(B, K, D, D)``."""
        wP, wJ, _ = self.weights
        B, D = targets.shape[0], self.dim
        parts = [wP**0.5 * targets]
        if self.G.shape[0]:
            K = self.G.shape[0]
            R = rotations if rotations is not None else torch.eye(D, dtype=targets.dtype).expand(B, K, D, D)
            parts.append(wJ**0.5 * R.transpose(-1, -2).reshape(B, -1, D))  # row (i, c), column a: R[a, c]
        if self.H.shape[0]:
            parts.append(targets.new_zeros(B, self.H.shape[0] * D * D, D))
        return torch.cat(parts, dim=1)

    def jacobians(self, vertices: torch.Tensor) -> torch.Tensor:
        """Jacobians ``(*, K, D, D)`` of the deformation by ``vertices`` ``(*, V, D)`` at the rotation points."""
        return torch.einsum("kvc,...va->...kac", self.G.to(vertices.dtype), vertices)

    def solve(
        self,
        targets: torch.Tensor,
        rotations: torch.Tensor | str | None = "fit",
        *,
        max_iter: int = 100,
        tol: float = 1e-10,
    ) -> VariationalResult:
        """Cage vertices for the handles' target positions.

        Args:
            targets: ``(P, D)`` or ``(B, P, D)``: deformed positions of the handles (a batch of
                constraint sets is solved at once).
            rotations: ``"fit"`` (unknown rotations, alternating with the linear solve), a tensor
                ``(K, D, D)`` / ``(B, K, D, D)`` of given Jacobians, or ``None`` (identity).
            max_iter: most linear solves when fitting rotations.
            tol: stop when every set's energy decreases by less than ``tol`` times its value
                (or falls below ``tol`` times the squared cage size).

        Returns:
            :class:`VariationalResult`.
        """
        t = torch.as_tensor(targets, dtype=torch.float64, device=self._M.device)
        single = t.ndim == 2
        if t.ndim not in (2, 3) or t.shape[-2:] != self.handles.shape:
            want = f"(*, {self.handles.shape[0]}, {self.dim})"
            raise ValueError(f"targets must have shape {want}, got {tuple(targets.shape)}")
        if not torch.isfinite(t).all():
            raise ValueError("targets contain NaN or inf")
        t = t[None] if single else t
        B, K, D = t.shape[0], self.G.shape[0], self.dim
        fit = isinstance(rotations, str)
        if fit and rotations != "fit":
            raise ValueError(f"rotations must be 'fit', a tensor or None, got {rotations!r}")
        R = None
        if not fit and rotations is not None:
            R = torch.as_tensor(rotations, dtype=torch.float64, device=t.device).expand(B, K, D, D)
        if fit and K:  # start from the solve without rotation rows, then alternate
            rhs = self._rhs(t, None)
            P = self.handles.shape[0]
            C = self._solve0(torch.cat([rhs[:, :P], rhs[:, P + K * D :]], dim=1))
            R = _nearest_rotation(self.jacobians(C))
        C = self._solve(self._rhs(t, R))
        history = [self._energy(C, t, R)]
        iterations, converged = 1, True
        if fit and K:
            converged = False
            scale2 = self.cage.scale**2
            for _ in range(max_iter - 1):
                R = _nearest_rotation(self.jacobians(C))
                C = self._solve(self._rhs(t, R))
                history.append(self._energy(C, t, R))
                iterations += 1
                prev, cur = history[-2], history[-1]
                if bool(((prev - cur).abs() <= tol * cur.abs().clamp_min(tol * scale2)).all()):
                    converged = True
                    break
        res = torch.einsum("pv,bvd->bpd", self.A, C) - t
        out = VariationalResult(
            vertices=C[0] if single else C,
            rotations=(R[0] if single else R) if R is not None else None,
            energy=history[-1][0] if single else history[-1],
            positional_residual=(res.norm(dim=-1).amax(-1))[0] if single else res.norm(dim=-1).amax(-1),
            iterations=iterations,
            converged=converged,
            history=history,
        )
        return out

    def _energy(self, C: torch.Tensor, t: torch.Tensor, R: torch.Tensor | None) -> torch.Tensor:
        r = self._M @ C - self._rhs(t, R)
        return (r * r).sum(dim=(-1, -2))


def _nearest_rotation(J: torch.Tensor) -> torch.Tensor:
    """Closest rotations (Frobenius) to the matrices ``J`` ``(*, D, D)``: ``U diag(1, .., det) V^T``."""
    U, _, Vh = torch.linalg.svd(J)
    d = torch.det(U @ Vh)
    U = torch.cat([U[..., :-1], U[..., -1:] * d[..., None, None]], dim=-1)
    return U @ Vh


# ----------------------------------------------------------------------------- scalar fields
def cotangent_laplacian(cage: Cage) -> torch.Tensor:
    """Discrete Laplacian ``(V, V)`` on the cage, float64 dense: the cotangent Laplacian divided by
    the barycentric vertex areas (triangle cage), or the second difference divided by the half
    lengths of the adjacent edges (polygon). Rows sum to zero (constants are in its kernel)."""
    v = cage.vertices.detach().to(torch.float64)
    V = v.shape[0]
    L = torch.zeros(V, V, dtype=torch.float64, device=v.device)
    if cage.dim == 3:
        t = cage.triangulated().triangles
        p = v[t]
        area = torch.zeros(V, dtype=torch.float64, device=v.device)
        two_a = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1).norm(dim=-1)
        for k in range(3):
            i, j, o = t[:, (k + 1) % 3], t[:, (k + 2) % 3], t[:, k]
            u, w = v[i] - v[o], v[j] - v[o]
            cot = (u * w).sum(-1) / torch.linalg.cross(u, w, dim=-1).norm(dim=-1)
            L.index_put_((i, j), cot / 2, accumulate=True)
            L.index_put_((j, i), cot / 2, accumulate=True)
            area.index_add_(0, o, two_a / 6)
    else:
        e = cage.edges
        ln = (v[e[:, 0]] - v[e[:, 1]]).norm(dim=-1)
        L.index_put_((e[:, 0], e[:, 1]), 1 / ln, accumulate=True)
        L.index_put_((e[:, 1], e[:, 0]), 1 / ln, accumulate=True)
        area = torch.zeros(V, dtype=torch.float64, device=v.device)
        area.index_add_(0, e[:, 0], ln / 2).index_add_(0, e[:, 1], ln / 2)
    L = L - torch.diag(L.sum(dim=1))
    return L / area[:, None]


@dataclass
class ScalarFieldResult:
    """Result of :func:`design_scalar_field`."""

    values: torch.Tensor  #: (*B, V) field values at the cage vertices
    value_residual: torch.Tensor  #: (*B,) largest |field - target| at the value points
    gradient_residual: torch.Tensor  #: (*B,) largest |grad field - target| at the gradient points


def design_scalar_field(
    cage: Cage,
    value_points: torch.Tensor,
    values: torch.Tensor,
    gradient_points: torch.Tensor | None = None,
    gradients: torch.Tensor | None = None,
    *,
    value_weight: float = 1.0,
    gradient_weight: float = 1.0,
    smoothness_weight: float = 1e-3,
    regularization: float = 1e-12,
) -> ScalarFieldResult:
    """A scalar field from value and gradient constraints inside the cage (Sec. 8.2).

    Minimises ``w_v sum |lam(x_i) f - v_i|^2 + w_g s^2 sum |grad lam(y_k)^T f - g_k|^2 +
    w_s s^4 |L f|^2`` over the values ``f`` at the cage vertices (``L``: :func:`cotangent_laplacian`;
    ``s`` the cage size, so that the three terms share the units of the values); the field at any
    point is ``mean_value_coordinates(x, cage) @ f``.

    Args:
        cage: the cage.
        value_points: ``(P, D)`` points with prescribed values.
        values: ``(*B, P)`` the values there (a batch of value sets is solved at once).
        gradient_points: ``(G, D)`` points with prescribed gradients.
        gradients: ``(*B, G, D)`` the gradients there.
        value_weight: ``w_v``, the weight of the value constraints.
        gradient_weight: ``w_g``, the weight of the gradient constraints.
        smoothness_weight: ``w_s``, the weight of the Laplacian term.
        regularization: relative Tikhonov term of the normal matrix.

    Returns:
        :class:`ScalarFieldResult`.

    Examples:
        >>> import torch, torchcage
        >>> from torchcage.variational import design_scalar_field
        >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> pts = torch.tensor([[0.0, 0, -0.5], [0.0, 0, 0.5]], dtype=torch.float64)
        >>> res = design_scalar_field(cage, pts, torch.tensor([0.0, 1.0]), pts, torch.tensor([[0.0, 0, 2.0]] * 2))
        >>> res.values.shape
        torch.Size([8])
    """
    D, size = cage.dim, cage.scale
    f64 = torch.float64
    xv = torch.as_tensor(value_points, dtype=f64).reshape(-1, D)
    vals = torch.as_tensor(values, dtype=f64)
    if vals.shape[-1] != xv.shape[0]:
        raise ValueError(f"values must have shape (*, {xv.shape[0]}), got {tuple(vals.shape)}")
    single = vals.ndim == 1
    vals = vals.reshape(-1, xv.shape[0])
    A = mean_value_coordinates(xv, cage, dtype=f64)
    blocks = [value_weight**0.5 * A]
    rhs = [value_weight**0.5 * vals]
    G = None
    if gradient_points is not None and gradients is not None:
        xg = torch.as_tensor(gradient_points, dtype=f64).reshape(-1, D)
        gr = torch.as_tensor(gradients, dtype=f64).reshape(-1, xg.shape[0], D)
        G = mean_value_derivatives(xg, cage, 1)[1]  # (K, V, D)
        blocks.append(gradient_weight**0.5 * size * G.permute(0, 2, 1).reshape(-1, cage.num_vertices))
        rhs.append(gradient_weight**0.5 * size * gr.expand(vals.shape[0], -1, -1).reshape(vals.shape[0], -1))
    L = cotangent_laplacian(cage)
    blocks.append(smoothness_weight**0.5 * size**2 * L)
    rhs.append(vals.new_zeros(vals.shape[0], L.shape[0]))
    M = torch.cat(blocks)
    b = torch.cat([r.expand(vals.shape[0], -1) for r in rhs], dim=1)[..., None]  # (B, rows, 1)
    f = _normal_solver(M, regularization)(b)[..., 0]  # (B, V)
    vres = (torch.einsum("pv,bv->bp", A, f) - vals).abs().amax(-1)
    if G is not None:
        gres = (torch.einsum("kvc,bv->bkc", G, f) - gr).norm(dim=-1).amax(-1)
    else:
        gres = torch.zeros(vals.shape[0], dtype=f64)
    if single:
        f, vres, gres = f[0], vres[0], gres[0]
    return ScalarFieldResult(values=f, value_residual=vres, gradient_residual=gres)
