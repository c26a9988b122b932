"""Green coordinates for closed triangle cages (3D) and closed polygons (2D): the public function.

The closed forms and their numerical care are described in ``kernel3d`` and ``kernel2d``.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch._C._functorch import is_functorch_wrapped_tensor

from torchcage._core.batch import over_cage_batch
from torchcage._core.common import (
    ON_CAGE_TOLERANCE,
    VERTEX_SNAP,
    as_inputs,
    check_points,
    records_graph,
    result_dtype,
    snap_to_vertices,
    unit_sum,
)
from torchcage._core.compiled import CompiledOp, through_op
from torchcage.backends import resolve
from torchcage.cage import Cage
from torchcage.families.green.batch import coordinates_batch
from torchcage.families.green.batch2d import polygons_batch
from torchcage.families.green.dispatch import GC, green_flat
from torchcage.families.green.exterior import extend_outside
from torchcage.families.green.kernel3d import triangle_green_data
from torchcage.families.green.ops import green_function

__all__ = ["green_coordinates"]


def centred(x: torch.Tensor, cage: Cage, dtype: torch.dtype) -> tuple[torch.Tensor, Cage]:
    """``x`` ``(N, D)`` and ``cage`` (one cage) in ``dtype``, both moved by minus the middle of the
    cage's bounding box (a constant: Green coordinates are invariant under translation, so the
    derivatives through the moved vertices are the whole derivatives).

    Examples:
        >>> import torch, torchcage
        >>> sq = torchcage.Cage([[1e6, 1e6], [1e6 + 1, 1e6], [1e6 + 1, 1e6 + 1], [1e6, 1e6 + 1]])
        >>> y, c = centred(torch.tensor([[1e6 + 0.25, 1e6 + 0.5]]), sq, torch.float64)
        >>> y.tolist(), c.vertices[0].tolist()
        ([[-0.25, 0.0]], [-0.5, -0.5])
    """
    v = cage.vertices.to(dtype)
    with torch.no_grad():
        centre = (v.detach().amax(dim=0) + v.detach().amin(dim=0)) / 2
    return x.to(dtype) - centre, cage._like(v - centre)


#: The function as one opaque custom op under ``torch.compile`` (:mod:`torchcage._core.compiled`).
COMPILED = CompiledOp(
    "green",
    lambda points, cage, options: tuple(green_coordinates(points, cage, **options)),
    lambda vertices, triangles, quads, edges: [
        vertices.shape[-2],
        triangles.shape[0] if vertices.shape[-1] == 3 else edges.shape[0],
    ],
    GC,
)


def green_coordinates(
    points: torch.Tensor,
    cage: Cage,
    *,
    chunk_size: int | None = None,
    dtype: torch.dtype | None = None,
    progress: bool | Callable[[int, int], None] = False,
    backend: str = "auto",
    exterior: str = "extend",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Green coordinates (Lipman, Levin, Cohen-Or 2008) of points inside a closed triangle cage
    or a closed polygon.

    At rest, ``phi @ cage.vertices + psi @ n = points`` for points inside the cage, with ``n`` the
    unit outward normals of the triangles (``cage.triangle_normals()``) or of the polygon's edges
    (``cage.edge_normals()``); points on the cage get the limit from inside. Outside the cage the
    Green integrals alone give 0; by default the coordinates of outside points are continued
    through the cage's nearest faces (Lipman et al.'s exterior extension, blended between faces at
    nearly the same distance: docs/accuracy.md), so that they too are reproduced at rest and move
    continuously as they cross the cage.

    Args:
        points: ``(*, 3)`` query points.
        cage: a closed triangle cage (quad cages are refused: use ``cage.triangulated()``) or a
            closed polygon.
            Or a batch of cages ``(*B, V, D)`` with one topology: then ``points`` are
            ``(*B, N, D)`` (or ``(N, D)``, shared) and every result gains the batch shape in front
            (``(*B, N, V)``); each element equals the call on ``cage[b]`` (docs/learning.md).
        chunk_size: points per chunk (default: about 130k point–face pairs).
        dtype: dtype of the result (default: that of the inputs). The kernels compute in float64
            whatever it is (float32 would lose accuracy near the cage: see docs/accuracy.md).
        progress: ``True`` for a progress bar, or a callable ``progress(done, total)``.
        backend: ``"auto"`` (the native CPU kernel for 3D float64 on the CPU when it can be built
            and no autograd graph is needed, the Triton kernel for 3D CUDA tensors when triton is
            installed, else torch), ``"native"``, ``"triton"`` (3D; docs/gpu.md) or ``"torch"``.
        exterior: ``"extend"`` (default) continues the coordinates outside the cage; ``"none"``
            gives the bare Green integrals there (which map outside points to the origin).

    Returns:
        ``(phi (*, V), psi (*, T))``, ``T`` the triangles, or the edges in 2D.

    Raises:
        CageError: a quad cage.
        PointsError: bad points (shape, device, NaN or inf).
        ValueError: an unknown ``exterior``.

    Examples:
        >>> import torch, torchcage
        >>> from torchcage import functional as F
        >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
        >>> x = torch.tensor([[0.1, 0.2, -0.3], [0.5, 0.5, 0.99]], dtype=torch.float64)
        >>> phi, psi = F.green_coordinates(x, cube)
        >>> phi.shape, psi.shape
        (torch.Size([2, 8]), torch.Size([2, 12]))
        >>> torch.allclose(phi @ cube.vertices + psi @ cube.triangle_normals(), x)
        True
    """
    if exterior not in ("extend", "none"):
        raise ValueError(f"exterior must be 'extend' or 'none', got {exterior!r}")
    if through_op(points, cage) and exterior == "extend":  # one opaque op (compile, vmap: :mod:`_core.compiled`)
        phi, psi = COMPILED(points, cage, chunk_size, backend, dtype=dtype)
        return phi, psi
    backend = resolve(backend)
    points, cage = as_inputs(points, cage)
    if cage.is_batched:
        # One native call for the whole batch (a triangle cage, the CPU; with a graph, one more
        # for the backward pass) ...
        batched = coordinates_batch(points, cage, chunk_size, dtype, progress, backend, exterior)
        if batched is None:  # (polygons without a graph: the torch kernel vectorised over the batch)
            batched = polygons_batch(points, cage, chunk_size, dtype, progress, backend, exterior)
        if batched is not None:
            return batched
        # ... elsewhere (the torch or Triton kernels in 3D, a graph in 2D, torch.func transforms)
        # one call per element.
        return over_cage_batch(
            green_coordinates,
            points,
            cage,
            chunk_size=chunk_size,
            dtype=dtype,
            progress=progress,
            backend=backend,
            exterior=exterior,
        )
    flat = check_points(points, cage)
    compute, out_dtype = result_dtype(flat, cage, dtype)
    # Everything about the cage's centre (the coordinates do not change under translation): about
    # the origin, a cage moved by 1e6 of its sizes had an on-cage band of 2 eps 1e6 sizes, whose
    # points took the interpolant's derivatives (Jacobians off by 0.4 at 1e-9 of the size from a
    # vertex), and every difference of corner and point lost 1e6 eps.
    x, cage_c = centred(flat.to(compute), cage, compute)
    if cage.dim == 3:  # (points a few tolerances from a vertex: the limit at the vertex)
        x = snap_to_vertices(x, cage_c.vertices, VERTEX_SNAP * ON_CAGE_TOLERANCE * cage.scale)
    if records_graph(flat, cage.vertices) and not is_functorch_wrapped_tensor(flat):
        if cage.dim == 3:
            triangle_green_data(cage_c, compute)  # the same checks as the plain path (a triangle cage)
        phi, psi = green_function(x, cage_c, chunk_size, backend)
    else:
        phi, psi = green_flat(x, cage_c, chunk_size, progress, backend)
    if exterior == "extend":
        own = not records_graph(phi, psi)  # (the kernel's fresh tables: continued in place)
        phi, psi, _ = extend_outside(x, cage_c, phi.to(compute), psi.to(compute), inplace=own)
    # (the sum made 1 where the caller multiplies by the vertices: about the origin)
    phi = unit_sum(phi, flat.to(phi.dtype), cage.vertices.to(phi.dtype))
    lead = points.shape[:-1]
    return phi.to(out_dtype).reshape(*lead, cage.num_vertices), psi.to(out_dtype).reshape(*lead, psi.shape[-1])
