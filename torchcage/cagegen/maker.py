"""``make_cage``: an enclosing, self-intersection-free cage for a mesh or a point cloud.

The pipeline (each step its own module):

1. :mod:`.inputs`: check the mesh (or point cloud);
2. :mod:`.envelope`: a closed envelope at twice the margin, by a morphological closing on a voxel
   grid (bridges holes and gaps narrower than ``2 seal``, so open, multi-part and inner-face input
   works), extracted by marching cubes;
3. :mod:`.simplify`: quadric decimation to the target vertex count;
4. :mod:`.enclosure`: faces pushed outward until every input vertex is at least ``margin`` inside,
   never letting the surface pass through itself;
5. :mod:`.quads` (``kind="quad"``): triangle pairs merged into quads valid for QMVC (a maximum
   weight matching), then step 4 again for the bilinear patches (quads that lose validity are
   split back), and :mod:`.tighten` pulls the vertices that the bent patches carried far out back
   towards the shape;
6. the result is validated as a :class:`~torchcage.Cage` (closed, manifold, outward, no
   self-intersection) before it is returned.
"""

from __future__ import annotations

import sys
import time
import warnings
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
import torch

from torchcage.cage import Cage
from torchcage.cagegen.checks import self_intersections
from torchcage.cagegen.enclosure import push_outward
from torchcage.cagegen.envelope import envelope, point_spacing
from torchcage.cagegen.inputs import MeshInput, check_input
from torchcage.cagegen.quads import MIN_COSINE, corner_cosines, pair_triangles
from torchcage.cagegen.simplify import decimate
from torchcage.cagegen.tighten import tighten
from torchcage.errors import CageError, CageMakerError

__all__ = ["DEFAULT_MARGIN", "DEFAULT_SEAL", "make_cage"]

#: Default margin, as a fraction of the shape's bounding-box diagonal.
DEFAULT_MARGIN = 0.005
#: Default closing radius, as a fraction of the diagonal.
DEFAULT_SEAL = 0.03
#: Where a cage cannot be made without self-intersections (thin features that decimation folds
#: onto each other), the envelope is rebuilt twice as far out (and sealed twice as wide), this often.
INFLATIONS = 4
#: Before that, decimation targets within this fraction of ``target_vertices`` are tried, at most
#: ``TARGETS`` of them (decimations of one envelope to nearby sizes differ in where they fold and
#: in how many triangles pair into valid quads).
TARGET_SPREAD = 0.1
TARGETS = 7
#: An envelope on which this many targets fail before any succeeds is inflated.
FAILED_TARGETS = 2
#: The quad kind's least fraction of quads among the faces; below it, the next target is tried.
QUAD_FRACTION = 0.8


