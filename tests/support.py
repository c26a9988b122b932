"""Shared test builders: the shared data folder, hand-made cages and point sets. Tests import
them from here (``from support import ...``); ``conftest.py`` holds the fixtures only."""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest
import torch

import torchcage
from torchcage.testing import QMVC_MODELS

__all__ = [
    "DATA",
    "DISTANCES",
    "HANDMADE",
    "QMVC_MODELS",
    "REPO",
    "TRITON_DEVICE",
    "bent_box",
    "box_cage",
    "box_points",
    "centred_cube",
    "cube",
    "data_path",
    "extruded_polygon",
    "l_shape",
    "model_points",
    "notched",
    "quad_adversarial_points",
    "require_triton",
    "sheet",
    "sheet_normal",
    "triquad",
    "twisted_bar",
]  # fmt: skip

REPO = Path(__file__).resolve().parents[1]

#: Where the Triton tests run their kernels: the GPU, or CPU tensors under Triton's interpreter.
TRITON_DEVICE = "cuda" if torch.cuda.is_available() else "cpu"


def require_triton() -> None:
    """Skip the calling test module unless the Triton kernels can run: triton installed, and a GPU
    or Triton's interpreter (``TRITON_INTERPRET=1``, CI's own step: ``pytest -m triton``)."""
    pytest.importorskip("triton", reason="triton is not installed (pip install torchcage[triton])")
    if not torch.cuda.is_available() and os.environ.get("TRITON_INTERPRET", "0") in ("", "0"):
        pytest.skip("no GPU, and TRITON_INTERPRET=1 is not set: the Triton kernels cannot run", allow_module_level=True)


def _find_data() -> Path:
    """``$TORCHCAGE_DATA``, else the first ``shared/data`` folder beside the repository or one of
    its parents (the project's layout keeps it beside the checkout)."""
    if "TORCHCAGE_DATA" in os.environ:
        return Path(os.environ["TORCHCAGE_DATA"])
    for parent in REPO.parents:
        if (parent / "shared" / "data").is_dir():
            return parent / "shared" / "data"
    return REPO.parent / "shared" / "data"


DATA = _find_data()


def data_path(*parts: str) -> Path:
    """A file of the shared data set; skips the test cleanly when it is absent."""
    p = DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not found: {p} (set TORCHCAGE_DATA)")
    return p


def model_points(model: str, cage: torchcage.Cage, n: int, seed: int = 0) -> torch.Tensor:
    """Points of a data-set model: its mesh vertices (float64), or, for a model whose mesh the data
    set lacks (Cactus), ``n`` points sampled in the cage's bounding box and kept where the cage's
    winding number is one (inside)."""
    mesh = DATA / "qmvc" / f"{model}.obj"
    if mesh.exists():
        return torchcage.load_mesh(mesh)[0].to(torch.float64)
    from torchcage.geometry import inside_cage

    g = torch.Generator().manual_seed(seed)
    v = cage.vertices.to(torch.float64)
    lo, hi = v.min(0).values, v.max(0).values
    x = lo + (hi - lo) * torch.rand(8 * n, 3, generator=g, dtype=torch.float64)
    return x[inside_cage(x, cage)][:n]


def box_cage(nx: int = 1, ny: int = 1, nz: int = 1, size=(2.0, 2.0, 2.0)) -> torchcage.Cage:
    """A subdivided box of quads, centred at the origin, as a Cage (quads)."""
    import itertools

    verts, index = [], {}
    gx, gy, gz = (torch.linspace(-s / 2, s / 2, n + 1).tolist() for s, n in zip(size, (nx, ny, nz), strict=True))
    for i, j, k in itertools.product(range(nx + 1), range(ny + 1), range(nz + 1)):
        if i in (0, nx) or j in (0, ny) or k in (0, nz):
            index[(i, j, k)] = len(verts)
            verts.append([gx[i], gy[j], gz[k]])
    quads = []

    def add(a, b, c, d, flip):
        q = [index[a], index[b], index[c], index[d]]
        quads.append(q[::-1] if flip else q)

    for j in range(ny):
        for k in range(nz):
            add((0, j, k), (0, j + 1, k), (0, j + 1, k + 1), (0, j, k + 1), True)
            add((nx, j, k), (nx, j + 1, k), (nx, j + 1, k + 1), (nx, j, k + 1), False)
    for i in range(nx):
        for k in range(nz):
            add((i, 0, k), (i + 1, 0, k), (i + 1, 0, k + 1), (i, 0, k + 1), False)
            add((i, ny, k), (i + 1, ny, k), (i + 1, ny, k + 1), (i, ny, k + 1), True)
    for i in range(nx):
        for j in range(ny):
            add((i, j, 0), (i + 1, j, 0), (i + 1, j + 1, 0), (i, j + 1, 0), True)
            add((i, j, nz), (i + 1, j, nz), (i + 1, j + 1, nz), (i, j + 1, nz), False)
    return torchcage.Cage(torch.tensor(verts, dtype=torch.float64), quads)


