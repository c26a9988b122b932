"""Green coordinates where rounding used to decide the answer: points a
few rounding units from a polygon's vertex, gradients just outside a thin cage's edge, cages far
from the origin. Random cages and points; references in 50-digit mpmath."""

from __future__ import annotations

import math

import mpmath as mp
import pytest
import torch

import torchcage
from torchcage import functional as F
from torchcage.families.green.kernel2d import green2d_coordinates

EPS = torch.finfo(torch.float64).eps


@mp.workdps(50)
def green2d_reference(x, vertices) -> tuple[list, list]:
    """Bare 2D Green coordinates ``(phi (V,), psi (E,))`` of one point (floats taken exactly) for a
    counter-clockwise polygon, from the arctangent antiderivatives (not the kernel's atan2 forms):
    per edge ``P(t) = |b + t a|^2 = Q t^2 + R t + S``, ``c = b x a``,
    ``int dt / P = [atan((Q t + R / 2) / |c|)] / |c|``, ``int t / P = log(P1 / S) / 2Q - R / 2Q int 1 / P``,
    ``int log P = [(t + R / 2Q) log P - 2 t + 2 |c| / Q atan(...)]``."""
    V = [[mp.mpf(float(c)) for c in r] for r in vertices]
    X = [mp.mpf(float(c)) for c in x]
    n = len(V)
    phi, psi = [mp.mpf(0)] * n, []
    for j in range(n):
        k = (j + 1) % n
        ax, ay = V[k][0] - V[j][0], V[k][1] - V[j][1]
        bx, by = V[j][0] - X[0], V[j][1] - X[1]
        Q, R, S = ax * ax + ay * ay, 2 * (ax * bx + ay * by), bx * bx + by * by
        c = bx * ay - by * ax
        P1 = Q + R + S
        dF = mp.atan((Q + R / 2) / abs(c)) - mp.atan((R / 2) / abs(c))
        I0 = dF / abs(c)
        I1 = (mp.log(P1) - mp.log(S)) / (2 * Q) - R / (2 * Q) * I0
        IL = (1 + R / (2 * Q)) * mp.log(P1) - R / (2 * Q) * mp.log(S) - 2 + 2 * abs(c) / Q * dF
        psi.append(-mp.sqrt(Q) / (4 * mp.pi) * IL)
        phi[k] += c / (2 * mp.pi) * I1
        phi[j] += c / (2 * mp.pi) * (I0 - I1)
    return phi, psi


@mp.workdps(50)
def distance2d(x, vertices) -> float:
    """Distance from a point to a closed polygon's edges, in mpmath (floats taken exactly)."""
    V = [[mp.mpf(float(c)) for c in r] for r in vertices]
    X = [mp.mpf(float(c)) for c in x]
    best = mp.inf
    for j in range(len(V)):
        k = (j + 1) % len(V)
        ax, ay = V[k][0] - V[j][0], V[k][1] - V[j][1]
        yx, yy = X[0] - V[j][0], X[1] - V[j][1]
        t = min(max((ax * yx + ay * yy) / (ax * ax + ay * ay), 0), 1)
        best = min(best, mp.sqrt((yx - t * ax) ** 2 + (yy - t * ay) ** 2))
    return float(best)


def star_polygon(n: int, g: torch.Generator) -> torch.Tensor:
    """A random star-shaped counter-clockwise polygon ``(n, 2)`` of size about 2."""
    ang = torch.sort(torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi).values
    r = 0.5 + torch.rand(n, generator=g, dtype=torch.float64)
    return torch.stack([r * ang.cos(), r * ang.sin()], 1)


