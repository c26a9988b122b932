"""Reusable property checks for cage coordinates, for this library's tests and for users' own.

Examples:
    >>> import torch, torchcage
    >>> from torchcage.testing import assert_partition_of_unity, assert_linear_precision
    >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
    >>> x = torch.rand(50, 3, dtype=torch.float64) * 4 - 2
    >>> w = torchcage.functional.mean_value_coordinates(x, cage)
    >>> assert_partition_of_unity(w, atol=1e-12)
    >>> assert_linear_precision(w, cage.vertices, x, rtol=1e-10)
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from torchcage.cage import Cage

__all__ = [
    "QMVC_MODELS",
    "adversarial_points",
    "assert_interpolates",
    "assert_linear_precision",
    "assert_partition_of_unity",
    "hard_cages",
    "icosphere",
    "sliver_cube",
    "twisted_bar",
]

#: The models of the QMVC paper's data set (``shared/data/qmvc/<model>.obj`` and ``<model>_Cage.obj``,
#: not shipped), used by the tests and the benchmarks.
QMVC_MODELS = ("Beast", "Bench", "Cactus", "FireHydrant", "ManHead", "Ogre", "SpikyBox", "WireSphere")


def assert_partition_of_unity(weights: torch.Tensor, *, atol: float = 1e-12) -> None:
    """Every row of ``weights`` ``(*, V)`` sums to one within ``atol`` and is finite."""
    if not bool(torch.isfinite(weights).all()):
        raise AssertionError("weights contain NaN or inf")
    err = float((weights.sum(dim=-1) - 1).abs().max()) if weights.numel() else 0.0
    if err > atol:
        raise AssertionError(f"partition of unity violated: max |sum - 1| = {err:.3e} > {atol:.1e}")


def assert_linear_precision(
    weights: torch.Tensor, vertices: torch.Tensor, points: torch.Tensor, *, rtol: float = 1e-10
) -> None:
    """``weights @ vertices`` reproduces ``points`` within ``rtol`` times the cage's bounding-box diagonal.

    Args:
        weights: ``(N, V)`` coordinates.
        vertices: ``(V, D)`` rest cage vertices.
        points: ``(N, D)`` the points the coordinates were computed for.
    """
    scale = float((vertices.max(dim=0).values - vertices.min(dim=0).values).norm())
    err = float((weights.to(vertices.dtype) @ vertices - points).abs().max()) / scale if points.numel() else 0.0
    if not err <= rtol:
        raise AssertionError(f"linear precision violated: max error {err:.3e} x cage size > {rtol:.1e}")


def assert_interpolates(weights: torch.Tensor, expected: torch.Tensor, *, atol: float = 1e-12) -> None:
    """Coordinates equal the expected hat-function values (``(N, V)`` each) within ``atol``."""
    err = float((weights - expected).abs().max()) if weights.numel() else 0.0
    if not err <= atol:
        raise AssertionError(f"interpolation violated: max error {err:.3e} > {atol:.1e}")


# ----------------------------------------------------------------------------- hard cages
# Cages that put kernels under numerical stress; used by the tests and benchmarks/robustness.py.
_CUBE = [[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1], [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]]
_CUBE_SIDES = [[4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]  # all but the bottom


def sliver_cube(gap: float = 1e-9, dtype: torch.dtype = torch.float64) -> Cage:
    """The cube ``[-1, 1]^3`` whose bottom face is fanned around an extra vertex ``gap`` from the
    bottom face's edge ``y = -1``: one triangle of height ``gap`` (a sliver), all faces coplanar
    with a neighbour.

    Returns:
        The cage: 9 vertices, 14 triangles.

    Examples:
        >>> from torchcage.testing import sliver_cube
        >>> sliver_cube().triangles.shape
        torch.Size([14, 3])
    """
    from torchcage.cage import Cage

    v = torch.tensor([*_CUBE, [0.0, -1.0 + gap, -1.0]], dtype=dtype)
    faces = []
    for a, b, c, d in _CUBE_SIDES:
        faces += [[a, b, c], [a, c, d]]
    faces += [[8, 1, 0], [8, 2, 1], [8, 3, 2], [8, 0, 3]]  # the bottom fan (outward normal -z)
    return Cage(v, torch.tensor(faces))


def twisted_bar(levels: int = 4, twist: float = 90.0, quads: bool = True, dtype: torch.dtype = torch.float64) -> Cage:
    """A square bar of side 1 along ``z`` (``0 <= z <= levels / 2``) made of ``levels`` segments,
    its square sections turned progressively by ``twist`` degrees in all: non-planar side quads.

    Args:
        levels: segments along the bar.
        twist: total twist in degrees.
        quads: keep the quads (a quad cage for QMVC/QGC); ``False`` triangulates them.

    Examples:
        >>> from torchcage.testing import twisted_bar
        >>> bar = twisted_bar()
        >>> bar.num_vertices, bar.quads.shape[0]
        (20, 18)
    """
    from torchcage.cage import Cage

    verts = []
    for k in range(levels + 1):
        a = math.radians(twist) * k / levels
        for cx, cy in ((-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)):
            verts.append([cx * math.cos(a) - cy * math.sin(a), cx * math.sin(a) + cy * math.cos(a), 0.5 * k])
    faces = [[0, 3, 2, 1], [4 * levels, 4 * levels + 1, 4 * levels + 2, 4 * levels + 3]]
    for k in range(levels):
        for i in range(4):
            j = (i + 1) % 4
            faces.append([4 * k + i, 4 * k + j, 4 * (k + 1) + j, 4 * (k + 1) + i])
    cage = Cage(torch.tensor(verts, dtype=dtype), faces)
    return cage if quads else cage.triangulated()


def icosphere(subdivisions: int = 1, radius: float = 1.0, dtype: torch.dtype = torch.float64) -> Cage:
    """A geodesic sphere: the icosahedron with each triangle split into four ``subdivisions`` times,
    vertices pushed onto the sphere. ``subdivisions=1`` gives 42 vertices and 80 triangles, the
    template size of Neural Cages.

    Examples:
        >>> from torchcage.testing import icosphere
        >>> ico = icosphere()
        >>> ico.num_vertices, ico.triangles.shape[0]
        (42, 80)
    """
    from torchcage.cage import Cage

    t = (1 + 5**0.5) / 2
    verts = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t]]
    verts += [[0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]
    verts = [[float(c) for c in v] for v in verts]
    faces = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2]]
    faces += [[10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5]]
    faces += [[2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    for _ in range(subdivisions):
        mid: dict[tuple[int, int], int] = {}

        def midpoint(a: int, b: int, mid: dict[tuple[int, int], int] = mid) -> int:
            key = (min(a, b), max(a, b))
            if key not in mid:
                mid[key] = len(verts)
                verts.append([(verts[a][k] + verts[b][k]) / 2 for k in range(3)])
            return mid[key]

        split = []
        for a, b, c in faces:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            split += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = split
    v = torch.tensor(verts, dtype=torch.float64)
    v = radius * v / v.norm(dim=1, keepdim=True)
    return Cage(v.to(dtype), torch.tensor(faces))


def hard_cages(dtype: torch.dtype = torch.float64) -> dict[str, Cage]:
    """Named hard cages (triangle cages unless the name says quads): slivers, coplanar neighbours,
    twisted quads, tiny and huge scales, a far translation.

    Examples:
        >>> from torchcage.testing import hard_cages
        >>> len(hard_cages()), hard_cages()["sliver_cube"].num_vertices
        (6, 9)
    """
    from torchcage import data
    from torchcage.io import load_cage

    cube = load_cage(data.path("cube.obj")).triangulated().to(dtype)
    from torchcage.cage import Cage

    def moved(s: float, t: float = 0.0):
        return Cage(cube.vertices * s + t, cube.triangles)

    return {
        "cube_1e-6": moved(1e-6),
        "cube_1e6": moved(1e6),
        "cube_shift_1e6": moved(1.0, 1e6),
        "sliver_cube": sliver_cube(dtype=dtype),
        "twisted_bar": twisted_bar(quads=False, dtype=dtype),
        "twisted_bar_quads": twisted_bar(dtype=dtype),
    }


def adversarial_points(cage, n: int = 64, *, seed: int = 0, far: bool = True, sides: bool = False):
    """Query points that stress coordinate kernels, by category, in the cage's dtype.

    Categories: ``vertex``, ``edge``, ``face`` (exactly on the cage, up to rounding); ``near_vertex``,
    ``near_edge``, ``near_face`` (offsets of ``1e-15 .. 1e-3`` times the cage size, both sides);
    ``plane`` (on faces' support planes, off the faces), ``edge_line`` (on edges' lines beyond
    their ends); ``far`` (``1e2 .. 1e9`` cage sizes away, only with ``far=True``). 2D cages use
    their edges as faces. Each category has about ``n`` points (``(m, D)``).

    With ``sides=True`` returns ``(points, sides)``: ``sides[cat]`` ``(m,)`` is ``-1`` for points
    known to be inside the cage, ``+1`` outside, ``0`` on it and NaN where the construction does not
    tell (offsets in random directions near vertices and edges, points off the cage's surface).
    ``near_face`` points are offset along the outward normal of the surface (of the bilinear sheet
    for quads), so their side is the offset's sign (for offsets below the local feature size).

    Examples:
        >>> import torchcage
        >>> from torchcage.testing import adversarial_points
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> pts = adversarial_points(cube, 16)
        >>> len(pts), pts["vertex"].shape[1]
        (9, 3)
    """
    g = torch.Generator().manual_seed(seed)
    v = cage.vertices.detach()
    dt, D = v.dtype, v.shape[1]
    size = cage.scale
    faces = cage.triangulated().triangles if D == 3 else cage.edges
    if D == 3:
        edges = cage.unique_edges()
    else:
        edges = faces

    def rand(*shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=g, dtype=dt)

    def pick(m: int, k: int) -> torch.Tensor:
        return torch.randint(0, m, (k,), generator=g)

    def unit(k: int) -> torch.Tensor:
        d = torch.randn(k, D, generator=g, dtype=dt)
        return d / d.norm(dim=1, keepdim=True)

    def offsets(k: int) -> torch.Tensor:
        exp = -3.0 - 12.0 * rand(k)
        sign = torch.where(rand(k) < 0.5, -1.0, 1.0).to(dt)
        return (sign * size * 10.0**exp)[:, None]

    e = edges[pick(edges.shape[0], n)]
    t = rand(n, 1)
    on_edge = (1 - t) * v[e[:, 0]] + t * v[e[:, 1]]
    true_tri = cage.triangles if D == 3 and cage.triangles.shape[0] else faces
    f = true_tri[pick(true_tri.shape[0], n)]  # (quad cages: only their real triangles here)
    if D == 3:
        b = -torch.log(rand(n, 3))
        b = b / b.sum(dim=1, keepdim=True)
        on_face = torch.einsum("ni,nic->nc", b, v[f])
        nrm = torch.linalg.cross(v[f][:, 1] - v[f][:, 0], v[f][:, 2] - v[f][:, 0], dim=-1)
        if cage.has_quads:  # points on the bilinear quads themselves (not on their split triangles)
            quads = cage.quads
            nt = cage.triangles.shape[0]
            use = (
                torch.rand(n, generator=g) < quads.shape[0] / (quads.shape[0] + nt)
                if nt
                else torch.ones(n, dtype=torch.bool)
            )
            q = v[quads[pick(quads.shape[0], n)]]  # (n, 4, D)
            uu, vv = rand(n, 1), rand(n, 1)
            sheet = (
                (1 - uu) * (1 - vv) * q[:, 0] + uu * (1 - vv) * q[:, 1] + uu * vv * q[:, 2] + (1 - uu) * vv * q[:, 3]
            )
            xu = (1 - vv) * (q[:, 1] - q[:, 0]) + vv * (q[:, 2] - q[:, 3])
            xv = (1 - uu) * (q[:, 3] - q[:, 0]) + uu * (q[:, 2] - q[:, 1])
            on_face = torch.where(use[:, None], sheet, on_face)
            nrm = torch.where(use[:, None], torch.linalg.cross(xu, xv, dim=-1), nrm)
        tang = torch.linalg.cross(nrm, unit(n), dim=-1)
        plane = on_face + tang / tang.norm(dim=1, keepdim=True) * size * (0.05 + 2 * rand(n, 1))
    else:
        on_face = on_edge
        nrm = (v[e[:, 1]] - v[e[:, 0]]).flip(1) * torch.tensor([1.0, -1.0], dtype=dt)
        plane = on_edge + (v[e[:, 1]] - v[e[:, 0]]) * (1 + 2 * rand(n, 1))
    nrm = nrm / nrm.norm(dim=1, keepdim=True)
    face_off = offsets(n)
    beyond = v[e[:, 1]] + (v[e[:, 1]] - v[e[:, 0]]) * (0.01 + 3 * rand(n, 1))
    vi = pick(v.shape[0], n)
    out = {
        "vertex": v[vi],
        "edge": on_edge,
        "face": on_face,
        "near_vertex": v[vi] + offsets(n) * unit(n),
        "near_edge": on_edge + offsets(n) * unit(n),
        "near_face": on_face + face_off * nrm,
        "plane": plane,
        "edge_line": beyond,
    }
    if far:
        centre = (v.max(dim=0).values + v.min(dim=0).values) / 2
        out["far"] = centre + unit(n) * size * 10.0 ** (2 + 7 * rand(n, 1))
    if not sides:
        return out
    side = {k: torch.full((p.shape[0],), float("nan"), dtype=dt) for k, p in out.items()}
    for k in ("vertex", "edge", "face"):
        side[k] = torch.zeros(out[k].shape[0], dtype=dt)
    side["near_face"] = torch.sign(face_off[:, 0])
    return out, side