def cube() -> torchcage.Cage:
    return box_cage().triangulated()


def l_shape() -> torchcage.Cage:
    """An L-shaped (non-convex) prism cage."""
    return extruded_polygon([[-1, -1], [1, -1], [1, 0], [0, 0], [0, 1], [-1, 1]], height=1.0)


def extruded_polygon(poly, height: float = 1.0, twist: float = 0.0, layers: int = 1) -> torchcage.Cage:
    """Extrude a counter-clockwise polygon along z into a closed triangle cage (caps fan-free:
    triangulated by ear clipping), optionally twisting the layers by ``twist`` radians in total."""
    n = len(poly)
    verts = []
    for layer in range(layers + 1):
        z = -height / 2 + height * layer / layers
        a = twist * layer / layers
        c, s = math.cos(a), math.sin(a)
        verts += [[c * x - s * y, s * x + c * y, z] for x, y in poly]
    tris = []
    for layer in range(layers):
        b0, b1 = layer * n, (layer + 1) * n
        for i in range(n):
            j = (i + 1) % n
            tris += [[b0 + i, b0 + j, b1 + j], [b0 + i, b1 + j, b1 + i]]
    cap = _ear_clip(poly)
    top = layers * n
    tris += [[c, b, a] for a, b, c in cap]  # bottom, facing -z
    tris += [[top + a, top + b, top + c] for a, b, c in cap]
    return torchcage.Cage(torch.tensor(verts, dtype=torch.float64), tris)


def _ear_clip(poly):
    idx = list(range(len(poly)))
    out = []

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    while len(idx) > 3:
        for k in range(len(idx)):
            i, j, l = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            if cross(poly[i], poly[j], poly[l]) <= 0:
                continue
            if any(
                cross(poly[i], poly[j], poly[m]) >= 0
                and cross(poly[j], poly[l], poly[m]) >= 0
                and cross(poly[l], poly[i], poly[m]) >= 0
                for m in idx
                if m not in (i, j, l)
            ):
                continue
            out.append([i, j, l])
            idx.pop(k)
            break
    out.append(idx)
    return out


def twisted_bar() -> torchcage.Cage:
    return extruded_polygon([[-0.3, -0.3], [0.3, -0.3], [0.3, 0.3], [-0.3, 0.3]], height=2.0, twist=1.2, layers=4)


def notched() -> torchcage.Cage:
    """A box with a thin concave notch cut into one side (width 0.02)."""
    poly = [[-1, -1], [1, -1], [1, 1], [0.01, 1], [0.01, -0.8], [-0.01, -0.8], [-0.01, 1], [-1, 1]]
    return extruded_polygon(poly, height=1.0)


HANDMADE = {"cube": cube, "l_shape": l_shape, "twisted_bar": twisted_bar, "notched": notched}


def centred_cube() -> torchcage.Cage:
    """The cube [-1, 1]^3 with a vertex at each face centre (14 vertices, 24 triangles): mirror
    symmetric in x, y and z, unlike a cube whose quads are split along one diagonal."""
    box = box_cage()
    v = box.vertices
    tris, verts = [], v.tolist()
    for q in box.quads.tolist():
        c = len(verts)
        verts.append(v[q].mean(0).tolist())
        tris += [[q[k], q[(k + 1) % 4], c] for k in range(4)]
    return torchcage.Cage(torch.tensor(verts, dtype=torch.float64), tris)


def bent_box() -> torchcage.Cage:
    """A 2x2x2-subdivided box bent symmetrically in x (z += 0.15 x^2 y): non-planar quads, mirror
    symmetric under x -> -x."""
    cage = box_cage(2, 2, 2)
    v = cage.vertices.clone()
    v[:, 2] += 0.15 * v[:, 0] ** 2 * v[:, 1] + 0.1 * v[:, 1] ** 2
    return torchcage.Cage(v, cage.quads)


