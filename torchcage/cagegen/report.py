"""How good a cage is for a shape: enclosure, validity and tightness, measured (for made and for
hand-made cages alike)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import torch

from torchcage.cage import Cage
from torchcage.cagegen.checks import self_intersections, signed_clearance, tightness
from torchcage.cagegen.inputs import check_input


@dataclass(frozen=True)
class CageReport:
    """Measured properties of a cage around a shape. Distances are fractions of the shape's
    bounding-box diagonal.

    Attributes:
        vertices, triangles, quads: the cage's counts.
        quad_fraction: ``quads / (triangles + quads)``.
        invalid_quads: quads not valid for QMVC (:meth:`torchcage.Cage.invalid_quads`).
        self_intersections: see :func:`torchcage.cagegen.self_intersections`.
        outside: input vertices outside the cage (winding number below 1/2).
        min_clearance: the least signed distance from an input vertex to the cage (negative: outside).
        mean_distance, max_distance: distance from the cage's vertices and face centroids to the shape.
    """

    vertices: int
    triangles: int
    quads: int
    quad_fraction: float
    invalid_quads: int
    self_intersections: int
    outside: int
    min_clearance: float
    mean_distance: float
    max_distance: float

    def as_dict(self) -> dict[str, Any]:
        """The fields as a dict."""
        return asdict(self)


def measure_cage(cage: Cage, vertices: Any, faces: Any = None) -> CageReport:
    """Measure a cage against the shape it should enclose.

    Args:
        cage: a 3D cage.
        vertices: ``(N, 3)`` the shape's vertices.
        faces: ``(F, 3)`` its triangles (distances to the surface), or ``None`` (to the points).

    Returns:
        a :class:`CageReport`.

    Raises:
        ValueError: a 2D or batched cage; MeshError: unusable shape (see :func:`make_cage`).

    Examples:
        >>> import torch, torchcage
        >>> from torchcage.cagegen import measure_cage
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))  # [-1, 1]^3
        >>> r = measure_cage(cube, torch.tensor([[0.0, 0, 0], [0.5, 0, 0], [0, 0, 3.0]]))
        >>> r.outside, r.quads, r.self_intersections
        (1, 6, 0)
    """
    if cage.dim != 3 or cage.is_batched:
        raise ValueError(
            f"measure_cage measures one 3D cage, got dim={cage.dim}, batch shape {tuple(cage.batch_shape)}"
        )
    mesh = check_input(vertices, faces)
    points = torch.from_numpy(mesh.vertices)
    v = cage.vertices.detach().to(torch.float64).cpu()
    tri, quads = cage.triangles.cpu(), cage.quads.cpu()
    s, _ = signed_clearance(points, v, tri, quads)
    faces_t = None if mesh.faces is None else torch.from_numpy(mesh.faces)
    d = tightness(v, tri, quads, points, faces_t) / mesh.diagonal
    n_faces = tri.shape[0] + quads.shape[0]
    return CageReport(
        vertices=cage.num_vertices,
        triangles=int(tri.shape[0]),
        quads=int(quads.shape[0]),
        quad_fraction=quads.shape[0] / max(n_faces, 1),
        invalid_quads=int(cage.invalid_quads().numel()),
        self_intersections=self_intersections(v, tri, quads),
        outside=int((s < 0).sum()),
        min_clearance=float(s.min()) / mesh.diagonal,
        mean_distance=float(d.mean()),
        max_distance=float(d.max()),
    )
