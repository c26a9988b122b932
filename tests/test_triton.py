"""The Triton kernels against the native ones, run by Triton's interpreter on CPU tensors
(``TRITON_INTERPRET=1``; CI's own step: ``pytest -m triton``) or on a GPU when there is one.

Targets: float64 within 1e-12 (relative to ``max(1, |lam|)``) of the native kernel
(2e-12 on Bench's support planes, where the native kernel itself is 1.7e-12 from the 40-digit
reference); float32 within 1e-5 of the native kernel on the same float32 inputs (1e-3 relative far
away, where the coordinates are ``distance / size`` sums that cancel to one).
"""

from __future__ import annotations

import os

import pytest
import torch
from support import TRITON_DEVICE, require_triton

import torchcage as tc
from torchcage import functional as F
from torchcage.testing import QMVC_MODELS, adversarial_points, hard_cages, sliver_cube

pytestmark = pytest.mark.triton

require_triton()

DEVICE = TRITON_DEVICE
D64 = torch.float64


def _rel(a: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Per-row error relative to ``max(1, |ref|)`` entrywise, ``(n,)``."""
    return ((a.double() - ref.double()).abs() / ref.double().abs().clamp_min(1.0)).amax(dim=1)


def _cages() -> dict[str, tc.Cage]:
    out = {"cube": tc.load_cage(tc.data.path("cube.obj")).to(D64).triangulated()}
    out.update({k: c.triangulated() for k, c in hard_cages().items() if k != "sliver_cube"})
    root = os.environ.get("TORCHCAGE_DATA")
    if root:
        for m in QMVC_MODELS:
            f = os.path.join(root, "qmvc", f"{m}_Cage.obj")
            if os.path.exists(f):
                out[m] = tc.load_cage(f).to(D64).triangulated()
    return out


CAGES = _cages()


def _points(cage: tc.Cage, per: int = 24, seed: int = 0) -> tuple[torch.Tensor, list[str]]:
    pts = adversarial_points(cage, per, seed=seed)
    cats = [c for c, x in pts.items() for _ in range(x.shape[0])]
    return torch.cat(list(pts.values())), cats


@pytest.mark.parametrize("name", sorted(CAGES))
def test_float64_matches_the_native_kernel(name: str) -> None:
    """Adversarial points (on and 1e-15..1e-3 of the size from vertices, edges and faces, support
    planes, edge lines) within 2e-12 of the native kernel (relative to ``max(1, |lam|)``: on Bench's
    support planes the two kernels are 1.0e-12 (Triton) and 1.7e-12 (native) from the 40-digit
    reference, so 1e-12 between them is below what either holds), with partition of unity and
    linear precision; far points (1e2..1e9 sizes) to the far field's target, linear precision 1e-8
    of the distance, and within 1e-9 of the native kernel."""
    cage = CAGES[name]
    x, cats = _points(cage)
    far = torch.tensor([c == "far" for c in cats])
    ref = F.mean_value_coordinates(x, cage, backend="native" if tc.backends.native.available() else "torch")
    got = F.mean_value_coordinates(x.to(DEVICE), cage.to(DEVICE), backend="triton").cpu()
    assert got.dtype == D64
    err = _rel(got, ref)
    assert float(err[~far].max()) < 2e-12, (name, float(err[~far].max()), x[~far][int(err[~far].argmax())].tolist())
    assert float(err[far].max()) < 1e-9, (name, float(err[far].max()))
    assert float((got[~far].sum(dim=1) - 1).abs().max()) < 1e-12
    assert float((got[~far] @ cage.vertices - x[~far]).norm(dim=1).max() / cage.scale) < 1e-9
    rel = (got[far] @ cage.vertices - x[far]).norm(dim=1) / (x[far] - cage.vertices.mean(dim=0)).norm(dim=1)
    assert float(rel.max()) < 1e-8


@pytest.mark.parametrize("name", ["cube", "twisted_bar", "FireHydrant", "Beast"])
def test_float32_matches_the_native_kernel_on_the_same_inputs(name: str) -> None:
    """Float32 compute (``backend="triton", dtype=torch.float32``) against float64 native on the
    float32-rounded cage and points: 1e-5 off the far field (the split forms near support planes
    are kept in float32) and linear precision 1e-4 of the size; far away (coordinates of size
    ``distance / size`` summing to one, which float32 keeps to about 1e-3 relative) linear precision
    1e-3 of the distance."""
    if name not in CAGES:
        pytest.skip("the QMVC data set is not available (TORCHCAGE_DATA)")
    cage = CAGES[name]
    x, cats = _points(cage, per=16, seed=1)
    c32 = cage.to(torch.float32)
    rounded = tc.Cage(c32.vertices.double(), cage.triangles)
    xr = x.float().double()
    ref = F.mean_value_coordinates(xr, rounded, backend="native" if tc.backends.native.available() else "torch")
    got = F.mean_value_coordinates(x.float().to(DEVICE), c32.to(DEVICE), backend="triton", dtype=torch.float32).cpu()
    assert got.dtype == torch.float32 and bool(torch.isfinite(got).all())
    err = _rel(got, ref)
    far = torch.tensor([c == "far" for c in cats])
    # (2e-5: compiled on an H200 without fused multiply-adds, twisted_bar's worst point is 1.07e-5 off;
    # the interpreter, which computes float literals in float64, stays below 1e-5)
    assert float(err[~far].max()) < 2e-5, (name, float(err[~far].max()))
    lp = (got[~far].double() @ rounded.vertices - xr[~far]).norm(dim=1).max() / cage.scale
    assert float(lp) < 1e-4
    y = xr[far] - rounded.vertices.mean(dim=0)
    rel = (got[far].double() @ rounded.vertices - xr[far]).norm(dim=1) / y.norm(dim=1)
    assert float(rel.max()) < 1e-3, (name, float(rel.max()))


def test_far_points_in_float32_do_not_overflow() -> None:
    """``1 / r^4`` of a cage of size 1e6 seen from 1e9 sizes overflows float32: the far pass scales
    each point's weights (the coordinates are a ratio)."""
    cage = hard_cages()["cube_1e6"].triangulated().to(torch.float32)
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=torch.Generator().manual_seed(0)), dim=1)
    x = d * torch.logspace(3, 15, 64)[:, None]
    got = F.mean_value_coordinates(x.to(DEVICE), cage.to(DEVICE), backend="triton", dtype=torch.float32).cpu()
    assert bool(torch.isfinite(got).all())
    rel = (got.double() @ cage.vertices.double() - x.double()).norm(dim=1) / x.double().norm(dim=1)
    assert float(rel.max()) < 1e-3


