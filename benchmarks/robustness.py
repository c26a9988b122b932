"""Robustness sweep: adversarial queries for every coordinate family, values and gradients.

For each family and cage (the eight QMVC cages when the data set is present, and the hard cages of
:func:`torchcage.testing.hard_cages`), queries from :func:`torchcage.testing.adversarial_points`
(on and 1e-15..1e-3 of the size from vertices, edges and faces, on support planes and edge lines,
far away) are evaluated with the default backend (values) and with gradients of a random linear
functional with respect to the points and the rest cage's vertices (the torch kernels, through
the custom autograd Functions where they exist). Prints one table: queries, non-finite values,
non-finite gradients, the worst partition of unity and linear precision (relative to the cage
size; far points relative to their distance) and the category where each occurs.

A second table counts damaged cages (coincident or pinched vertices, folded flat, NaN/inf vertices),
given through the constructor, ``with_vertices`` and a ``validate="topology"`` batch to every
closed-form family: each must be refused with a ``CageError``, none answered.

Usage:
    python benchmarks/robustness.py [--data ../shared/data] [--per-category 2000] [--grad-per-category 200]
        [--dtype float64|float32] [--families mvc3d,mvc2d,...] [--invalid-trials 20]

The test suite runs a small slice (``tests/test_robustness.py``).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch

import torchcage
from torchcage import functional as F
from torchcage.geometry import inside_cage
from torchcage.testing import QMVC_MODELS, adversarial_points, hard_cages

MODELS = list(QMVC_MODELS)
FAMILIES = ["mvc3d", "mvc2d", "mvc_derivatives", "qmvc", "gc", "qgc", "lbc", "image"]

#: Mesh size of the LBC solves in the sweep (one solve per cage, reused for every category).
LBC_CELLS = 1500
_LBC_SOLUTIONS: dict[int, object] = {}


@dataclass
class Stats:
    """Running totals of one family over all its cages."""

    queries: int = 0
    bad_values: int = 0
    grad_queries: int = 0
    bad_grads: int = 0
    on_cage_refused: int = 0
    errors: list[str] = field(default_factory=list)
    pu: tuple[float, str] = (0.0, "")
    lp: tuple[float, str] = (0.0, "")
    far: tuple[float, str] = (0.0, "")
    far_pu: tuple[float, str] = (0.0, "")

    def worst(self, name: str, value: float, where: str) -> None:
        if value > getattr(self, name)[0] or math.isnan(value):
            setattr(self, name, (value, where))


def _nonfinite(*ts: torch.Tensor) -> torch.Tensor:
    """Per-row mask of rows holding NaN or inf in any of ``ts`` (each ``(N, ...)``)."""
    bad = torch.zeros(ts[0].shape[0], dtype=torch.bool)
    for t in ts:
        bad |= ~torch.isfinite(t.reshape(t.shape[0], -1)).all(dim=1)
    return bad


def _coordinates(family: str, x: torch.Tensor, cage: torchcage.Cage, dtype: torch.dtype | None):
    """(weights, extra) of a family; Green families return (phi, psi)."""
    if family in ("mvc3d", "mvc2d"):
        return F.mean_value_coordinates(x, cage, dtype=dtype), None
    if family == "qmvc":
        return F.quad_mean_value_coordinates(x, cage, dtype=dtype), None
    if family == "gc":
        return F.green_coordinates(x, cage, dtype=dtype)
    if family == "qgc":
        return F.quad_green_coordinates(x, cage, dtype=dtype)
    if family == "lbc":
        key = id(cage)
        if key not in _LBC_SOLUTIONS:
            _LBC_SOLUTIONS[key] = F.solve_local_barycentric(cage, target_cells=LBC_CELLS)
        return F.local_barycentric_coordinates(x, cage, solution=_LBC_SOLUTIONS[key]).to_dense(), None
    if family == "mvc_derivatives":
        lam, grad, hess = F.mean_value_derivatives(x, cage, order=2)
        return lam, torch.cat([grad.flatten(1), hess.flatten(1)], dim=1)
    raise ValueError(family)


def _normals(family: str, cage: torchcage.Cage) -> torch.Tensor | None:
    if family == "gc":
        return cage.triangle_normals() if cage.dim == 3 else cage.edge_normals()
    if family == "qgc":
        T = cage.triangles
        n = torch.nn.functional.normalize(
            torch.linalg.cross(*(cage.vertices[T][:, i] - cage.vertices[T][:, 0] for i in (1, 2)), dim=-1), dim=-1
        )
        return torch.cat([n, cage.quad_corner_normals().reshape(-1, 3)])
    return None


def _inside(x: torch.Tensor, cage: torchcage.Cage) -> tuple[torch.Tensor, torch.Tensor]:
    """(inside, sure) masks. A bilinear quad lies in the tetrahedron of its corners, between its two
    diagonal splits: where the winding numbers of both triangulations agree, so does the sheet's."""
    from torchcage.geometry import winding_number

    a = inside_cage(x, cage)
    if not cage.has_quads:
        return a, torch.ones_like(a)
    q = cage.quads
    tri = (
        torch.cat([cage.triangles, q[:, [0, 1, 3]], q[:, [1, 2, 3]]])
        if cage.triangles.shape[0]
        else torch.cat([q[:, [0, 1, 3]], q[:, [1, 2, 3]]])
    )
    b = winding_number(x.to(cage.vertices.dtype), cage.vertices, tri) > 0.5
    return a, a == b


