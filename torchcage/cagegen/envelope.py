"""A closed envelope around a mesh or a point cloud: voxel occupancy, morphological closing,
offset, marching cubes.

The shape's surface is sampled densely (triangles subdivided until every edge is shorter than a
voxel) and the voxels that hold a sample are marked. The envelope is the offset of the closing of
that set: with ``d`` the distance to the marked voxels,

    D = fill(d <= seal + offset)              (cavities filled: one solid per part)
    envelope = {x in D : distance(x, outside D) >= seal}

so gaps and holes narrower than about ``2 seal`` are bridged, and every sample lies at least
``offset`` inside the envelope, up to the voxel size. Its boundary is extracted by marching cubes
on the signed distance field of ``D`` (scikit-image), which gives a smooth, closed, fine triangle
surface; :mod:`.simplify` makes it coarse.
"""

from __future__ import annotations

import numpy as np

from torchcage.cagegen._deps import require
from torchcage.cagegen.inputs import MeshInput

#: The grid never holds more voxels than this (memory: a few float64 fields of this size).
MAX_VOXELS = 300**3


def surface_samples(mesh: MeshInput, spacing: float) -> np.ndarray:
    """Points ``(S, 3)`` on the mesh, no point of the surface farther than ``spacing`` from one:
    the vertices and the corners of the triangles subdivided (1 -> 4, at the edge midpoints) until
    their longest edge is at most ``spacing``. A point cloud is its own sample.

    Examples:
        >>> from torchcage.cagegen.inputs import check_input
        >>> m = check_input([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
        >>> s = surface_samples(m, 0.5)
        >>> s.shape[1], bool((s.sum(axis=1) <= 1 + 1e-12).all())
        (3, True)
    """
    if mesh.faces is None:
        return mesh.vertices
    out = [mesh.vertices]
    p = mesh.vertices[mesh.faces]  # (F, 3, 3)
    while p.shape[0]:
        longest = np.linalg.norm(p - np.roll(p, -1, axis=1), axis=-1).max(axis=1)
        p = p[longest > spacing]
        if not p.shape[0]:
            break
        m01, m12, m20 = (p[:, 0] + p[:, 1]) / 2, (p[:, 1] + p[:, 2]) / 2, (p[:, 2] + p[:, 0]) / 2
        out += [m01, m12, m20, (p[:, 0] + p[:, 1] + p[:, 2]) / 3]
        p = np.concatenate(
            [
                np.stack([p[:, 0], m01, m20], 1),
                np.stack([m01, p[:, 1], m12], 1),
                np.stack([m20, m12, p[:, 2]], 1),
                np.stack([m01, m12, m20], 1),
            ]
        )
    return np.concatenate(out)


def point_spacing(points: np.ndarray, sample: int = 20000) -> float:
    """The 99th percentile of nearest-neighbour distances of ``points (N, 3)`` (on at most
    ``sample`` of them): the size of the gaps a point cloud's envelope must bridge.

    Examples:
        >>> round(point_spacing(np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])), 6)
        1.0
    """
    spatial = require("scipy.spatial")
    if points.shape[0] < 2:
        return 0.0
    rng = np.random.default_rng(0)
    q = points if points.shape[0] <= sample else points[rng.choice(points.shape[0], sample, replace=False)]
    d, _ = spatial.cKDTree(points).query(q, k=2)
    return float(np.percentile(d[:, 1], 99))


def envelope(mesh: MeshInput, *, offset: float, seal: float, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """The closed envelope around a shape.

    Args:
        mesh: the checked input.
        offset: distance from the shape to the envelope (before simplification).
        seal: closing radius: gaps narrower than about ``2 seal`` are bridged.
        resolution: voxels along the longest side of the grid.

    Returns:
        the fine surface: ``vertices (M, 3)``, ``faces (K, 3)`` (closed, outward).

    Examples:
        >>> import torch
        >>> from torchcage.cagegen.inputs import check_input
        >>> m = check_input(np.random.default_rng(0).normal(size=(500, 3)))
        >>> v, f = envelope(m, offset=0.2, seal=0.5, resolution=64)  # voxels of about 0.114
        >>> from torchcage.cagegen.checks import signed_clearance
        >>> s, _ = signed_clearance(torch.from_numpy(m.vertices), torch.from_numpy(v), torch.from_numpy(f))
        >>> bool(s.min() > 0.2 - 0.114)  # every point inside, at least the offset less a voxel away
        True
    """
    ndimage = require("scipy.ndimage")
    measure = require("skimage.measure")
    reach = seal + offset
    extent = mesh.hi - mesh.lo
    h = float((extent.max() + 2 * reach) / max(resolution - 4, 4))
    shape = np.ceil((extent + 2 * reach) / h).astype(np.int64) + 5
    if int(np.prod(shape)) > MAX_VOXELS:
        raise ValueError(
            f"a voxel grid of {tuple(shape.tolist())} is too large; lower resolution (now {resolution}) or the seal"
        )
    origin = mesh.lo - reach - 2.5 * h
    samples = surface_samples(mesh, h)
    index = np.clip(np.floor((samples - origin) / h).astype(np.int64), 0, shape - 1)
    marked = np.zeros(tuple(shape), dtype=bool)
    marked[index[:, 0], index[:, 1], index[:, 2]] = True
    distance = ndimage.distance_transform_edt(~marked) * h
    solid = ndimage.binary_fill_holes(distance <= reach)
    phi = (ndimage.distance_transform_edt(solid) - ndimage.distance_transform_edt(~solid)) * h
    level = max(seal, 0.5 * h)
    verts, faces, _, _ = measure.marching_cubes(phi, level=level, spacing=(h, h, h))
    verts = verts + origin + 0.5 * h  # voxel i's centre is origin + (i + 1/2) h
    faces = faces.astype(np.int64)
    p = verts[faces]
    volume = float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum())
    if volume < 0:
        faces = faces[:, ::-1].copy()
    return verts, faces