def _quadify(
    v: torch.Tensor, tri: torch.Tensor, points: torch.Tensor, margin: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pair triangles into quads and push the bilinear patches out; quads that the push leaves
    invalid for QMVC are split back into their triangles, and the rest pushed again."""
    left, quads = pair_triangles(v, tri)
    for _ in range(4):
        v = push_outward(v, left, quads, points, margin)
        bad = corner_cosines(v[quads]) <= 0.2 * MIN_COSINE
        if not bad.any():
            return v, left, quads
        left, quads = _split_back(left, quads, bad)
    v = push_outward(v, left, quads, points, margin)
    # quads still not valid are split along q0-q2, a triangulation the clearance was measured on
    left, quads = _split_back(left, quads, corner_cosines(v[quads]) <= 0)
    return v, left, quads


def _split_back(left: torch.Tensor, quads: torch.Tensor, bad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Triangles ``left`` plus the ``bad`` quads' halves along ``q0-q2``, and the other quads."""
    return torch.cat([left, quads[bad][:, [0, 1, 2]], quads[bad][:, [0, 2, 3]]]), quads[~bad]


def make_cage(
    vertices: Any,
    faces: Any = None,
    *,
    target_vertices: int = 200,
    kind: Literal["triangle", "quad"] = "triangle",
    margin: float | None = None,
    seal: float | None = None,
    resolution: int = 128,
    dtype: torch.dtype = torch.float64,
    progress: bool | Callable[[str], None] = False,
) -> Cage:
    """Make a closed, coarse cage that encloses a mesh or a point cloud.

    Args:
        vertices: ``(N, 3)`` the shape's vertices (tensor or array).
        faces: ``(F, 3)`` its triangles, or ``None`` for a point cloud. The mesh need not be
            watertight or manifold: holes, several parts and inner faces are fine.
        target_vertices: the cage's vertex count, met within about 10% (at least 8).
        kind: ``"triangle"`` or ``"quad"`` (quad-dominant: triangle pairs merged into quads that
            are valid for QMVC and QGC, with the leftover triangles).
        margin: the least distance from every input vertex to the cage (default 0.005 of the
            bounding-box diagonal). The envelope is first built at twice this distance.
        seal: closing radius (default 0.03 of the diagonal, and for a point cloud at least twice
            its point spacing): holes, gaps and concavities narrower than about ``2 seal`` are
            bridged; wider openings are followed into.
        resolution: voxels along the longest side of the envelope's grid (detail of the envelope).
        dtype: dtype of the cage's vertices.
        progress: ``True`` to print each step with its time on stderr, or a callable
            ``progress(step)`` that receives a line per step (envelope, decimation, push, quads, checks).

    Returns:
        a validated :class:`~torchcage.Cage` (closed, manifold, outward, free of
        self-intersections) with every input vertex at least ``margin`` inside it.

    Raises:
        MeshError: unusable input (empty, NaN, a single point, only degenerate faces, bad indices).
        CageMakerError: the guarantees could not be met with these settings (the message says
            which setting to change).
        ImportError: the ``cage`` extra is not installed.

    Warns:
        UserWarning: ``kind="quad"`` and no decimation near the target gives at least 80% quads
            (coarse cages of bent shapes); the cage with the most quads is returned.

    Examples:
        >>> import torch, torchcage
        >>> from torchcage.geometry import inside_cage
        >>> points = torch.randn(2000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
        >>> cage = torchcage.make_cage(points, target_vertices=40)
        >>> 30 <= cage.num_vertices <= 50, bool(inside_cage(points, cage).all())
        (True, True)
    """
    if kind not in ("triangle", "quad"):
        raise ValueError(f'kind must be "triangle" or "quad", got {kind!r}')
    if int(target_vertices) != target_vertices or target_vertices < 8:
        raise ValueError(f"target_vertices must be an integer of at least 8, got {target_vertices!r}")
    if int(resolution) != resolution or resolution < 16:
        raise ValueError(f"resolution must be an integer of at least 16, got {resolution!r}")
    mesh = check_input(vertices, faces)
    margin = DEFAULT_MARGIN * mesh.diagonal if margin is None else float(margin)
    if not (np.isfinite(margin) and 0 < margin < mesh.diagonal):
        raise ValueError(f"margin must be positive and smaller than the shape ({mesh.diagonal:.4g}), got {margin!r}")
    if seal is None:
        seal = DEFAULT_SEAL * mesh.diagonal
        if mesh.faces is None:
            seal = max(seal, 2.0 * point_spacing(mesh.vertices))
    seal = float(seal)
    if not (np.isfinite(seal) and seal >= 0):
        raise ValueError(f"seal must be zero or positive, got {seal!r}")

    points = torch.from_numpy(mesh.vertices)
    report = _reporter(progress)
    failure: CageMakerError | None = None
    for attempt in range(INFLATIONS + 1):
        try:
            return _attempt(
                mesh, points, int(target_vertices), kind, margin, seal, int(resolution), attempt, dtype, report
            )
        except CageMakerError as err:
            failure = err
            report(f"attempt {attempt + 1} failed ({err}); rebuilding the envelope twice as far out")
    raise CageMakerError(f"{failure} (after {INFLATIONS + 1} envelopes, each twice as far out)") from failure


def _reporter(progress: bool | Callable[[str], None]) -> Callable[[str], None]:
    """``progress`` as a callable of one line (``True``: stderr, with the time since the start)."""
    if callable(progress):
        return progress
    if not progress:
        return lambda line: None
    start = time.perf_counter()
    return lambda line: print(f"make_cage [{time.perf_counter() - start:5.1f} s] {line}", file=sys.stderr)


def _attempt(
    mesh: MeshInput,
    points: torch.Tensor,
    target_vertices: int,
    kind: str,
    margin: float,
    seal: float,
    resolution: int,
    attempt: int,
    dtype: torch.dtype,
    report: Callable[[str], None],
) -> Cage:
    """One envelope (offset ``2^(attempt + 1) margin``, seal ``2^attempt seal``), decimated, pushed
    out, checked: decimation targets near ``target_vertices`` are tried in turn (:func:`_targets`)
    until one gives a cage (and, for quads, at least ``QUAD_FRACTION`` quads)."""
    grow = 2.0**attempt
    report(f"envelope: closing and offset on a {resolution}-voxel grid")
    fine_v, fine_f = envelope(mesh, offset=2.0 * margin * grow, seal=seal * grow, resolution=resolution)
    best: tuple[float, torch.Tensor, torch.Tensor, torch.Tensor] | None = None
    failure: CageMakerError | None = None
    failures = 0
    for target in _targets(target_vertices):
        if best is None and failures >= FAILED_TARGETS:
            break  # this envelope folds at every size near the target: inflate it instead
        report(f"decimation: {fine_v.shape[0]:,} envelope vertices to about {target}")
        try:
            v, tri = _coarse(fine_v, fine_f, target, points, margin, report)
        except CageMakerError as err:
            failure, failures = err, failures + 1
            report(f"decimation to {target} failed ({err})")
            continue
        quads = torch.zeros((0, 4), dtype=torch.long)
        if kind == "quad":
            report("quads: pairing triangles into quads valid for QMVC, pushing the patches out")
            try:
                v, tri, quads = _quadify(v, tri, points, margin)
            except CageMakerError as err:
                failure, failures = err, failures + 1
                report(f"quads on the cage of {v.shape[0]} vertices failed ({err})")
                continue
        fraction = quads.shape[0] / (quads.shape[0] + tri.shape[0])
        if best is None or fraction > best[0]:
            best = (fraction, v, tri, quads)
        if kind == "triangle" or fraction >= QUAD_FRACTION:
            break
        report(f"{fraction:.0%} quads on the cage of {v.shape[0]} vertices; trying another decimation")
    if best is None:
        assert failure is not None
        raise failure
    fraction, v, tri, quads = best
    if kind == "quad" and fraction < QUAD_FRACTION:
        warnings.warn(
            f"only {fraction:.0%} of the made cage's faces are quads (wanted {QUAD_FRACTION:.0%}): at this size too "
            "many neighbouring triangles bend too much to make quads valid for QMVC; try a higher target_vertices",
            stacklevel=3,
        )
    if kind == "quad":
        report("tightening: pulling the farthest vertices back towards the shape")
        v = tighten(v, tri, quads, points, None if mesh.faces is None else torch.from_numpy(mesh.faces), margin)
    report("checks: self-intersections and validation")
    if self_intersections(v, tri, quads):
        raise CageMakerError(
            "the made cage intersects itself; try a higher target_vertices, a larger seal or a larger margin"
        )
    faces_out = tri.tolist() + quads.tolist()
    return Cage(v.to(dtype), faces_out, check_intersections=True)


def _targets(target_vertices: int) -> list[int]:
    """Decimation targets to try, nearest first: ``target_vertices``, then steps of about 3% of it
    up and down, within ``TARGET_SPREAD`` of it, at most ``TARGETS``."""
    step = max(1, round(0.03 * target_vertices))
    out = [target_vertices]
    k = 1
    while len(out) < TARGETS and k * step <= TARGET_SPREAD * target_vertices:
        out += [target_vertices + k * step, target_vertices - k * step]
        k += 1
    return [t for t in out[:TARGETS] if t >= 8]


def _coarse(
    fine_v: torch.Tensor,
    fine_f: torch.Tensor,
    target: int,
    points: torch.Tensor,
    margin: float,
    report: Callable[[str], None],
) -> tuple[torch.Tensor, torch.Tensor]:
    """The envelope decimated to about ``target`` vertices, checked, and pushed out until every
    point is ``margin`` inside; ``CageMakerError`` where that cannot be done."""
    v_np, f_np = decimate(fine_v, fine_f, target)
    v = torch.from_numpy(v_np)
    tri = torch.from_numpy(f_np)
    try:
        Cage(v, tri, check_intersections=False)
    except CageError as err:
        raise CageMakerError(
            f"the simplified envelope is not a valid cage ({err}); try a higher target_vertices or resolution"
        ) from err
    if self_intersections(v, tri):
        raise CageMakerError(
            "the simplified envelope intersects itself; try a higher target_vertices or a larger margin"
        )
    report(f"enclosure: pushing faces out until all {points.shape[0]:,} input vertices are inside")
    return push_outward(v, tri, torch.zeros((0, 4), dtype=torch.long), points, margin), tri