def _inside_sheets(x: torch.Tensor, cage: torchcage.Cage, n: int = 64) -> torch.Tensor:
    """Inside masks from the winding number of the cage with its quads' bilinear sheets: that of the
    split ``(q0 q1 q3), (q1 q2 q3)``, corrected for every quad whose tetrahedron holds the point by the
    winding number of the closed surface made of its sheet (tessellated ``n x n``, within
    ``|q0 - q1 + q2 - q3| / (8 n^2)`` of it) and the split reversed (0 for the other quads)."""
    from torchcage.geometry import winding_number

    q = cage.quads
    tri = torch.cat([cage.triangles, q[:, [0, 1, 3]], q[:, [1, 2, 3]]])
    w = winding_number(x.to(cage.vertices.dtype), cage.vertices, tri)
    P = cage.vertices[q]  # (Q, 4, 3)
    # points inside each quad's tetrahedron (the same sign of the four orientations)
    faces = [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)]
    sides = []
    for a, b, c in faces:
        nrm = torch.linalg.cross(P[:, b] - P[:, a], P[:, c] - P[:, a], dim=-1)
        sides.append(((x[:, None] - P[None, :, a]) * nrm[None]).sum(-1))
    S = torch.stack(sides)  # (4, m, Q)
    hold = (S > 0).all(dim=0) | (S < 0).all(dim=0)
    t = torch.linspace(0, 1, n + 1, dtype=cage.vertices.dtype)
    U, W = torch.meshgrid(t, t, indexing="ij")
    wts = torch.stack([(1 - U) * (1 - W), U * (1 - W), U * W, (1 - U) * W], dim=-1).reshape(-1, 4)
    idx = torch.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    cell = torch.cat([torch.stack([a, b, c], -1).reshape(-1, 3), torch.stack([a, c, d], -1).reshape(-1, 3)])
    corners = {0: 0, 1: n * (n + 1), 2: (n + 1) ** 2 - 1, 3: n}  # grid index of each corner
    back = torch.tensor([[corners[0], corners[3], corners[1]], [corners[1], corners[3], corners[2]]])
    closed = torch.cat([cell, back])  # the sheet, then the split (q0 q1 q3), (q1 q2 q3) reversed
    for qi in torch.nonzero(hold.any(dim=0)).flatten().tolist():
        rows = torch.nonzero(hold[:, qi]).flatten()
        grid = wts @ P[qi]
        w[rows] = w[rows] + winding_number(x[rows].to(grid.dtype), grid, closed)
    return w > 0.5


def sweep_values(family: str, cage: torchcage.Cage, name: str, pts: dict, side: dict, stats: Stats, dtype) -> None:
    """Values of every category: finiteness, partition of unity and linear precision."""
    size = cage.scale
    green = family in ("gc", "qgc")
    for cat, x in pts.items():
        if family == "image":
            continue
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                w, extra = _coordinates(family, x, cage, dtype)
        except torchcage.errors.PointsError as err:
            if family == "mvc_derivatives" and "lie on the cage" in str(err):
                stats.on_cage_refused += x.shape[0]  # documented: no derivatives on the cage itself
                continue
            stats.errors.append(f"{name}/{cat}: {type(err).__name__}: {str(err)[:120]}")
            continue
        except Exception as err:  # an error is a finding too: the table reports it
            stats.errors.append(f"{name}/{cat}: {type(err).__name__}: {str(err)[:120]}")
            continue
        stats.queries += x.shape[0]
        w64 = w.to(torch.float64)
        bad = _nonfinite(w64, *([extra] if extra is not None else []))
        stats.bad_values += int(bad.sum())
        ok = ~bad
        # quad Green coordinates and LBC (defined on the meshed interior, outside points clamped to
        # it) reproduce points inside the cage and on it
        if family in ("qgc", "lbc"):
            known = side[cat]
            inside, sure = _inside(x, cage)
            if family == "qgc" and not bool(sure.all()):
                # Inside a quad's tetrahedron the side of the sheet is neither split's. A side known
                # by construction can be wrong there (an offset along a face normal near a twisted
                # edge crossed the neighbouring sheet: 1 of 1e6 points was labelled inside), and so
                # can a tessellation of the sheets (for points nearer than its error): a point
                # whose label and tessellated side disagree has no known side and is skipped.
                unsure = ~sure & ~torch.isnan(known) & (known != 0)
                rows = torch.nonzero(unsure).flatten()
                if rows.numel():
                    dense = _inside_sheets(x[rows], cage)
                    conflict = dense != (known[rows] < 0)
                    known = known.clone()
                    known[rows[conflict]] = 1.0  # (treated as outside: not checked)
            # a side known by construction (an offset along the normal) holds only within the local
            # feature size: where the winding numbers are sure and disagree (a thin part), skip
            agree = (known == 0) | ~sure | (inside == (known < 0))
            ok &= torch.where(torch.isnan(known), sure & inside, (known <= 0) & agree)
        if not bool(ok.any()):
            continue
        w64, xv = w64[ok], x[ok].to(torch.float64)
        pu = (w64.sum(dim=1) - 1).abs()
        rec = w64 @ cage.vertices.to(torch.float64)
        if green:
            rec = rec + extra[ok].to(torch.float64) @ _normals(family, cage).to(torch.float64)
        err = (rec - xv).norm(dim=1)
        if cat == "far":
            stats.worst("far", float((err / (xv - cage.vertices.mean(0).to(xv)).norm(dim=1)).max()), f"{name}/{cat}")
        else:
            stats.worst("lp", float(err.max()) / size, f"{name}/{cat}")
        if cat == "far":  # (partition of unity far away: reported in the far column with the LP)
            stats.worst("far_pu", float(pu.max()), f"{name}/{cat}")
        else:
            stats.worst("pu", float(pu.max()), f"{name}/{cat}")