def test_thin_faces_are_redone_by_the_torch_kernel() -> None:
    """The sliver cube: points that see the sliver from a few widths are flagged by the Triton
    kernel and take the torch kernel's swept form, so the result matches the native kernel's."""
    cage = sliver_cube()
    x, _ = _points(cage, per=12)
    from torchcage.families.mean_value.kernel3d import triangle_cage_data
    from torchcage.families.mean_value.triton.mvc3d import mvc3d_triton, triton_tables

    _, flags = mvc3d_triton(x.to(DEVICE), triton_tables(triangle_cage_data(cage.to(DEVICE), D64)))
    assert int((flags.cpu() == 2).sum()) > 0
    ref = F.mean_value_coordinates(x, cage, backend="native" if tc.backends.native.available() else "torch")
    got = F.mean_value_coordinates(x.to(DEVICE), cage.to(DEVICE), backend="triton").cpu()
    assert float(_rel(got, ref).max()) < 1e-12


def test_on_the_cage_the_coordinates_interpolate() -> None:
    cage = CAGES["cube"]
    got = F.mean_value_coordinates(cage.vertices.to(DEVICE), cage.to(DEVICE), backend="triton").cpu()
    assert torch.equal(got, torch.eye(cage.num_vertices, dtype=D64))
    mid = 0.5 * (cage.vertices[0] + cage.vertices[1])
    got = F.mean_value_coordinates(mid[None].to(DEVICE), cage.to(DEVICE), backend="triton").cpu()
    assert torch.allclose(got @ cage.vertices, mid[None], atol=1e-15)


def test_with_a_graph_the_values_come_from_the_triton_kernel() -> None:
    """``backend="triton"`` when the points require grad: the autograd Function takes its values from
    the Triton kernel, its derivatives from the analytic (or autograd) path of the same coordinates:
    linear precision's derivative is the identity."""
    cage = CAGES["cube"].to(DEVICE)
    x0 = 0.4 * torch.randn(8, 3, dtype=D64, generator=torch.Generator().manual_seed(0)).to(DEVICE)
    x = x0.clone().requires_grad_()
    lam = F.mean_value_coordinates(x, cage, backend="triton")
    assert torch.equal(lam.detach(), F.mean_value_coordinates(x0, cage, backend="triton"))
    (g,) = torch.autograd.grad((lam @ cage.vertices)[:, 0].sum(), x)
    assert torch.allclose(g, torch.tensor([1.0, 0.0, 0.0], dtype=D64, device=DEVICE).expand_as(g), atol=1e-10)


