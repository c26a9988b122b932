"""Green coordinates for closed triangle cages (3D) and closed polygons (2D): the public function.

The closed forms and their numerical care are described in ``_green3d`` and ``_green2d``.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from .. import _native
from ..cage import Cage
from ._batch import over_cage_batch
from ._common import check_points, chunks, default_chunk, result_dtype
from ._green2d import green2d_coordinates
from ._green3d import green3d_coordinates, triangle_green_data
from ._green3d_native import native_chunk, native_tables

__all__ = ["green_coordinates"]


def green_coordinates(
    points: torch.Tensor,
    cage: Cage,
    *,
    chunk_size: int | None = None,
    dtype: torch.dtype | None = None,
    progress: bool | Callable[[int, int], None] = False,
    backend: str = "auto",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Green coordinates (Lipman, Levin, Cohen-Or 2008) of points inside a closed triangle cage
    or a closed polygon.

    At rest, ``phi @ cage.vertices + psi @ n = points`` for points inside the cage, with ``n`` the
    unit outward normals of the triangles (``cage.triangle_normals()``) or of the polygon's edges
    (``cage.edge_normals()``); points on the cage get the limit from inside. Outside the cage the
    same sums give 0: Green coordinates are defined inside.

    Args:
        points: ``(*, 3)`` query points.
        cage: a closed triangle cage (quad cages are refused: use ``cage.triangulated()``) or a
            closed polygon.
        chunk_size: points per chunk (default: about 130k point–face pairs).
        dtype: dtype of the result (default: that of the inputs). The kernels compute in float64
            whatever it is (float32 would lose accuracy near the cage: see docs/accuracy.md).
        progress: ``True`` for a progress bar, or a callable ``progress(done, total)``.
        backend: ``"auto"`` (the native CPU kernel for 3D float64 on the CPU when it can be built
            and no autograd graph is needed, else torch), ``"native"`` or ``"torch"``.

    Returns:
        ``(phi (*, V), psi (*, T))``, ``T`` the triangles, or the edges in 2D.

    Raises:
        CageError: a quad cage.
        PointsError: bad points (shape, device, NaN or inf).

    Example:
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
    if cage.is_batched:
        return over_cage_batch(
            green_coordinates, points, cage, chunk_size=chunk_size, dtype=dtype, progress=progress, backend=backend
        )
    flat = check_points(points, cage)
    compute, out_dtype = result_dtype(flat, cage, dtype)
    x = flat.to(compute)
    lib = _native.select(backend, x, cage.vertices)
    if cage.dim == 3:
        data = triangle_green_data(cage, compute)
        T = data.tri.shape[0]
        tables = native_tables(data, cage.vertices.to(compute)) if lib is not None else {}

        def kernel(c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            return green3d_coordinates(c, data, cage.num_vertices)
    else:
        T = cage.edges.shape[0]
        poly = cage.to(compute)

        def kernel(c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            return green2d_coordinates(c, poly)

    # The native kernel needs no temporaries beyond its outputs: chunks only pace the progress bar.
    size = chunk_size if chunk_size is not None else default_chunk(T, 1 << 23 if lib is not None else 1 << 17)
    phi = torch.empty(x.shape[0], cage.num_vertices, dtype=compute, device=x.device)
    psi = torch.empty(x.shape[0], T, dtype=compute, device=x.device)
    for sl in chunks(x.shape[0], size, progress, desc="Green coordinates"):
        if lib is not None:  # writes straight into the row blocks (contiguous): no copies
            native_chunk(x[sl], tables, lib, phi[sl], psi[sl])
        else:
            phi[sl], psi[sl] = kernel(x[sl])
    lead = points.shape[:-1]
    return phi.to(out_dtype).reshape(*lead, cage.num_vertices), psi.to(out_dtype).reshape(*lead, T)
