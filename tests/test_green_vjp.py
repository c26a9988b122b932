"""The native first-order backward pass of 3D Green coordinates (``gc3d_vjp.c``, glue in
``families/green/vjp3d_native.py``): for the points it takes (every face by the closed forms or the
far-field rule) its products with respect to the points and the rest cage agree with plain autograd
of the torch kernel, an independent computation; the points it leaves (on or near a face's plane or
a corner, beside a thin face) add nothing; and through ``green_coordinates`` the gradients equal
those of ``backend="torch"`` (autograd throughout) for every kind of point, and pass gradcheck."""

from __future__ import annotations

import pytest
import torch
from support import box_cage

import torchcage
from torchcage import functional as F
from torchcage.families.green.kernel3d import green3d_coordinates, triangle_green_data
from torchcage.families.green.vjp3d_native import native_vjp
from torchcage.testing import icosphere

D64 = torch.float64


def _jittered(cage: torchcage.Cage, seed: int) -> torchcage.Cage:
    g = torch.Generator().manual_seed(seed)
    P = cage.vertices.to(D64)
    return cage._like(P + 0.02 * P.abs().max() * torch.randn(P.shape, generator=g, dtype=D64))


def _points(cage: torchcage.Cage, seed: int) -> torch.Tensor:
    """Inside (most), outside, far away (faces by the far-field rule), on a face, near a face's
    plane, at and near a vertex."""
    g = torch.Generator().manual_seed(seed)
    P = cage.vertices
    c, s = P.mean(0), float((P - P.mean(0)).norm(dim=1).max())
    inside = c + 0.5 * s * (torch.rand(40, 3, generator=g, dtype=D64) - 0.5)
    outside = c + 1.6 * s * torch.nn.functional.normalize(torch.randn(6, 3, generator=g, dtype=D64), dim=1)
    far = c + 40 * s * torch.nn.functional.normalize(torch.randn(4, 3, generator=g, dtype=D64), dim=1)
    tri = P[cage.triangles[:3]]  # (3, 3, 3)
    n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
    n = n / n.norm(dim=1, keepdim=True)
    foot = tri.mean(1)
    on = foot
    near = foot - 1e-5 * s * n
    vertex = torch.stack([P[0], P[1] + 1e-6 * s])
    return torch.cat([inside, outside, far, on, near, vertex])


def _autograd_reference(x: torch.Tensor, cage: torchcage.Cage, gphi: torch.Tensor, gpsi: torch.Tensor):
    xr, Pr = x.clone().requires_grad_(), cage.vertices.clone().requires_grad_()
    phi, psi = green3d_coordinates(xr, triangle_green_data(cage._like(Pr), D64), cage.num_vertices)
    return torch.autograd.grad((phi, psi), (xr, Pr), (gphi, gpsi))


@pytest.mark.parametrize("name", ["icosphere", "box"])
def test_native_products_agree_with_autograd_of_the_torch_kernel(lib, name) -> None:
    cage = icosphere() if name == "icosphere" else box_cage(2, 1, 1).triangulated()
    cage = _jittered(cage.to(D64), 1)
    # the points left out (on a face, near its plane, at and near a vertex: rows 50-57, whose
    # closed forms are inf or NaN there) one per block of four, beside points the kernel takes
    order = list(range(50))
    for k, bad in enumerate(range(50, 58)):
        order.insert(4 * k + 1, bad)
    x = _points(cage, 2)[order]
    g = torch.Generator().manual_seed(3)
    gphi = torch.randn(x.shape[0], cage.num_vertices, generator=g, dtype=D64)
    gpsi = torch.randn(x.shape[0], cage.triangles.shape[0], generator=g, dtype=D64)
    gx, gP, reg = native_vjp(lib, x, cage.vertices, cage.triangles, gphi, gpsi, 1e-12 * cage.scale)
    # the inside and far points are taken (outside ones unless near a face's plane); on a face,
    # near its plane, at a vertex are not
    taken = torch.tensor([i < 40 or 46 <= i < 50 for i in order])
    left = torch.tensor([i >= 50 for i in order])
    assert bool(reg[taken].all()) and not bool(reg[left].any())
    assert float(gx[~reg].abs().max()) == 0.0 and bool(torch.isfinite(gx).all() and torch.isfinite(gP).all())
    rx, rP = _autograd_reference(x[reg], cage, gphi[reg], gpsi[reg])
    assert float((gx[reg] - rx).abs().max()) <= 1e-12 * float(rx.abs().max())
    # the points left out add nothing to the vertices' products
    assert float((gP - rP).abs().max()) <= 1e-12 * float(rP.abs().max())


def test_a_thin_face_leaves_the_points_beside_it(lib) -> None:
    cage = box_cage(1, 1, 1, size=(300.0, 1.0, 1.0)).triangulated().to(D64)  # faces 300 times longer than wide
    # beside the box, inside it near an end (neither near a face's plane nor far: the thin faces'
    # swept form, not the closed forms, gives their values), far away
    x = torch.tensor([[30.0, 5.0, -12.0], [145.0, 0.0, 0.0], [0.0, 0.0, 5000.0]], dtype=D64)
    gphi, gpsi = torch.ones(3, cage.num_vertices, dtype=D64), torch.ones(3, cage.triangles.shape[0], dtype=D64)
    gx, gP, reg = native_vjp(lib, x, cage.vertices, cage.triangles, gphi, gpsi, 1e-12 * cage.scale)
    assert reg.tolist() == [False, False, True]  # the far point sees every face by the far-field rule
    rx, rP = _autograd_reference(x[2:], cage, gphi[2:], gpsi[2:])
    assert float((gx[2:] - rx).abs().max()) <= 1e-12 * float(rx.abs().max())
    assert float((gP - rP).abs().max()) <= 1e-12 * float(rP.abs().max())