def triquad() -> torchcage.Cage:
    """A bent box whose top quads are split into triangles: a triquad cage."""
    cage = bent_box()
    q = cage.quads
    top = cage.vertices[q].mean(1)[:, 2] > 0.9
    tris = torch.cat([q[top][:, [0, 1, 2]], q[top][:, [0, 2, 3]]])
    return torchcage.Cage(cage.vertices, tris.tolist() + q[~top].tolist())


def sheet(corners: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Points ``xi(u, v)`` of the bilinear sheet of ``corners`` ``(4, 3)``."""
    b = torch.stack([(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v], dim=-1)
    return b @ corners


def sheet_normal(corners: torch.Tensor, u: float, v: float) -> torch.Tensor:
    q0, q1, q2, q3 = corners
    du = (1 - v) * (q1 - q0) + v * (q2 - q3)
    dv = (1 - u) * (q3 - q0) + u * (q2 - q1)
    return torch.nn.functional.normalize(torch.linalg.cross(du, dv), dim=0)


DISTANCES = (0.0, 1e-15, 1e-12, 1e-9, 1e-6, 1e-3)


def quad_adversarial_points(cage: torchcage.Cage, seed: int = 0, distances=DISTANCES) -> torch.Tensor:
    """Points on quads, edges and corners, 1e-15..1e-3 of the cage size off them (both sides), in
    the tangent plane outside the quad, and two to five cage sizes away."""
    g = torch.Generator().manual_seed(seed)
    v, q = cage.vertices, cage.quads
    pts = []
    for f in torch.randperm(q.shape[0], generator=g)[:6].tolist():
        c = v[q[f]]
        u0, v0 = torch.rand(2, generator=g, dtype=torch.float64).tolist()
        n = sheet_normal(c, u0, v0)
        on_quad = sheet(c, torch.tensor(u0, dtype=torch.float64), torch.tensor(v0, dtype=torch.float64))
        on_edge = sheet(c, torch.tensor(u0, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64))
        centre = c.mean(0)
        beside = centre + 2.5 * (on_edge - centre)  # tangent direction, off the quad
        for d in distances:
            for sgn in (1.0, -1.0):
                off = sgn * d * cage.scale * n
                pts += [on_quad + off, on_edge + off, c[0] + off, beside + off]
    dirs = torch.nn.functional.normalize(torch.randn(8, 3, generator=g, dtype=torch.float64), dim=-1)
    for k, r in enumerate([2.0, 3.0, 5.0] * 3):
        pts.append(v.mean(0) + dirs[k % 8] * r * cage.scale)
    return torch.stack(pts)


def box_points(cage: torchcage.Cage, n: int, spread: float = 1.4, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    lo, hi = cage.vertices.min(0).values, cage.vertices.max(0).values
    c, h = (lo + hi) / 2, (hi - lo) / 2 * spread
    return c + (torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * h


def sample_inside(cage: torchcage.Cage, n: int, seed: int = 0) -> torch.Tensor:
    """Up to ``n`` float64 points drawn uniformly in the cage's bounding box and kept where they lie
    inside it (winding number)."""
    from torchcage.geometry import inside_cage

    g = torch.Generator().manual_seed(seed)
    v = cage.vertices.to(torch.float64)
    lo, hi = v.min(0).values, v.max(0).values
    x = lo + (hi - lo) * torch.rand(6 * n, cage.dim, generator=g, dtype=torch.float64)
    return x[inside_cage(x, cage)][:n]


def p1_stiffness(vertices, cells):
    """The P1 stiffness matrix ``(n, n)`` (scipy CSR), assembled cell by cell from the inverse of
    each cell's ``[1, x]`` matrix (the hat functions' coefficients): an assembly independent of
    the library's (which inverts edge matrices in torch). ``vertices (n, D)``, ``cells (C, D + 1)``
    numpy arrays."""
    import numpy as np
    from scipy.sparse import coo_matrix

    n, k = vertices.shape[0], cells.shape[1]
    D = k - 1
    M = np.concatenate([np.ones((cells.shape[0], k, 1)), vertices[cells]], axis=2)  # (C, k, k)
    grads = np.linalg.inv(M)[:, 1:, :]  # (C, D, k): rows 1..D of the coefficients are the gradients
    vol = np.abs(np.linalg.det(M)) / math.factorial(D)
    local = vol[:, None, None] * np.einsum("cda,cdb->cab", grads, grads)
    rows = np.repeat(cells, k, axis=1).ravel()
    cols = np.tile(cells, (1, k)).ravel()
    return coo_matrix((local.ravel(), (rows, cols)), shape=(n, n)).tocsr()


def cube_files(tmp_path, scale: float = 0.5):
    """A cube cage, a stretched pose and a small sphere mesh (``scale`` times the cube's half-size)."""
    from torchcage.testing import icosphere

    cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
    torchcage.save_cage(tmp_path / "cage.obj", cube)
    torchcage.save_cage(tmp_path / "pose.obj", cube, cube.vertices * torch.tensor([1.5, 1.0, 1.0], dtype=torch.float64))
    ball = icosphere(1)
    torchcage.save_mesh(tmp_path / "mesh.obj", scale * ball.vertices, ball.triangles)
    return ["deform", "--cage", str(tmp_path / "cage.obj"), "--deformed", str(tmp_path / "pose.obj"),
            "--mesh", str(tmp_path / "mesh.obj")]  # fmt: skip


# ------------------------------------------------------------------ the family contract (test_contract.py)
#: Mesh size of the solved families' cases: coarse, so that a solve takes well under a second.
CONTRACT_CELLS = 150


def contract_polygon() -> torchcage.Cage:
    """A small non-symmetric pentagon (counter-clockwise): the 2D cage of the contract tests."""
    return torchcage.Cage(torch.tensor([[0.0, 0], [2, 0], [2, 1], [1, 1.5], [0, 1]], dtype=torch.float64))


def contract_cage(faces: str, dim: int) -> torchcage.Cage:
    """The cage of a family's contract case: in 3D the packaged cube ``[-1, 1]^3`` (six quads),
    triangulated for a ``"triangles"`` family and kept with its quads for a ``"triquads"`` one; in
    2D :func:`contract_polygon`."""
    if dim == 2:
        return contract_polygon()
    cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
    return cube.triangulated() if faces == "triangles" else cube


def contract_points(dim: int) -> torch.Tensor:
    """A few fixed float64 points well inside :func:`contract_cage` (``(5, 3)`` or ``(4, 2)``): off
    the cage, off its symmetry planes, not all on one line."""
    if dim == 2:
        return torch.tensor([[0.5, 0.5], [1.5, 0.7], [1.0, 1.1], [0.3, 0.2]], dtype=torch.float64)
    return torch.tensor(
        [[0.1, 0.2, -0.3], [-0.5, 0.4, 0.2], [0.3, -0.6, 0.5], [0.05, -0.1, 0.15], [0.7, 0.6, -0.65]],
        dtype=torch.float64,
    )


def dense_outputs(out) -> tuple[torch.Tensor, ...]:
    """A functional entry's result as a tuple of dense tensors (one for weights, two for Green's
    ``(phi, psi)``; a sparse result, as local barycentric coordinates give, made dense)."""
    outs = out if isinstance(out, tuple) else (out,)
    return tuple(t.to_dense() if t.layout != torch.strided else t for t in outs)


def contract_solution(short: str, cage: torchcage.Cage):
    """One solve of a solved family on ``cage`` (``CONTRACT_CELLS`` cells), to pass as ``solution=``,
    or ``None`` for a family whose solver is not known here (its calls then solve each time)."""
    from torchcage import functional as F

    solvers = {
        "lbc": F.solve_local_barycentric,
        "hc": F.solve_harmonic_coordinates,
        "bbw": F.solve_bounded_biharmonic_weights,
    }
    if short not in solvers:
        return None
    # One thread: the ADMM loop of a small solve is thousands of tiny products, which torch's thread
    # pool slows 10-100x on a busy machine (measured on the 2-core box: 0.2 s alone, 2-20 s with 2 threads).
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return solvers[short](cage, target_cells=CONTRACT_CELLS)
    finally:
        torch.set_num_threads(threads)


def assert_same_to_rounding(out: torch.Tensor, ref: torch.Tensor) -> None:
    """Equal to rounding: the same tables and kernel give the same numbers (bitwise here; a few
    ulps are allowed for platforms whose batched tensor ops round differently)."""
    assert out.shape == ref.shape and out.dtype == ref.dtype
    eps = torch.finfo(out.dtype).eps
    err = (out - ref).abs() / ref.abs().clamp_min(1.0)
    assert torch.isfinite(out).all() and float(err.max()) <= 4 * eps, float(err.max())


class CountNativeCalls:
    """Counts ``tc_mvc3d`` calls (or those of ``entry``, with their batch size) through ``_native.call``."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, entry: str = "tc_mvc3d") -> None:
        from torchcage.backends import native as _native

        self.batches: list[int] = []
        real = _native.call

        def call(lib, name, **kw):
            if name == entry:
                self.batches.append(int(kw["B"]))
            return real(lib, name, **kw)

        monkeypatch.setattr(_native, "call", call)
