"""The native QGC kernel's Riemann form takes eight points per quad side by side (qgc3d.c:
tc_quad_pair_lanes and riemann_lanes), leaving the lanes on corners, flat quads' planes and hull
faces' planes to the one-point code: a point's coordinates must not depend on the points that share
its block, must agree with the torch kernel whatever the number of points, and must keep linear
precision on a real cage."""

from __future__ import annotations

import pytest
import torch
from support import QMVC_MODELS, bent_box, box_points, data_path, model_points, quad_adversarial_points, sheet, triquad
from test_quad_green import assert_reproduces, inside_bilinear

import torchcage
from torchcage import functional as F


@pytest.fixture(autouse=True)
def _need_native():
    from torchcage.backends import native as _native

    if not _native.available():
        pytest.skip("no C compiler")


def _kinds(cage: torchcage.Cage) -> dict[str, torch.Tensor]:
    """Points of each kind a lane can be: on a quad, at a corner, inside a quad's tetrahedron (its
    corners' mean), near a quad, far away, and generic points."""
    v, q = cage.vertices.to(torch.float64), cage.quads
    c = v[q[: min(4, q.shape[0])]]  # (k, 4, 3)
    u0 = torch.tensor(0.3, dtype=torch.float64)
    w0 = torch.tensor(0.6, dtype=torch.float64)
    on = torch.stack([sheet(ci, u0, w0) for ci in c])
    mid = c.mean(1)
    normal = torch.nn.functional.normalize(torch.linalg.cross(c[:, 2] - c[:, 0], c[:, 3] - c[:, 1], dim=-1), dim=-1)
    near = on + 1e-3 * cage.scale * normal
    far = v.mean(0) + 3 * cage.scale * torch.nn.functional.normalize(
        torch.randn(3, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64), dim=-1
    )
    return {
        "on": on,
        "corner": v[q[:3, 0]],
        "tetrahedron": mid,
        "near": near,
        "far": far,
        "generic": box_points(cage, 7, spread=0.8, seed=2),
    }


def _mixed(cage: torchcage.Cage) -> torch.Tensor:
    """The kinds interleaved, so that each block of eight mixes them."""
    parts = list(_kinds(cage).values())
    rows = []
    for i in range(max(p.shape[0] for p in parts)):
        rows += [p[i] for p in parts if i < p.shape[0]]
    return torch.stack(rows)


def _close(a: torch.Tensor, b: torch.Tensor) -> None:
    torch.testing.assert_close(a, b, rtol=1e-13, atol=1e-13 * float(b.abs().max()))


@pytest.mark.filterwarnings("ignore::torchcage.OutsideCageWarning")  # (far points, on purpose)
@pytest.mark.parametrize("make", [bent_box, triquad])
def test_rows_do_not_depend_on_block_neighbours(make):
    cage = make()
    x = _mixed(cage)
    phi, psi = F.quad_green_coordinates(x, cage, backend="native")
    assert torch.isfinite(phi).all() and torch.isfinite(psi).all()
    for i in range(x.shape[0]):  # each point alone (a block of one, its lanes padded)
        a, b = F.quad_green_coordinates(x[i : i + 1], cage, backend="native")
        _close(a, phi[i : i + 1])
        _close(b, psi[i : i + 1])
    perm = torch.randperm(x.shape[0], generator=torch.Generator().manual_seed(0))
    a, b = F.quad_green_coordinates(x[perm], cage, backend="native")
    _close(a, phi[perm])
    _close(b, psi[perm])
    for size in (3, 5, 11):  # blocks cut at other places, partial blocks
        for s in range(0, x.shape[0], size):
            a, b = F.quad_green_coordinates(x[s : s + size], cage, backend="native")
            _close(a, phi[s : s + size])
            _close(b, psi[s : s + size])


@pytest.mark.filterwarnings("ignore::torchcage.OutsideCageWarning")
@pytest.mark.parametrize("n", [1, 2])
def test_partial_blocks_agree_with_torch(n):
    cage = triquad()
    x = torch.cat([_mixed(cage), quad_adversarial_points(cage, seed=4, distances=(0.0, 1e-6, 1e-3))[:-9]])
    for count in (1, 2, 3, 7, 8, 9, 17, x.shape[0]):
        a = F.quad_green_coordinates(x[:count], cage, n, backend="native")
        b = F.quad_green_coordinates(x[:count], cage, n, backend="torch")
        # (the tolerance of test_quad_green.py's test_backends_agree)
        for u, w in zip(a, b, strict=True):
            assert torch.isfinite(u).all()
            torch.testing.assert_close(u, w, atol=1e-10, rtol=0)


@pytest.mark.parametrize("model", [m for m in QMVC_MODELS if m in ("FireHydrant", "Beast")])
def test_data_cage_linear_precision(model):
    cage = torchcage.load_cage(data_path("qmvc", f"{model}_Cage.obj"))
    pts = model_points(model, cage, 400)
    g = torch.Generator().manual_seed(1)
    pts = pts[torch.randperm(pts.shape[0], generator=g)[:203]]  # (not a multiple of eight)
    x = pts[inside_bilinear(pts, cage, (6, 12))]
    phi, psi = F.quad_green_coordinates(x, cage, 2, backend="native")
    assert torch.isfinite(psi).all()
    assert_reproduces(phi, psi, cage, x)