#: Points per backward pass of the gradient sweep (the autograd graphs of the quad families hold
#: about 1 MB per point: 10^4 points at once ran out of memory).
GRAD_CHUNK = 1024


def sweep_grads(family: str, cage: torchcage.Cage, name: str, pts: dict, stats: Stats, dtype, k: int) -> None:
    """Gradients of a random linear functional with respect to the points and the rest vertices,
    chunk by chunk, and of the module's output with respect to the deformed cage
    (:func:`_deformed_grads`)."""
    g = torch.Generator().manual_seed(1 + SEED)
    if family == "image":
        return
    for cat, xs in pts.items():
        xs = xs[:k]
        for s in range(0, xs.shape[0], GRAD_CHUNK):
            x = xs[s : s + GRAD_CHUNK].clone().requires_grad_()
            V = cage.vertices.clone().requires_grad_()
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    c = torchcage.Cage(V, cage.faces)
                    w, extra = _coordinates(family if family != "mvc_derivatives" else "mvc3d", x, c, dtype)
                    loss = (w * torch.randn(w.shape, generator=g, dtype=w.dtype)).sum()
                    if extra is not None:
                        loss = loss + (extra * torch.randn(extra.shape, generator=g, dtype=extra.dtype)).sum()
                    gx, gV = torch.autograd.grad(loss, (x, V), allow_unused=True)
            except Exception as err:
                stats.errors.append(f"grad {name}/{cat}: {type(err).__name__}: {str(err)[:120]}")
                continue
            stats.grad_queries += x.shape[0]
            stats.bad_grads += int(_nonfinite(gx if gx is not None else torch.zeros_like(x)).sum())
            if gV is not None and not bool(torch.isfinite(gV).all()):
                stats.bad_grads += 1
                stats.errors.append(f"grad {name}/{cat}: non-finite gradient w.r.t. the rest vertices")
        _deformed_grads(family, cage, name, cat, xs.detach(), stats, g)


MODULES = {
    "mvc3d": "MeanValueCoordinates",
    "mvc2d": "MeanValueCoordinates",
    "qmvc": "QuadMeanValueCoordinates",
    "gc": "GreenCoordinates",
    "qgc": "QuadGreenCoordinates",
}


#: The categories whose points the deformed-cage check builds modules on (None: all of them).
DEFORMED_CATEGORIES: tuple[str, ...] | None = None


def _deformed_grads(family: str, cage, name: str, cat: str, x: torch.Tensor, stats: Stats, g) -> None:
    """Gradients of the module's output with respect to the deformed cage: a random pose, a pose
    that collapses the cage to a point and one that flattens it onto a plane."""
    if family not in MODULES or (DEFORMED_CATEGORIES is not None and cat not in DEFORMED_CATEGORIES):
        return
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            m = getattr(torchcage, MODULES[family])(cage, x)
            V = cage.vertices
            poses = {
                "random": V + 0.1 * cage.scale * torch.randn(V.shape, generator=g, dtype=V.dtype),
                "collapsed": V.mean(0, keepdim=True).expand_as(V).clone(),
                "flattened": V * torch.tensor([1.0] * (V.shape[1] - 1) + [0.0], dtype=V.dtype),
            }
            for pose_name, pose in poses.items():
                P = pose.clone().requires_grad_()
                y = m(P)
                (gP,) = torch.autograd.grad((y * torch.randn(y.shape, generator=g, dtype=y.dtype)).sum(), P)
                stats.grad_queries += x.shape[0]
                if not (bool(torch.isfinite(y).all()) and bool(torch.isfinite(gP).all())):
                    stats.bad_grads += 1
                    stats.errors.append(f"grad {name}/{cat}: non-finite w.r.t. the deformed cage ({pose_name} pose)")
    except Exception as err:
        stats.errors.append(f"deformed {name}/{cat}: {type(err).__name__}: {str(err)[:120]}")