def near_vertices(V: torch.Tensor, per: int, lo: float, hi: float, size: float, g: torch.Generator) -> torch.Tensor:
    """``per`` points around each vertex at log-uniform distances ``lo..hi`` times ``size``, in
    random directions (inside and outside)."""
    d = torch.randn(V.shape[0], per, 2, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    r = 10 ** (math.log10(lo) + torch.rand(V.shape[0], per, 1, generator=g, dtype=torch.float64) * math.log10(hi / lo))
    return (V[:, None] + r * size * d).reshape(-1, 2)


def random_polygon_cases(seed: int, count: int, translate: bool):
    g = torch.Generator().manual_seed(seed)
    out = []
    while len(out) < count:
        V = star_polygon(5 + len(out) % 4, g)
        scale = 10 ** (float(torch.rand(1, generator=g)) * 12 - 6)
        shift = (torch.rand(2, generator=g, dtype=torch.float64) * 2 - 1) * 1e6 * scale if translate else 0.0
        Vs = V * scale + shift
        try:
            out.append(torchcage.Cage(Vs))
        except torchcage.errors.CageError:  # (a polygon that rounding folded: draw another)
            continue
    return out


def test_green2d_kernel_next_to_vertices_agrees_with_mpmath():
    """The bare integrals at points 1e-15..1e-12 of the size from a vertex (the
    side of an edge was decided by a cross product that had cancelled, phi off by 0.1)."""
    g = torch.Generator().manual_seed(11)
    worst = 0.0
    for cage in random_polygon_cases(3, 4, translate=False):
        size = cage.scale
        x = near_vertices(cage.vertices, 5, 1e-15, 1e-12, size, g)
        phi, psi = green2d_coordinates(x, cage)
        for p in range(x.shape[0]):
            if distance2d(x[p].tolist(), cage.vertices.tolist()) < 64 * EPS * size:
                continue  # (the on-cage band: the limit from inside, by design)
            rphi, rpsi = green2d_reference(x[p].tolist(), cage.vertices.tolist())
            e = max(abs(float(r) - float(c)) for r, c in zip(rphi, phi[p], strict=True))
            e = max(e, max(abs(float(r) - float(c)) / size for r, c in zip(rpsi, psi[p], strict=True)))
            worst = max(worst, e)
    assert worst < 1e-12, worst


@pytest.mark.parametrize("translate", [False, True])
def test_green2d_partition_and_linear_precision_next_to_vertices(translate):
    """Public function (exterior extension included): sum(phi) = 1 and phi @ V + psi @ n = x
    within 1e-9 of the size next to vertices, inside and outside, at random scales and (with
    ``translate``) a million sizes from the origin, linear precision measured about the cage's
    centre (the input's own rounding, eps |x|, is not the coordinates' error)."""
    g = torch.Generator().manual_seed(5)
    worst_pu = worst_lp = 0.0
    for cage in random_polygon_cases(7, 6, translate):
        size = cage.scale
        x = near_vertices(cage.vertices, 8, 1e-15, 1e-6, size, g)
        phi, psi = F.green_coordinates(x, cage)
        c = (cage.vertices.amax(0) + cage.vertices.amin(0)) / 2
        rec = phi @ (cage.vertices - c) + psi @ cage.edge_normals()
        worst_pu = max(worst_pu, float((phi.sum(1) - 1).abs().max()))
        worst_lp = max(worst_lp, float((rec - (x - c)).norm(dim=1).max()) / size)
    assert worst_pu < 1e-9 and worst_lp < 1e-9, (worst_pu, worst_lp)


def _rotation(g: torch.Generator) -> torch.Tensor:
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    return q * torch.linalg.det(q)


def needle_cage(kind: int, g: torch.Generator) -> torchcage.Cage:
    """A random needle of aspect 1e3..1e5 (0: a bipyramid, 1: a triangular prism, 2: a tetrahedron
    with two cap slivers), randomly turned and scaled by 1e-6..1e6."""
    w = 10 ** (-3 - 2 * float(torch.rand(1, generator=g)))
    ang = torch.tensor([0.0, 2.1, 4.2], dtype=torch.float64) + 0.3 * torch.rand(3, generator=g, dtype=torch.float64)
    ring = torch.stack([w * ang.cos(), w * ang.sin()], 1)
    if kind == 0:
        V = torch.cat([torch.cat([torch.zeros(3, 1, dtype=torch.float64), ring], 1)])
        V = torch.cat([V, torch.tensor([[-0.5, 0, 0], [0.5, 0, 0]], dtype=torch.float64)])
        faces = [[3, 1, 0], [3, 2, 1], [3, 0, 2], [4, 0, 1], [4, 1, 2], [4, 2, 0]]
    elif kind == 1:
        half = torch.full((3, 1), 0.5, dtype=torch.float64)
        V = torch.cat([torch.cat([-half, ring], 1), torch.cat([half, ring], 1)])
        faces = [[0, 2, 1], [3, 4, 5], [0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [2, 0, 3], [2, 3, 5]]
    else:
        V = torch.tensor([[-0.5, 0, 0], [0.5, 0, 0], [0.1, w, 0], [0.2, -0.3 * w, w]], dtype=torch.float64)
        faces = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
    V = V @ _rotation(g).T * 10 ** (float(torch.rand(1, generator=g)) * 12 - 6)
    return torchcage.Cage(V, torch.tensor(faces))


def outside_edges(cage: torchcage.Cage, lo: float, hi: float, per: int, g: torch.Generator) -> torch.Tensor:
    """Points outside every edge of a triangle cage at log-uniform distances ``lo..hi`` times its
    size, between the edge's two face normals, somewhere along the edge's middle 80%."""
    V, n, size = cage.vertices, cage.triangle_normals(), cage.scale
    faces_of: dict = {}
    for t, f in enumerate(cage.triangles.tolist()):
        for i in range(3):
            faces_of.setdefault(tuple(sorted((f[i], f[(i + 1) % 3]))), []).append(t)
    pts = []
    for (a, b), (t1, t2) in faces_of.items():
        for _ in range(per):
            d = 10 ** (math.log10(lo) + float(torch.rand(1, generator=g)) * math.log10(hi / lo)) * size
            u = float(torch.rand(1, generator=g))
            s = 0.1 + 0.8 * float(torch.rand(1, generator=g))
            direction = n[t1] * u + n[t2] * (1 - u)
            pts.append(V[a] * (1 - s) + V[b] * s + d * direction / direction.norm())
    return torch.stack(pts)


def test_green_gradients_outside_needle_edges_sum_to_zero():
    """d(sum phi)/dx = 0 (sum phi is 1 outside too, by the extension) at 1e-14..1e-7 of the size
    outside needles' edges (the solid angle's Van Oosterom-Strackee value over the
    on-plane band gave 1e11 / size). Autograd of the torch kernel (the rest cage's vertices
    differentiated too, so no closed form stands in): what is left is the rounding of the faces'
    singular terms (each ~1 / distance), relative to them below 1e-3 (2e-4 at 1e-14 of the size,
    1e-10 at 1e-8; it was 1.5). green_derivatives and the points-only autograd path make the sum
    vanish exactly (the identity); their gradients agree with the kernel's to that rounding."""
    g = torch.Generator().manual_seed(2)
    worst = worst_sum = worst_agree = 0.0
    for kind in range(3):
        for _ in range(2):
            cage = needle_cage(kind, g)
            x = outside_edges(cage, 1e-14, 1e-7, 3, g)
            _, _, gphi, _ = F.green_derivatives(x, cage)
            mag = gphi.norm(dim=-1).amax(dim=1)
            worst_sum = max(worst_sum, float((gphi.sum(1).norm(dim=1) / mag).max()))
            xr = x.clone().requires_grad_(True)
            moving = cage._like(cage.vertices.clone().requires_grad_(True))
            phi, _ = F.green_coordinates(xr, moving)
            (gx,) = torch.autograd.grad(phi.sum(), xr, retain_graph=True)
            worst = max(worst, float((gx.norm(dim=1) / mag).max()))
            # a random linear functional of phi: the kernel's autograd against the analytic rows
            w = torch.randn(phi.shape[1], generator=g, dtype=torch.float64)
            (gw,) = torch.autograd.grad((phi @ w).sum(), xr)
            agree = (gw - torch.einsum("v,nvc->nc", w, gphi)).norm(dim=1) / (mag * w.abs().sum())
            worst_agree = max(worst_agree, float(agree.max()))
    assert worst < 1e-3 and worst_sum < 1e-12 and worst_agree < 1e-3, (worst, worst_sum, worst_agree)


def _moved(cage: torchcage.Cage, g: torch.Generator, distance: float = 1e6) -> torchcage.Cage:
    """``cage`` moved by ``distance`` times its size in a random direction."""
    d = torch.randn(cage.dim, generator=g, dtype=torch.float64)
    return cage._like(cage.vertices + d / d.norm() * distance * cage.scale)


@pytest.mark.parametrize("dim", [2, 3])
def test_green_translated_cages_linear_precision_and_jacobian(dim):
    """Cages moved by 1e6 of their sizes: linear precision and the Jacobian
    identity (sum P_i grad phi_i^T + sum n_t grad psi_t^T = I) about the cage's centre within a few
    units of the input's rounding (1e6 eps) relative to the size, for points inside, outside and
    1e-9..1e-3 of the size from vertices (there the rounding of the edges' angle gradients,
    eps size / r at r from the vertex, sets the bound). About the origin, the on-cage band
    (2 eps 1e6 sizes) gave those points the interpolant's derivatives: Jacobians off by 0.4."""
    g = torch.Generator().manual_seed(8 + dim)
    if dim == 2:
        cages = random_polygon_cases(13, 3, translate=False)
    else:
        cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated().to(torch.float64)
        cages = [needle_cage(1, g), cube]
    floor = 1e6 * EPS
    for rest in cages:
        cage = _moved(rest, g)
        V, size = cage.vertices, cage.scale
        c = (V.amax(0) + V.amin(0)) / 2
        spread = (V - c).abs().amax(0)
        x = c + (torch.rand(60, dim, generator=g, dtype=torch.float64) * 2 - 1) * 1.3 * spread
        if dim == 2:
            x = torch.cat([x, near_vertices(V, 4, 1e-9, 1e-3, size, g)])
        n = cage.edge_normals() if dim == 2 else cage.triangle_normals()
        phi, psi, gphi, gpsi = F.green_derivatives(x, cage)
        rec = phi @ (V - c) + psi @ n
        assert float((rec - (x - c)).norm(dim=1).max()) / size < 8 * floor
        J = torch.einsum("nvi,vj->nji", gphi, V - c) + torch.einsum("nti,tj->nji", gpsi, n)
        r = (x[:, None] - V[None]).norm(dim=-1).amin(dim=1)  # (each edge's angle has a gradient ~ 1 / r)
        bound = 8 * floor + 16 * EPS * size / r
        assert bool(((J - torch.eye(dim, dtype=torch.float64)).abs().amax(dim=(1, 2)) < bound).all())


@pytest.mark.slow
@mp.workdps(60)
def test_green_gradients_outside_needle_edges_agree_with_mpmath():
    """Autograd of the bare integrals (exterior='none') at 1e-12..1e-7 of the size outside needles'
    edges against 60-digit central differences of :func:`reference.green3d_reference`, relative
    to the point's largest coordinate gradient (an apex's entry there, ~1e-5 of it, is a difference
    of the near faces' terms and carries their rounding). Measured 3e-6 at worst."""
    from reference import gradient_reference, green3d_reference

    g = torch.Generator().manual_seed(21)
    worst = 0.0
    for kind in (2, 2, 0, 1):
        cage = needle_cage(kind, g)
        x = outside_edges(cage, 1e-12, 1e-7, 1, g)
        V, size, tri = cage.vertices, cage.scale, cage.triangles
        xr = x.clone().requires_grad_(True)
        phi, _ = F.green_coordinates(xr, cage, exterior="none")

        def entry(y, i, V=V, tri=tri):
            return green3d_reference(y, V, tri)[0][i]

        for p in range(x.shape[0]):
            got = torch.stack([torch.autograd.grad(phi[p, i], xr, retain_graph=True)[0][p] for i in range(V.shape[0])])
            ref = torch.tensor(
                [gradient_reference(lambda y, i=i: entry(y, i), x[p].tolist(), size) for i in range(V.shape[0])],
                dtype=torch.float64,
            )
            worst = max(worst, float((got - ref).norm(dim=1).max() / ref.norm(dim=1).max()))
    assert worst < 1e-5, worst