@pytest.mark.parametrize(
    ("dtype", "name"), [(torch.float64, "icosphere"), (torch.float32, "icosphere"), (torch.float64, "thin box")]
)
def test_gradients_through_green_coordinates_equal_the_torch_backend(lib, dtype, name) -> None:
    if name == "thin box":  # faces 300 times longer than wide
        cage = box_cage(1, 1, 1, size=(300.0, 1.0, 1.0)).triangulated().to(D64)
        extra = torch.tensor([[30.0, 5.0, -12.0], [145.0, 0.0, 0.0], [0.0, 3.0, 0.0], [-149.0, 0.1, 0.2]], dtype=D64)
    else:
        cage, extra = _jittered(icosphere().to(D64), 4), torch.zeros(0, 3, dtype=D64)
    x = torch.cat([_points(cage, 5), extra])
    g = torch.Generator().manual_seed(6)
    wphi = torch.randn(x.shape[0], cage.num_vertices, generator=g, dtype=D64)
    wpsi = torch.randn(x.shape[0], cage.triangles.shape[0], generator=g, dtype=D64)
    grads = {}
    for backend in ("auto", "torch"):
        xr = x.to(dtype).requires_grad_()
        P = cage.vertices.to(dtype).requires_grad_()
        phi, psi = F.green_coordinates(xr, cage._like(P), backend=backend)
        loss = (phi.to(D64) * wphi).sum() + (psi.to(D64) * wpsi).sum()
        grads[backend] = torch.autograd.grad(loss, (xr, P))
    for a, b in zip(grads["auto"], grads["torch"], strict=True):
        assert torch.isfinite(a).all()
        rtol = 1e-10 if dtype == torch.float64 else 1e-5
        assert float((a.to(D64) - b.to(D64)).abs().max()) <= rtol * float(b.abs().max())


def test_gradcheck_in_points_and_vertices(lib) -> None:
    cage = _jittered(box_cage(1, 1, 1).triangulated().to(D64), 7)
    pts = _points(cage, 8)
    x = torch.cat([pts[:3], pts[40:41], pts[46:47]]).requires_grad_()  # inside, outside, far
    P = cage.vertices.clone().requires_grad_()

    def f(y, Q):
        phi, psi = F.green_coordinates(y, cage._like(Q))
        return phi, psi

    assert torch.autograd.gradcheck(f, (x, P))


def test_a_batch_of_cages_with_a_graph(lib) -> None:
    base = icosphere().to(D64)
    P = torch.stack([_jittered(base, s).vertices for s in (10, 11)]).requires_grad_()
    x = torch.stack([_points(base, 12)[:50], _points(base, 13)[:50]])
    g = torch.Generator().manual_seed(14)
    w = torch.randn(2, 50, base.num_vertices, generator=g, dtype=D64)
    phi, _ = F.green_coordinates(x, torchcage.Cage(P, base.triangles, validate="topology"))
    (gP,) = torch.autograd.grad((phi * w).sum(), P)
    for b in range(2):
        Pb = P[b].detach().requires_grad_()
        phib, _ = F.green_coordinates(x[b], base._like(Pb), backend="torch")
        (ref,) = torch.autograd.grad((phib * w[b]).sum(), Pb)
        assert float((gP[b] - ref).abs().max()) <= 1e-10 * float(ref.abs().max())


@pytest.mark.parametrize("family", ["green", "mean value"])
def test_point_gradients_chunk_by_chunk(monkeypatch, family) -> None:
    """Gradients with respect to the points alone contract the closed-form gradient tables
    ``(n, V, 3)`` chunk by chunk of points (memory bounded whatever n): with chunks of 64 rows
    they equal the one-chunk result, and double backward still works."""
    import torchcage.families.green.ops as green_ops
    import torchcage.families.mean_value.ops as mvc_ops

    cage = _jittered(icosphere().to(D64), 20)
    x = _points(cage, 21)[:50]  # inside, outside, far
    x = torch.cat([x, x + 1e-3, x - 2e-3])  # 150 rows: three chunks of 64 rows
    w = torch.randn(x.shape[0], cage.num_vertices, generator=torch.Generator().manual_seed(22), dtype=D64)

    def grads(entries: int):
        monkeypatch.setattr(green_ops if family == "green" else mvc_ops, "GRADIENT_TABLE_ENTRIES", entries)
        xr = x.clone().requires_grad_()
        lam = F.green_coordinates(xr, cage)[0] if family == "green" else F.mean_value_coordinates(xr, cage)
        (gx,) = torch.autograd.grad((lam * w).sum(), xr, create_graph=True)
        (gxx,) = torch.autograd.grad(gx.square().sum(), xr)
        return gx.detach(), gxx

    one, chunked = grads(1 << 40), grads(1)
    for a, b in zip(one, chunked, strict=True):
        assert torch.isfinite(b).all() and float((a - b).abs().max()) <= 1e-12 * float(a.abs().max())