def sweep_image(cage2d: torchcage.Cage, name: str, stats: Stats, dtype) -> None:
    """warp_image gradients with respect to the deformed cage, on a cage drawn on pixel centres."""
    from torchcage.image import warp_image

    P = cage2d.vertices
    lo = P.min(dim=0).values
    Pint = torch.round((P - lo) / (P.max(dim=0).values - lo).max() * 20 + 2)  # integer pixel coordinates
    try:
        cage = torchcage.Cage(Pint.to(torch.float64), cage2d.edges)
    except ValueError:
        return
    img = torch.rand(1, 1, 26, 26, dtype=torch.float64)
    for method in ("mvc", "gc"):
        D = Pint[None].to(torch.float64).clone().requires_grad_()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                out = warp_image(img, cage, D, method=method)
                (out * torch.rand_like(out)).sum().backward()
        except Exception as err:
            stats.errors.append(f"image {name}/{method}: {type(err).__name__}: {str(err)[:120]}")
            continue
        stats.queries += img.shape[-1] * img.shape[-2]
        stats.bad_values += int((~torch.isfinite(out)).sum())
        stats.grad_queries += img.shape[-1] * img.shape[-2]
        stats.bad_grads += int((~torch.isfinite(D.grad)).sum())


def cages_for(family: str, data: Path | None) -> dict[str, torchcage.Cage]:
    """The cages a family is swept on."""
    out: dict[str, torchcage.Cage] = {}
    hard = hard_cages()
    if family == "lbc":  # (each cage costs a solve: the 2D data set's cages and small 3D ones)
        out["blob2d"] = torchcage.load_cage(torchcage.data.path("blob2d.obj"))
        if data is not None and (data / "lbc2d").is_dir():
            for f in sorted((data / "lbc2d").glob("*.obj")):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    out[f.stem] = torchcage.load_cage(f)
        out["cube_quads"] = torchcage.load_cage(torchcage.data.path("cube.obj"))
        out["sliver_cube"] = hard["sliver_cube"]
        return out
    if family in ("mvc2d", "image"):
        out["blob2d"] = torchcage.load_cage(torchcage.data.path("blob2d.obj"))
        out["square_px"] = torchcage.Cage(
            torch.tensor([[4.0, 4], [19, 4], [19, 19], [4, 19]], dtype=torch.float64), None
        )
        if data is not None and (data / "lbc2d").is_dir():
            for f in sorted((data / "lbc2d").glob("*.obj")):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    out[f.stem] = torchcage.load_cage(f)
        return out
    quads = family in ("qmvc", "qgc")
    for k, c in hard.items():
        if quads == c.has_quads or (quads and k == "sliver_cube"):
            out[k] = c
    if quads:
        out["cube_quads"] = torchcage.load_cage(torchcage.data.path("cube.obj"))
    if data is not None:
        for m in MODELS:
            f = data / "qmvc" / f"{m}_Cage.obj"
            if f.exists():
                c = torchcage.load_cage(f)
                out[m] = c if quads else c.triangulated()
    return out


#: Skip the values pass (``--grad-only``: a gradient sweep after a values sweep).
GRAD_ONLY = False
#: Seed of the points and of the random functionals (``--seed``).
SEED = 0


def run(families: list[str], data: Path | None, per_category: int, grad_k: int, dtype, seed: int = 0) -> dict:
    results = {}
    for fam in families:
        st = Stats()
        t0 = time.perf_counter()
        for name, cage in cages_for(fam, data).items():
            if fam == "image":
                sweep_image(cage, name, st, dtype)
                continue
            pts, side = adversarial_points(cage, max(per_category, grad_k), seed=seed, sides=True)
            if not GRAD_ONLY:
                sweep_values(fam, cage, name, pts, side, st, dtype)
            if grad_k > 0 and fam != "lbc":  # (LBC has no autograd: a sparse solve)
                sweep_grads(fam, cage, name, pts, st, dtype, grad_k)
        results[fam] = (st, time.perf_counter() - t0)
    return results


def print_table(results: dict) -> None:
    cols = [
        "queries",
        "bad val",
        "grad q",
        "bad grad",
        "worst PU",
        "at",
        "worst LP",
        "at",
        "far LP",
        "far PU",
        "time s",
    ]
    widths = [9, 8, 8, 8, 10, 30, 10, 30, 9, 9, 7]
    head = f"{'family':16s} " + " ".join(
        f"{c:>{w}s}" if c != "at" else f"{c:{w}s}" for c, w in zip(cols, widths, strict=True)
    )
    print(head)
    print("-" * len(head))
    for fam, (st, dt) in results.items():
        print(
            f"{fam:16s} {st.queries:9d} {st.bad_values:8d} {st.grad_queries:8d} {st.bad_grads:8d} "
            f"{st.pu[0]:10.2e} {st.pu[1][:30]:30s} {st.lp[0]:10.2e} {st.lp[1][:30]:30s} "
            f"{st.far[0]:9.1e} {st.far_pu[0]:9.1e} {dt:7.1f}"
        )
    for fam, (st, _) in results.items():
        if st.on_cage_refused:
            print(f"  {fam}: {st.on_cage_refused} queries on the cage refused with PointsError (documented)")
        for e in st.errors[:8]:
            print(f"  {fam}: {e}")
        if len(st.errors) > 8:
            print(f"  {fam}: ... {len(st.errors) - 8} more")