def test_the_backend_says_what_it_cannot_do() -> None:
    poly = tc.load_cage(tc.data.path("blob2d.obj")).to(D64)
    with pytest.raises(ValueError, match="triton"):
        F.green_coordinates(torch.zeros(1, 2, dtype=D64), poly, backend="triton")
    from torchcage.families.green.dispatch import green_flat

    x = torch.zeros(1, 3, dtype=D64, device=DEVICE, requires_grad=True)
    with pytest.raises(RuntimeError, match="autograd"):
        green_flat(x, CAGES["cube"].to(DEVICE), backend="triton")


def _polygons() -> dict[str, tc.Cage]:
    out = {"blob": tc.load_cage(tc.data.path("blob2d.obj")).to(D64)}
    px = torch.tensor([[4.0, 4], [19, 4], [19, 19], [4, 19]], dtype=D64)
    out["square_px"] = tc.Cage(px)
    root = os.environ.get("TORCHCAGE_DATA")
    if root and os.path.isdir(os.path.join(root, "lbc2d")):
        import warnings

        for f in sorted(os.listdir(os.path.join(root, "lbc2d")))[:3]:
            if f.endswith(".obj"):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    out[f[:-4]] = tc.load_cage(os.path.join(root, "lbc2d", f)).to(D64)
    return out


POLYGONS = _polygons()


@pytest.mark.parametrize("name", sorted(POLYGONS))
@pytest.mark.parametrize("dtype", [D64, torch.float32], ids=["float64", "float32"])
def test_2d_matches_the_native_kernel(name: str, dtype: torch.dtype) -> None:
    """2D mean value coordinates (the image warps' path) on the polygons' adversarial points:
    float64 within 1e-12 of the native kernel off the far field (1e-9 far away, linear precision
    1e-8 of the distance), float32 within 1e-5 on the same float32 inputs."""
    cage = POLYGONS[name]
    x, cats = _points(cage, per=16)
    far = torch.tensor([c == "far" for c in cats])
    rounded = tc.Cage(cage.vertices.to(dtype).double()) if dtype != D64 else cage
    xr = x.to(dtype).double()
    ref = F.mean_value_coordinates(xr, rounded, backend="native" if tc.backends.native.available() else "torch")
    got = F.mean_value_coordinates(x.to(dtype).to(DEVICE), cage.to(DEVICE).to(dtype), backend="triton", dtype=dtype)
    got = got.cpu()
    assert got.dtype == dtype and bool(torch.isfinite(got).all())
    err = _rel(got, ref)
    tol = 1e-12 if dtype == D64 else 1e-5
    assert float(err[~far].max()) < tol, (name, float(err[~far].max()), xr[~far][int(err[~far].argmax())].tolist())
    y = xr[far] - rounded.vertices.mean(dim=0)
    rel = (got[far].double() @ rounded.vertices - xr[far]).norm(dim=1) / y.norm(dim=1)
    assert float(rel.max()) < (1e-8 if dtype == D64 else 1e-3)


def test_gradients_through_the_autograd_function() -> None:
    """With ``backend="auto"`` on a GPU the values come from the Triton kernel inside the autograd
    Function; the derivatives (autograd of the torch kernel) are those of the same coordinates."""
    if DEVICE != "cuda":
        pytest.skip("backend='auto' picks the Triton kernel for CUDA tensors only")
    cage = CAGES["cube"].to(DEVICE)
    x = (0.3 * torch.randn(16, 3, dtype=D64, device=DEVICE)).requires_grad_()
    lam = F.mean_value_coordinates(x, cage)
    (g,) = torch.autograd.grad((lam @ cage.vertices).sum(), x)
    assert torch.allclose(g, torch.ones_like(g), atol=1e-10)  # linear precision: d(lam V)/dx = I


# ---- 2D mean value derivatives --------------------------------------------------------------------


