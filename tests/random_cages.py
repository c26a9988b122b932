"""Random cages of the adversarial sweeps: convex hulls, star-shaped spheres, needles,
slabs and bilinear triquad cages, optionally rotated, scaled and translated; and points on the
support planes of their faces. Builders only (no tests here).
"""

from __future__ import annotations

import math

import torch

import torchcage as tc

D64 = torch.float64


def _rotation(g: torch.Generator) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, dtype=D64, generator=g))
    q = q * torch.sign(torch.diagonal(r))
    if torch.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _hull(points: torch.Tensor) -> torch.Tensor:
    """Outward triangles ``(T, 3)`` of the convex hull of ``points`` ``(V, 3)`` (all on it)."""
    from scipy.spatial import ConvexHull

    tri = torch.as_tensor(ConvexHull(points.numpy()).simplices, dtype=torch.long)
    p = points[tri]
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    flip = (n * (p.mean(1) - points.mean(0))).sum(-1) < 0
    return torch.where(flip[:, None], tri[:, [0, 2, 1]], tri)


def _sphere_points(n: int, g: torch.Generator) -> torch.Tensor:
    d = torch.randn(n, 3, dtype=D64, generator=g)
    return d / d.norm(dim=1, keepdim=True)


def convex_cage(g: torch.Generator, n: int = 14, axes: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> tc.Cage:
    """The hull of ``n`` random points on the ellipsoid of half-axes ``axes`` (a needle: one long
    axis; a slab: one short one)."""
    v = _sphere_points(n, g) * torch.tensor(axes, dtype=D64)
    return tc.Cage(v, _hull(v))


def star_cage(g: torch.Generator, spread: float = 0.5) -> tc.Cage:
    """The icosphere (42 vertices) with random radii in ``[1 - spread, 1]``: star-shaped, not convex."""
    from torchcage.testing import icosphere

    ico = icosphere(1)
    r = 1 - spread * torch.rand(ico.num_vertices, 1, dtype=D64, generator=g)
    return tc.Cage(ico.vertices * r, ico.triangles)


def needle_cage(g: torch.Generator, aspect: float | None = None, n: int = 10) -> tc.Cage:
    """A convex needle of length 2 and aspect ``aspect`` (random in ``1e3 .. 1e4`` by default):
    the hull of two tips and a ring of ``n - 2`` points; its side faces are thin triangles."""
    if aspect is None:
        aspect = 10 ** (3 + float(torch.rand(1, generator=g, dtype=D64)))
    k = n - 2
    ang = torch.sort(torch.rand(k, dtype=D64, generator=g) * 2 * math.pi).values
    x = 1.6 * torch.rand(k, dtype=D64, generator=g) - 0.8
    ring = torch.stack([x, torch.cos(ang) / aspect, torch.sin(ang) / aspect], dim=1)
    v = torch.cat([ring, torch.tensor([[1.0, 0, 0], [-1.0, 0, 0]], dtype=D64)])
    return tc.Cage(v, _hull(v))


def slab_cage(g: torch.Generator, thickness: float = 1e-5, n: int = 12) -> tc.Cage:
    """A convex slab ``thickness`` thick and about 2 wide: two copies of a random convex polygon."""
    ang = torch.sort(torch.rand(n // 2, dtype=D64, generator=g) * 2 * math.pi).values
    ring = torch.stack([torch.cos(ang), torch.sin(ang)], dim=1)
    top = torch.cat([ring, torch.full((n // 2, 1), thickness / 2, dtype=D64)], dim=1)
    bot = torch.cat([ring, torch.full((n // 2, 1), -thickness / 2, dtype=D64)], dim=1)
    v = torch.cat([top, bot])
    return tc.Cage(v, _hull(v))


def moved(cage: tc.Cage, g: torch.Generator, scale: float = 1.0, shift: float = 0.0) -> tc.Cage:
    """``cage`` rotated at random, scaled by ``scale`` and translated by ``shift`` times a random
    unit vector (the vertices rounded to float64 there)."""
    t = _sphere_points(1, g)[0] * shift
    return tc.Cage(cage.vertices @ _rotation(g).T * scale + t, cage.faces if cage.has_quads else cage.triangles)


def plane_points(
    cage: tc.Cage, g: torch.Generator, n: int, lo: float = 0.05, hi: float = 2.0, faces: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` points on the support planes of random faces (of ``faces``, default all), ``lo .. hi``
    times the cage size from the face's centroid in a random in-plane direction, and the faces'
    indices. On the plane up to the rounding of the point (``eps |x|``)."""
    v, tri = cage.vertices, cage.triangles
    pool = torch.arange(tri.shape[0]) if faces is None else faces
    f = pool[torch.randint(0, pool.shape[0], (n,), generator=g)]
    p = v[tri[f]]
    nrm = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    nrm = nrm / nrm.norm(dim=1, keepdim=True)
    d = torch.linalg.cross(nrm, torch.randn(n, 3, dtype=D64, generator=g), dim=-1)
    d = d / d.norm(dim=1, keepdim=True)
    r = lo + (hi - lo) * torch.rand(n, 1, dtype=D64, generator=g)
    return p.mean(1) + d * r * cage.scale, f


def thin_faces(cage: tc.Cage, aspect: float = 100.0) -> torch.Tensor:
    """Indices of the triangles whose longest edge is ``aspect`` times their width or more."""
    p = cage.vertices[cage.triangles]
    two_area = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1).norm(dim=1)
    L2 = (p - p.roll(1, dims=1)).square().sum(-1).amax(-1)
    return torch.nonzero(L2 > aspect * two_area).flatten()


def triquad_cage(g: torch.Generator, n: int = 2, noise: float = 0.15, split: float = 0.3) -> tc.Cage:
    """A box of ``n^3`` cells, side 2, with its vertices moved at random by up to ``noise`` cells
    (bilinear, non-planar quads) and about ``split`` of its quads split into two triangles; every
    remaining quad valid (:meth:`~torchcage.Cage.invalid_quads`: the noise is halved until so)."""
    from support import box_cage

    box = box_cage(n, n, n)
    quads = box.quads.tolist()
    pick = torch.rand(len(quads), generator=g) < split
    faces = []
    for q, s in zip(quads, pick.tolist(), strict=True):
        faces += [[q[0], q[1], q[2]], [q[0], q[2], q[3]]] if s else [q]
    step = torch.rand(box.vertices.shape, dtype=D64, generator=g) * 2 - 1
    for _ in range(20):
        cage = tc.Cage(box.vertices + step * noise * 2 / n, faces)
        if cage.invalid_quads().numel() == 0:
            return cage
        noise /= 2
    return tc.Cage(box.vertices, faces)