DAMAGES = ("coincident neighbours", "duplicate (pinch)", "folded flat", "NaN vertex", "inf vertex")
PATHS = ("constructor", "with_vertices", "topology-only batch")
INVALID_FUNCTIONS = {
    "mvc": lambda x, c: F.mean_value_coordinates(x, c.triangulated()),
    "mvc_derivatives": lambda x, c: F.mean_value_derivatives(x, c.triangulated(), order=1),
    "gc": lambda x, c: F.green_coordinates(x, c.triangulated()),
    "green_derivatives": lambda x, c: F.green_derivatives(x, c.triangulated(), order=1),
    "qmvc": lambda x, c: F.quad_mean_value_coordinates(x, c),
    "qgc": lambda x, c: F.quad_green_coordinates(x, c),
}


def _damaged(v: torch.Tensor, edges: torch.Tensor, damage: str, g: torch.Generator) -> torch.Tensor:
    """A copy of vertices ``(V, 3)`` with one kind of damage at random places."""
    v = v.clone()
    if damage == "coincident neighbours":
        i, j = edges[int(torch.randint(edges.shape[0], (1,), generator=g))].tolist()
        v[i] = v[j]
    elif damage == "duplicate (pinch)":
        i, j = torch.randperm(v.shape[0], generator=g)[:2].tolist()
        v[i] = v[j]
    elif damage == "folded flat":
        n = torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=v.dtype), dim=0)
        v = v - (v @ n)[:, None] * n  # every vertex projected onto one plane
    else:
        v[int(torch.randint(v.shape[0], (1,), generator=g)), int(torch.randint(3, (1,), generator=g))] = (
            math.nan if damage == "NaN vertex" else math.inf
        )
    return v


def sweep_invalid(trials: int, seed: int = 0) -> dict:
    """Damaged cages (random star cages with quads, scaled by 1e-6..1e6 and moved by up to 1e6 of
    their size) given through each path that builds a cage, to each closed-form family: how many
    answers came back (silent: the defect this guards against) against clear CageErrors (the
    constructor's column counts cages it refused; the others count function calls); and the
    largest ``| |n| - 1 |`` of the unit triangle normals at those scales."""
    from torchcage.errors import CageError

    g = torch.Generator().manual_seed(seed)
    box = torchcage.load_cage(torchcage.data.path("cube.obj")).to(torch.float64)
    counts = {(d, p): [0, 0] for d in DAMAGES for p in PATHS}  # [refused, answered]
    worst_normal = 0.0
    for _ in range(trials):
        scale = 10 ** float(torch.empty(1).uniform_(-6, 6, generator=g))
        shift = scale * 10 ** float(torch.empty(1).uniform_(0, 6, generator=g)) * torch.randn(3, generator=g)
        rest = box.vertices * (0.7 + 0.6 * torch.rand(box.vertices.shape[0], 1, generator=g, dtype=torch.float64))
        cage = torchcage.Cage(rest * scale + shift.double(), box.faces)
        worst_normal = max(worst_normal, float((cage.triangle_normals().norm(dim=-1) - 1).abs().max()))
        x = cage.vertices.mean(0) + 0.2 * scale * torch.randn(16, 3, generator=g, dtype=torch.float64)
        for damage in DAMAGES:
            bad = _damaged(cage.vertices, cage.unique_edges(), damage, g)
            for path in PATHS:
                # one cage per path (the constructor's refusal counts once, not once per function);
                # a cage built, each function's answer or refusal counts
                try:
                    if path == "constructor":
                        c = torchcage.Cage(bad, cage.faces)
                    elif path == "with_vertices":
                        c = cage.with_vertices(bad)
                    else:
                        c = torchcage.Cage(torch.stack([cage.vertices, bad]), cage.faces, validate="topology")
                except CageError:
                    counts[damage, path][0] += 1
                    continue
                for fn in INVALID_FUNCTIONS.values():
                    try:
                        with warnings.catch_warnings():
                            warnings.simplefilter("ignore")
                            fn(x, c)
                        counts[damage, path][1] += 1
                    except CageError:
                        counts[damage, path][0] += 1
    return {"counts": counts, "normals": worst_normal}


def print_invalid(result: dict) -> None:
    print(f"\n{'damaged cage':24s} " + " ".join(f"{p:>22s}" for p in PATHS) + "   (refused / answered)")
    for d in DAMAGES:
        cells = " ".join(f"{result['counts'][d, p][0]:>12d} / {result['counts'][d, p][1]:<7d}" for p in PATHS)
        print(f"{d:24s} {cells}")
    print(f"unit triangle normals at scales 1e-6..1e6, moved by up to 1e6: worst | |n| - 1 | = {result['normals']:.1e}")


# ----------------------------------------------------------------------------- rounding-decided classes
def _star_polygon(n: int, g: torch.Generator) -> torch.Tensor:
    ang = torch.sort(torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi).values
    r = 0.5 + torch.rand(n, generator=g, dtype=torch.float64)
    return torch.stack([r * ang.cos(), r * ang.sin()], 1)


def _turn(g: torch.Generator) -> torch.Tensor:
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    return q * torch.linalg.det(q)