def _row_rel(a: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Per-row error relative to the row's largest reference entry, ``(n,)``."""
    a, ref = a.reshape(a.shape[0], -1).double(), ref.reshape(ref.shape[0], -1).double()
    return (a - ref).abs().amax(dim=1) / ref.abs().amax(dim=1).clamp_min(1e-300)


@pytest.mark.parametrize("name", sorted(POLYGONS))
def test_2d_derivatives_match_the_native_kernel(name: str) -> None:
    """The analytic gradients and Hessians of 2D mean value coordinates on the polygons' adversarial
    points, against the native kernel (float64):

    * coordinates within 1e-12 (relative to ``max(1, |lam|)``), the on-polygon flags identical;
    * gradients and Hessians within 1e-10 of the row's largest entry at the points that are not far
      and farther than 1e-4 of the size from every vertex (measured: 2e-13 and 1e-12);
    * at the far points (380 to 9e8 sizes) gradients within 1e-10 (measured 6e-13); the Hessians
      (down to 1e-21) cancel in every backend, more the farther: within ``3e-9 + 2e-14 r / size``
      (measured 1e-9 at 380 sizes, 4.5e-6 at 9e8, where the torch kernel is 9e-6 from the native);
    * closer than 1e-4 of the size to a vertex the weights' ``1 / distance`` cancels in the
      quotient and every backend's derivatives lose accuracy (the native kernel's Hessians break
      linear precision by 1e10 at 1e-13 distances, the Triton kernel's alike): finite only.
    """
    from torchcage.families.mean_value.derivatives import derivatives_flat

    cage = POLYGONS[name]
    x, cats = _points(cage, per=16)
    ref_backend = "native" if tc.backends.native.available() else "torch"
    L, G, H, on = derivatives_flat(x, cage, 2, backend=ref_backend)
    lam, g, h, on_t = derivatives_flat(x.to(DEVICE), cage.to(DEVICE), 2, backend="triton")
    lam, g, h, on_t = lam.cpu(), g.cpu(), h.cpu(), on_t.cpu()
    assert torch.equal(on_t, on) and bool(torch.isfinite(g).all() and torch.isfinite(h).all())
    assert float(_rel(lam, L).max()) < 1e-12
    size = float((cage.vertices.amax(0) - cage.vertices.amin(0)).norm())
    r = (x - cage.vertices.mean(dim=0)).norm(dim=1) / size
    dist = torch.cdist(x, cage.vertices).amin(dim=1) / size
    far = torch.tensor([c == "far" for c in cats])
    eg, eh = _row_rel(g, G), _row_rel(h, H)
    regular = ~on & ~far & (dist > 1e-4)
    assert float(eg[regular].max()) < 1e-10 and float(eh[regular].max()) < 1e-10, (name, float(eh[regular].max()))
    assert float(eg[far].max()) < 1e-10
    assert bool((eh[far] < 3e-9 + 2e-14 * r[far]).all()), (name, (eh[far] / (3e-9 + 2e-14 * r[far])).max())
    lam_on = L[on]
    assert torch.allclose(lam[on], lam_on, atol=1e-12) and torch.allclose(g[on], G[on], atol=1e-12)


def _route_derivatives_to_triton(monkeypatch) -> list[int]:
    """Send the mean value derivatives (public function and autograd Functions) to the Triton
    kernel, as they go for CUDA points (here on CPU tensors too); returns the list of orders the
    kernel was called with."""
    import importlib

    mvd = importlib.import_module("torchcage.families.mean_value.derivatives")  # (the module, not the function)
    calls: list[int] = []
    original = mvd._triton_derivatives

    def spy(*args, **kwargs):
        calls.append(args[2])
        return original(*args, **kwargs)

    from torchcage.backends import Choice

    monkeypatch.setattr(mvd, "select", lambda *args, **kwargs: Choice("triton"))
    monkeypatch.setattr(mvd, "_triton_derivatives", spy)
    if DEVICE == "cpu":  # (the autograd Functions take the analytic path for CPU points and the library)
        import torchcage.families.mean_value.ops as amv

        monkeypatch.setattr(amv, "_analytic", lambda points: True)
    return calls


def test_2d_derivatives_through_the_public_function_and_autograd(monkeypatch) -> None:
    """``backend="triton"`` in ``F.mean_value_derivatives`` (2D), and the autograd Functions'
    analytic gradients and Hessians taken from the Triton kernel (routed to it here on CPU tensors,
    as they are for CUDA points): backward and double backward against the native kernel's
    gradients and Hessians."""
    cage = POLYGONS["blob"].to(DEVICE)
    x = torch.tensor([[0.1, 0.2], [-0.3, 0.25], [0.4, -0.1]], dtype=D64, device=DEVICE)
    got = F.mean_value_derivatives(x, cage, backend="triton")
    backend = "native" if tc.backends.native.available() else "torch"
    ref = F.mean_value_derivatives(x.cpu(), POLYGONS["blob"], backend=backend)
    for a, b in zip(got, ref, strict=True):
        assert torch.allclose(a.cpu(), b, rtol=1e-10, atol=1e-12)
    calls = _route_derivatives_to_triton(monkeypatch)
    xg = x.clone().requires_grad_()
    lam = F.mean_value_coordinates(xg, cage)
    w = torch.linspace(-1.0, 1.0, lam.shape[1], dtype=D64, device=DEVICE)
    (g,) = torch.autograd.grad((lam * w).sum(), xg, create_graph=True)  # backward
    (h,) = torch.autograd.grad(g[:, 0].sum(), xg)  # double backward
    assert torch.allclose(g.cpu(), torch.einsum("nvc,v->nc", ref[1], w.cpu()), rtol=1e-10, atol=1e-12)
    assert torch.allclose(h.cpu(), torch.einsum("nvd,v->nd", ref[2][:, :, 0, :], w.cpu()), rtol=1e-10, atol=1e-12)
    assert 1 in calls and 2 in calls  # gradients and Hessians both came from the Triton kernel


# ---- 3D mean value derivatives --------------------------------------------------------------------


def _edge_distance(x: torch.Tensor, cage: tc.Cage) -> torch.Tensor:
    """Distance ``(n,)`` of points ``x`` to the cage's nearest edge (vertices included)."""
    e = cage.unique_edges()
    a, b = cage.vertices[e[:, 0]], cage.vertices[e[:, 1]]
    d = b - a
    t = (((x[:, None] - a[None]) * d[None]).sum(-1) / (d * d).sum(-1)).clamp(0.0, 1.0)
    return (x[:, None] - (a[None] + t[..., None] * d[None])).norm(dim=-1).amin(dim=1)


@pytest.mark.parametrize("name", sorted(CAGES))
def test_3d_derivatives_match_the_native_kernel(name: str) -> None:
    """The analytic gradients and Hessians of 3D mean value coordinates on the cages' adversarial
    points, against the native kernel (float64):

    * coordinates within 2e-11 (relative to ``max(1, |lam|)``; measured 8e-12 on Bench's support
      planes, where the native derivative kernel is 1.3e-11 from both coordinate kernels, 1e-13
      elsewhere), plus the points' own rounding ``4 eps max|p| / size`` (on the cube moved 1e6
      away, where next to an edge the native derivative kernel is 6e-11 from the coordinate
      kernels); the on-cage flags identical, and on
      the faces the interpolant's gradient (on edges and vertices it is one-sided: a face's, which
      may differ between backends);
    * gradients and Hessians within 1e-10 of the row's largest entry at the points that are not far
      and farther than 1e-4 of the size from every edge (measured on the eight QMVC cages: 3e-11
      and 8e-11), Hessians within twice the torch kernel's distance from the native one where that
      is larger (a point on Bench's coplanar faces' plane 1.5 sizes out: the Hessian cancels,
      Triton 2.1e-9 and torch 2.7e-9 from native);
    * at the far points (380 to 1e9 sizes) gradients within 1e-10 (measured 4e-12); the Hessians
      cancel in every backend, more the farther: within ``1.5e-8 + 1e-13 r / size`` (measured
      2.4 times ``3e-9 + 2e-14 r / size`` on Bench at 380 sizes, where the torch kernel is 6.7);
    * closer than 1e-4 of the size to an edge, the weights of the two faces there carry ``1 / h``
      parts that cancel in the quotient, and every backend's derivatives lose accuracy (Hessians
      off by up to 1e-1 relative at 1e-14 of the size, torch against native alike): finite only.
    """
    from torchcage.families.mean_value.derivatives import derivatives_flat

    cage = CAGES[name]
    x, cats = _points(cage, per=6)
    ref_backend = "native" if tc.backends.native.available() else "torch"
    L, G, H, on = derivatives_flat(x, cage, 2, backend=ref_backend)
    lam, g, h, on_t = derivatives_flat(x.to(DEVICE), cage.to(DEVICE), 2, backend="triton")
    lam, g, h, on_t = lam.cpu(), g.cpu(), h.cpu(), on_t.cpu()
    assert torch.equal(on_t, on) and bool(torch.isfinite(g).all() and torch.isfinite(h).all())
    size = float((cage.vertices.amax(0) - cage.vertices.amin(0)).norm())
    rounding = 4 * torch.finfo(D64).eps * float(cage.vertices.abs().max()) / size  # of the points themselves
    assert float(_rel(lam, L).max()) < 2e-11 + rounding
    r = (x - cage.vertices.mean(dim=0)).norm(dim=1) / size
    far = torch.tensor([c == "far" for c in cats])
    face = torch.tensor([c == "face" for c in cats]) & on
    eg, eh = _row_rel(g, G), _row_rel(h, H)
    regular = ~on & ~far & (_edge_distance(x, cage) / size > 1e-4)
    # where the Hessians cancel (outside, on coplanar faces' planes) the backends themselves differ:
    # there the bound is twice the torch kernel's distance from the native one
    _, Gt, Ht, _ = derivatives_flat(x[regular], cage, 2, backend="torch")
    spread = torch.maximum(_row_rel(Ht, H[regular]), _row_rel(Gt, G[regular]))
    assert float(eg[regular].max()) < 1e-10, (name, float(eg[regular].max()))
    assert bool((eh[regular] < torch.clamp(2 * spread, min=1e-10)).all()), (name, float(eh[regular].max()))
    assert float(eg[far].max()) < 1e-10
    assert bool((eh[far] < 1.5e-8 + 1e-13 * r[far]).all()), (name, (eh[far] / (1.5e-8 + 1e-13 * r[far])).max())
    assert torch.allclose(lam[on], L[on], atol=1e-12 + rounding) and torch.allclose(g[face], G[face], atol=1e-12)


def test_3d_derivatives_through_the_public_function_and_autograd(monkeypatch) -> None:
    """``backend="triton"`` in ``F.mean_value_derivatives`` for a 3D cage, batched points, and the
    autograd Functions' analytic gradients and Hessians taken from the Triton kernel (routed to it
    here on CPU tensors, as they are for CUDA points): backward and double backward against the
    native kernel's gradients and Hessians; a thin face's neighbours and a point on the cage are
    redone by the torch kernel's derivatives."""
    cage = CAGES["cube"].to(DEVICE)
    x = torch.tensor([[[0.1, 0.2, -0.3], [0.5, -0.45, 0.9]], [[-0.99, 0.0, 0.2], [2.0, 1.0, -3.0]]], dtype=D64)
    ref_backend = "native" if tc.backends.native.available() else "torch"
    got = F.mean_value_derivatives(x.to(DEVICE), cage, backend="triton")
    ref = F.mean_value_derivatives(x, CAGES["cube"], backend=ref_backend)
    for a, b in zip(got, ref, strict=True):
        assert a.shape == b.shape and torch.allclose(a.cpu(), b, rtol=1e-10, atol=1e-12)
    sliver = sliver_cube().triangulated()
    xs = torch.tensor([[0.0, 0.0, 0.0], [0.2, -0.1, 0.3]], dtype=D64)
    got = F.mean_value_derivatives(xs.to(DEVICE), sliver.to(DEVICE), backend="triton")
    ref = F.mean_value_derivatives(xs, sliver, backend=ref_backend)
    for a, b in zip(got, ref, strict=True):
        assert torch.allclose(a.cpu(), b, rtol=1e-9, atol=1e-11)
    pts = x.reshape(-1, 3)
    # (the reference before the routing: routed, a CPU call would reach the Triton kernel, which on a
    # GPU machine runs no CPU tensor)
    _, G, H = F.mean_value_derivatives(pts, CAGES["cube"], backend=ref_backend)
    calls = _route_derivatives_to_triton(monkeypatch)
    xg = pts.to(DEVICE).clone().requires_grad_()
    lam = F.mean_value_coordinates(xg, cage)
    w = torch.linspace(-1.0, 1.0, lam.shape[1], dtype=D64, device=DEVICE)
    (g,) = torch.autograd.grad((lam * w).sum(), xg, create_graph=True)  # backward
    (h,) = torch.autograd.grad(g[:, 2].sum(), xg)  # double backward
    assert torch.allclose(g.cpu(), torch.einsum("nvc,v->nc", G, w.cpu()), rtol=1e-10, atol=1e-12)
    assert torch.allclose(h.cpu(), torch.einsum("nvd,v->nd", H[:, :, 2, :], w.cpu()), rtol=1e-10, atol=1e-12)
    assert 1 in calls and 2 in calls  # gradients and Hessians both came from the Triton kernel


# ---- 3D Green coordinates -------------------------------------------------------------------------


def _green(x: torch.Tensor, cage: tc.Cage, backend: str, dtype: torch.dtype | None = None):
    """The bare Green integrals ``phi | psi`` ``(n, V + T)`` through the public function."""
    phi, psi = F.green_coordinates(x, cage, backend=backend, exterior="none", dtype=dtype)
    return torch.cat([phi, psi], dim=1)


@pytest.mark.parametrize("name", sorted(CAGES))
def test_green_float64_matches_the_native_kernel(name: str) -> None:
    """Adversarial points (on and 1e-15..1e-3 of the size from vertices, edges and faces, support
    planes, edge lines) within 1e-12 of the native kernel (relative to ``max(1, |ref|)``), the
    identity ``phi V + psi n = x`` inside; far points (1e2..1e9 sizes, where both kernels take the
    far-field Gauss rule of :mod:`torchcage.families.green.far_triangle`) within 1e-13 of the row's
    norm (measured: 1e-16 on the cube and FireHydrant)."""
    cage = CAGES[name]
    x, cats = _points(cage, per=16)
    far = torch.tensor([c == "far" for c in cats])
    ref = _green(x, cage, "native" if tc.backends.native.available() else "torch")
    got = _green(x.to(DEVICE), cage.to(DEVICE), "triton").cpu()
    assert got.dtype == D64 and bool(torch.isfinite(got).all())
    err = _rel(got, ref)
    assert float(err[~far].max()) < 1e-12, (name, float(err[~far].max()), x[~far][int(err[~far].argmax())].tolist())
    rel = (got[far] - ref[far]).norm(dim=1) / ref[far].norm(dim=1)
    assert float(rel.max()) < 1e-13, (name, float(rel.max()))
    inside = tc.geometry.inside_cage(x, cage) & ~far
    V = cage.num_vertices
    rec = got[inside, :V] @ cage.vertices + got[inside, V:] @ cage.triangle_normals()
    assert float((rec - x[inside]).norm(dim=1).max() / cage.scale) < 1e-9


@pytest.mark.parametrize("name", ["cube", "twisted_bar", "FireHydrant"])
def test_green_float32_matches_the_native_kernel_on_the_same_inputs(name: str) -> None:
    """Float32 compute against float64 native on the float32-rounded cage and points: 1e-5 off the
    far field (where float32 bare integrals are meaningless: the default extension replaces them)."""
    if name not in CAGES:
        pytest.skip("the QMVC data set is not available (TORCHCAGE_DATA)")
    cage = CAGES[name]
    x, cats = _points(cage, per=12, seed=1)
    far = torch.tensor([c == "far" for c in cats])
    c32 = cage.to(torch.float32)
    rounded = tc.Cage(c32.vertices.double(), cage.triangles)
    ref = _green(x.float().double(), rounded, "native" if tc.backends.native.available() else "torch")
    got = _green(x.float().to(DEVICE), c32.to(DEVICE), "triton", dtype=torch.float32).cpu()
    assert got.dtype == torch.float32 and bool(torch.isfinite(got[~far]).all())
    assert float(_rel(got[~far], ref[~far]).max()) < 1e-5, name


def test_green_thin_faces_are_redone_by_the_torch_kernel() -> None:
    """The sliver cube: points that see the sliver from a few widths are flagged and take the torch
    kernel's swept form, matching the native kernel."""
    from torchcage.families.green.kernel3d import triangle_green_data
    from torchcage.families.green.triton.gc3d import gc3d_triton, triton_tables

    cage = sliver_cube()
    x, cats = _points(cage, per=12)
    x = x[torch.tensor([c != "far" for c in cats])]
    tables = triton_tables(triangle_green_data(cage.to(DEVICE), D64), cage.vertices.to(DEVICE))
    _, _, flags = gc3d_triton(x.to(DEVICE), tables)
    assert int((flags.cpu() == 2).sum()) > 0 and int((flags.cpu() == 1).sum()) > 0
    ref = _green(x, cage, "native" if tc.backends.native.available() else "torch")
    assert float(_rel(_green(x.to(DEVICE), cage.to(DEVICE), "triton").cpu(), ref).max()) < 1e-12