def sweep_green_precision(trials: int, seed: int = 0) -> dict[str, float]:
    """Worst errors of the classes of issue 42 items 1, 2, 4 (QGC) and 13, on random cages at
    random scales (1e-6..1e6): ``gc2d_vertex``: |sum phi - 1| and linear precision (about the
    centre, relative to the size) 1e-15..1e-6 of the size from polygon vertices, inside and
    outside, on polygons at the origin and moved by 1e6 sizes; ``needle_grad``: |d(sum phi)/dx|
    relative to max |grad phi_i| 1e-14..1e-7 of the size outside needles' edges (green_derivatives
    and the torch kernel's autograd, the cage differentiated too); ``qgc_f32``: |sum phi - 1| of
    float32 points placed on a turned quad cube's faces; ``jacobian_moved``: |J - I| (about the
    centre) on polygons moved by 1e6 sizes, 1e-9..1e-3 of the size from vertices, in units of the
    input's rounding plus eps size / r."""
    g = torch.Generator().manual_seed(seed)
    eps = torch.finfo(torch.float64).eps
    out = {"gc2d_vertex_pu": 0.0, "gc2d_vertex_lp": 0.0, "needle_grad": 0.0, "qgc_f32": 0.0, "jacobian_moved": 0.0}
    for t in range(trials):
        V = _star_polygon(5 + t % 4, g) * 10 ** (float(torch.rand(1, generator=g)) * 12 - 6)
        try:
            rest = torchcage.Cage(V)
        except torchcage.errors.CageError:
            continue
        size = rest.scale
        for moved in (False, True):
            d = torch.randn(2, generator=g, dtype=torch.float64)
            cage = rest._like(rest.vertices + (d / d.norm() * 1e6 * size if moved else 0.0))
            P = cage.vertices
            c = (P.amax(0) + P.amin(0)) / 2
            u = torch.randn(P.shape[0], 20, 2, generator=g, dtype=torch.float64)
            lo, hi = (-9, -3) if moved else (-15, -6)
            r = 10 ** (lo + (hi - lo) * torch.rand(P.shape[0], 20, 1, generator=g, dtype=torch.float64))
            x = (P[:, None] + r * size * u / u.norm(dim=-1, keepdim=True)).reshape(-1, 2)
            phi, psi, gphi, gpsi = F.green_derivatives(x, cage)
            n = cage.edge_normals()
            rec = phi @ (P - c) + psi @ n
            out["gc2d_vertex_pu"] = max(out["gc2d_vertex_pu"], float((phi.sum(1) - 1).abs().max()))
            out["gc2d_vertex_lp"] = max(out["gc2d_vertex_lp"], float((rec - (x - c)).norm(dim=1).max()) / size)
            if moved:
                J = torch.einsum("nvi,vj->nji", gphi, P - c) + torch.einsum("nti,tj->nji", gpsi, n)
                rr = (x[:, None] - P[None]).norm(dim=-1).amin(dim=1)
                unit = 1e6 * eps + eps * size / rr
                err = (J - torch.eye(2, dtype=torch.float64)).abs().amax(dim=(1, 2)) / unit
                out["jacobian_moved"] = max(out["jacobian_moved"], float(err.max()))
        # a needle (a tetrahedron of aspect 1e3..1e5 with two cap slivers) and points outside its edges
        w = 10 ** (-3 - 2 * float(torch.rand(1, generator=g)))
        Vn = torch.tensor([[-0.5, 0, 0], [0.5, 0, 0], [0.1, w, 0], [0.2, -0.3 * w, w]], dtype=torch.float64)
        Vn = Vn @ _turn(g).T * 10 ** (float(torch.rand(1, generator=g)) * 12 - 6)
        needle = torchcage.Cage(Vn, torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))
        nn_ = needle.triangle_normals()
        faces_of: dict = {}
        for fi, tri in enumerate(needle.triangles.tolist()):
            for k in range(3):
                faces_of.setdefault(tuple(sorted((tri[k], tri[(k + 1) % 3]))), []).append(fi)
        pts = []
        for (a, b), (f1, f2) in faces_of.items():
            for _ in range(3):
                dist = 10 ** (-14 + 7 * float(torch.rand(1, generator=g))) * needle.scale
                s = 0.1 + 0.8 * float(torch.rand(1, generator=g))
                m = nn_[f1] + nn_[f2]
                pts.append(Vn[a] * (1 - s) + Vn[b] * s + dist * m / m.norm())
        x = torch.stack(pts)
        _, _, gphi, _ = F.green_derivatives(x, needle)
        xr = x.clone().requires_grad_(True)
        moving = needle._like(needle.vertices.clone().requires_grad_(True))  # (the torch kernel's autograd)
        (gx,) = torch.autograd.grad(F.green_coordinates(xr, moving)[0].sum(), xr)
        mag = gphi.norm(dim=-1).amax(dim=1)
        worst = max(float((gphi.sum(1).norm(dim=1) / mag).max()), float((gx.norm(dim=1) / mag).max()))
        out["needle_grad"] = max(out["needle_grad"], worst)
        # float32 points on a turned quad cube's faces
        cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
        Vc = (cube.vertices.to(torch.float64) @ _turn(g).T * 10 ** (float(torch.rand(1, generator=g)) * 12 - 6)).float()
        qc = torchcage.Cage(Vc, cube.quads)
        f = torch.randint(0, 6, (50,), generator=g)
        uu, vv = torch.rand(2, 50, 1, generator=g, dtype=torch.float64)
        Q = Vc.double()[cube.quads[f]]
        xq = (1 - uu) * (1 - vv) * Q[:, 0] + uu * (1 - vv) * Q[:, 1] + uu * vv * Q[:, 2] + (1 - uu) * vv * Q[:, 3]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            phi_q, _ = F.quad_green_coordinates(xq.float(), qc)
        out["qgc_f32"] = max(out["qgc_f32"], float((phi_q.double().sum(1) - 1).abs().max()))
    return out


def print_green_precision(result: dict[str, float]) -> None:
    print("\nGreen coordinates where rounding decided (issue 42 items 1, 2, 4, 13): worst errors")
    for k, v in result.items():
        print(f"  {k:16s} {v:.3g}")


# ----------------------------------------------------------------------------- mean value classes of issue 42
def sweep_mean_value_precision(trials: int, seed: int = 0) -> dict[str, float]:
    """Worst errors of the mean value classes of issue 42 (items 3, 4, 10, 13) on random cages:
    ``needle_plane_grad``: native analytic gradients against the torch kernel's autograd (an
    independent derivation) at points on the support planes of needles' thin faces (aspect
    1e3..1e4), relative; ``moved_lp`` / ``moved_identity``: linear precision and the derivative
    identity on convex hulls moved by 1e6 sizes, in units of the results' own rounding
    (``eps sum |w| |V|``); ``mec_refused``: the fraction of points on a random triquad cage's bilinear
    sheets (float64 and float32) and 1e-10..1e-6 of the size inside them that maximum entropy
    coordinates refuse (before the fixes: 5.6e-5 seen, 42, 107 and a third of the points)."""
    from scipy.spatial import ConvexHull

    g = torch.Generator().manual_seed(seed)
    d64, eps = torch.float64, torch.finfo(torch.float64).eps
    out = {"needle_plane_grad": 0.0, "moved_lp": 0.0, "moved_identity": 0.0, "mec_refused": 0.0}

    def hull(v: torch.Tensor) -> torchcage.Cage:
        tri = torch.as_tensor(ConvexHull(v.numpy()).simplices, dtype=torch.long)
        p = v[tri]
        n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
        flip = (n * (p.mean(1) - v.mean(0))).sum(-1) < 0
        return torchcage.Cage(v, torch.where(flip[:, None], tri[:, [0, 2, 1]], tri))

    for _ in range(trials):
        # item 3: a needle, points on its thin faces' support planes 0.2..0.8 of the size away
        aspect = 10 ** (3 + float(torch.rand(1, generator=g)))
        ang = torch.rand(8, generator=g, dtype=d64) * 2 * math.pi
        ring = torch.stack(
            [1.6 * torch.rand(8, generator=g, dtype=d64) - 0.8, ang.cos() / aspect, ang.sin() / aspect], 1
        )
        needle = hull(torch.cat([ring, torch.tensor([[1.0, 0, 0], [-1.0, 0, 0]], dtype=d64)]) @ _turn(g).T)
        p = needle.vertices[needle.triangles]
        cr = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
        thin = torch.nonzero((p - p.roll(1, 1)).square().sum(-1).amax(-1) > 100 * cr.norm(dim=1)).flatten()
        f = thin[torch.randint(0, thin.numel(), (20,), generator=g)]
        n = cr[f] / cr[f].norm(dim=1, keepdim=True)
        t = torch.linalg.cross(n, torch.randn(20, 3, generator=g, dtype=d64), dim=-1)
        x = p[f].mean(1) + t / t.norm(dim=1, keepdim=True) * (0.2 + 0.6 * torch.rand(20, 1, generator=g, dtype=d64))
        _, ga, _ = F.mean_value_derivatives(x, needle, order=1)
        _, gt, _ = F.mean_value_derivatives(x, needle, order=1, backend="torch")
        out["needle_plane_grad"] = max(
            out["needle_plane_grad"], float(((ga - gt).flatten(1).norm(dim=1) / gt.flatten(1).norm(dim=1)).max())
        )
        # item 13: a convex hull moved by 1e6 sizes, points inside and 1e-3..1 of the size beside them
        v = torch.randn(14, 3, generator=g, dtype=d64)
        base = hull(v / v.norm(dim=1, keepdim=True))
        d = torch.randn(3, generator=g, dtype=d64)
        cage = base._like(base.vertices + d / d.norm() * 1e6 * base.scale)
        P = cage.vertices
        w = torch.rand(40, P.shape[0], generator=g, dtype=d64) ** 4
        xin = (w / w.sum(1, keepdim=True)) @ (P - P.mean(0)) + P.mean(0)
        u = torch.randn(40, 3, generator=g, dtype=d64)
        xm = torch.cat(
            [
                xin,
                xin
                + u
                / u.norm(dim=1, keepdim=True)
                * cage.scale
                * 10 ** (-3 + 3 * torch.rand(40, 1, generator=g, dtype=d64)),
            ]
        )
        W = F.mean_value_coordinates(xm, cage)
        lp = (W @ P - xm).abs().amax(1) / (eps * (W.abs() @ P.abs()).amax(1) + eps * xm.abs().amax(1))
        _, G, _ = F.mean_value_derivatives(xin, cage, order=1)
        J = torch.einsum("nvc,vd->ncd", G, P) - torch.eye(3, dtype=d64)
        unit = eps * torch.einsum("nvc,vd->ncd", G.abs(), P.abs()) + eps
        out["moved_lp"] = max(out["moved_lp"], float(lp.max()))
        out["moved_identity"] = max(out["moved_identity"], float((J.abs() / unit).max()))
        # items 4 and 10: the quad cube with its vertices moved by up to 0.1 (bilinear, non-planar quads)
        box = torchcage.load_cage(torchcage.data.path("cube.obj")).to(d64)
        noise = 0.1
        cq = box._like(box.vertices + noise * (2 * torch.rand(box.vertices.shape, generator=g, dtype=d64) - 1))
        if cq.invalid_quads().numel():
            continue
        q = cq.vertices[cq.quads]
        qi = torch.randint(0, q.shape[0], (30,), generator=g)
        uu, vv = torch.rand(2, 30, 1, generator=g, dtype=d64)
        Q = q[qi]
        xs = (1 - uu) * (1 - vv) * Q[:, 0] + uu * (1 - vv) * Q[:, 1] + uu * vv * Q[:, 2] + (1 - uu) * vv * Q[:, 3]
        xu = (1 - vv) * (Q[:, 1] - Q[:, 0]) + vv * (Q[:, 2] - Q[:, 3])
        xv = (1 - uu) * (Q[:, 3] - Q[:, 0]) + uu * (Q[:, 2] - Q[:, 1])
        nn_ = torch.linalg.cross(xu, xv, dim=-1)
        xi = xs - nn_ / nn_.norm(dim=1, keepdim=True) * cq.scale * 10 ** (
            -10 + 4 * torch.rand(30, 1, generator=g, dtype=d64)
        )
        refused = 0
        for pts in (xs, xs.float(), xi):
            for k in range(pts.shape[0]):
                try:
                    F.maximum_entropy_coordinates(pts[k : k + 1], cq)
                except torchcage.errors.PointsError:
                    refused += 1
        out["mec_refused"] = max(out["mec_refused"], refused / 90)
    return out


def print_mean_value_precision(result: dict[str, float]) -> None:
    print("\nMean value classes of issue 42 (items 3, 4, 10, 13): worst errors")
    for k, v in result.items():
        print(f"  {k:18s} {v:.3g}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--data", default=os.environ.get("TORCHCAGE_DATA", str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    )
    ap.add_argument("--per-category", type=int, default=2000)
    ap.add_argument("--grad-per-category", type=int, default=200)
    ap.add_argument("--dtype", choices=["float64", "float32"], default="float64")
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument(
        "--no-deformed",
        action="store_true",
        help="gradients with respect to the points and the rest cage only (no modules at deformed poses): "
        "the cheap way to 10^6 gradient queries",
    )
    ap.add_argument("--grad-only", action="store_true", help="skip the values pass (its columns stay empty)")
    ap.add_argument(
        "--seed", type=int, default=0, help="seed of the adversarial points (runs with different seeds add up)"
    )
    ap.add_argument(
        "--invalid-trials",
        type=int,
        default=20,
        help="damaged cages (coincident, pinched, flat, NaN/inf vertices) per kind and path, to every closed-form "
        "family: each must be refused with a CageError (0 skips the table)",
    )
    ap.add_argument(
        "--green-precision-trials",
        type=int,
        default=4,
        help="random polygons, needles and float32 quad cubes for the Green classes of issue 42 (0 skips the table)",
    )
    ap.add_argument(
        "--mean-value-precision-trials",
        type=int,
        default=3,
        help="random needles, moved hulls and triquad cages for the mean value classes of issue 42 (0 skips)",
    )
    args = ap.parse_args(argv)
    global DEFORMED_CATEGORIES, GRAD_ONLY, SEED
    GRAD_ONLY = args.grad_only
    SEED = args.seed
    if args.no_deformed:
        DEFORMED_CATEGORIES = ()
    data = Path(args.data) if Path(args.data).is_dir() else None
    dtype = None if args.dtype == "float64" else torch.float32
    results = run(args.families.split(","), data, args.per_category, args.grad_per_category, dtype, seed=args.seed)
    print_table(results)
    if args.invalid_trials > 0:
        print_invalid(sweep_invalid(args.invalid_trials, seed=args.seed))
    if args.green_precision_trials > 0:
        print_green_precision(sweep_green_precision(args.green_precision_trials, seed=args.seed))
    if args.mean_value_precision_trials > 0:
        print_mean_value_precision(sweep_mean_value_precision(args.mean_value_precision_trials, seed=args.seed))
    return 0


if __name__ == "__main__":
    sys.exit(main())
