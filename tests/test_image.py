"""Image warping with 2D cages: reproduction at rest, exact translations and affine maps, the
forward mapping's inversion checked against the point deformation, gradients, outside modes."""

from __future__ import annotations

import math

import pytest
import torch

import torchcage
from torchcage._raster import _interpolate, _rasterize_one, rasterize_triangles
from torchcage.geometry import inside_polygon
from torchcage.image import CageWarp, pixel_centres, warp_image

pytest.importorskip("kornia")

H, W = 40, 48


def star_cage(cx: float = 24.0, cy: float = 20.0, n: int = 12, dtype=torch.float64) -> torch.Tensor:
    """A non-convex polygon in pixel coordinates, listed clockwise on screen (y down)."""
    k = torch.arange(n, dtype=dtype) * 2 * math.pi / n
    r = 14 + 3 * torch.cos(3 * k)
    return torch.stack([cx + 1.2 * r * torch.cos(k), cy + r * torch.sin(k)], dim=1)


def test_image(dtype=torch.float64) -> torch.Tensor:
    """A smooth image with structure (sharp edges would make the sampling tests about aliasing)."""
    y, x = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")
    chans = [torch.sin(x / 3) * torch.cos(y / 4), torch.cos((x + y) / 5), torch.sin(x * y / 90)]
    return torch.stack(chans)[None]


test_image.__test__ = False  # a helper, not a test


def psnr(a: torch.Tensor, b: torch.Tensor, peak: float = 2.0) -> float:
    mse = float((a - b).square().mean())
    return math.inf if mse == 0 else 10 * math.log10(peak**2 / mse)


CASES = [("mvc", "forward"), ("mvc", "backward"), ("gc", "forward"), ("gc", "backward"), ("lbc", "forward")]


@pytest.mark.parametrize(("method", "mapping"), CASES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["float32", "float64"])
def test_rest_cage_reproduces_the_image(method, mapping, dtype):
    cage = star_cage()
    img = test_image(dtype)
    out, mask = CageWarp(cage, H, W, method=method, mapping=mapping, outside="mask")(img, cage.to(dtype))
    m = mask.expand_as(img)
    assert int(mask.sum()) > 0.3 * H * W
    assert psnr(out[m], img[m]) >= 60.0
    # the mask is the polygon's interior
    ins = inside_polygon(pixel_centres(H, W), cage, torchcage.Cage(cage).edges).reshape(H, W)
    assert int((mask[0, 0] != ins).sum()) <= 4  # pixel centres exactly on an edge may go either way


# (LBC's translation: slow tier; its similarity motions, translations included, stay in the default one)
@pytest.mark.parametrize(("method", "mapping"), [*CASES[:4], pytest.param("lbc", "forward", marks=pytest.mark.slow)])
def test_translation_is_exact(method, mapping):
    cage = star_cage()
    t = torch.tensor([2.37, -1.61], dtype=torch.float64)
    grid, inside = CageWarp(cage, H, W, method=method, mapping=mapping).sampling_grid(cage + t)
    y = pixel_centres(H, W).reshape(H, W, 2)
    assert int(inside.sum()) > 0.3 * H * W
    assert float((grid - (y - t))[inside].abs().max()) <= 1e-9
    # an integer shift moves the pixels themselves
    img = test_image()
    warp = CageWarp(cage, H, W, method=method, mapping=mapping, outside="mask")
    out, mask = warp(img, cage + torch.tensor([3.0, 2.0], dtype=torch.float64))
    src = torch.roll(img, shifts=(2, 3), dims=(2, 3))
    m = mask.expand_as(img).clone()
    m[..., :3, :] = False
    m[..., :, :4] = False
    assert float((out - src)[m].abs().max()) <= 1e-9


def affine_pose(cage: torch.Tensor, similarity: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    a = 0.3
    A = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=torch.float64) * 1.1
    if not similarity:
        A = A @ torch.tensor([[1.2, 0.25], [0.0, 0.85]], dtype=torch.float64)
    c = cage.mean(dim=0)
    t = c - c @ A.T + torch.tensor([1.3, -0.7], dtype=torch.float64)
    return cage @ A.T + t, A, t


@pytest.mark.parametrize(("method", "mapping"), CASES)
def test_affine_and_similarity_motions(method, mapping):
    """MVC has linear precision: any affine cage motion gives the affine warp; Green coordinates
    reproduce similarities."""
    cage = star_cage()
    moved, A, t = affine_pose(cage, similarity=method == "gc")  # MVC and LBC: any affine map
    grid, inside = CageWarp(cage, H, W, method=method, mapping=mapping).sampling_grid(moved)
    y = pixel_centres(H, W).reshape(H, W, 2)
    expected = (y - t) @ torch.linalg.inv(A).T
    assert int(inside.sum()) > 0.3 * H * W
    assert float((grid - expected)[inside].abs().max()) <= 1e-4
    # the inside mask is the interior of the moved polygon, up to pixels at the boundary
    ins = inside_polygon(y.reshape(-1, 2), moved, torchcage.Cage(cage).edges).reshape(H, W)
    assert int((inside[0] != ins).sum()) <= 6


def bent_pose(cage: torch.Tensor) -> torch.Tensor:
    c = cage.mean(dim=0)
    d = cage - c
    ang = 0.25 * d[:, 0] / 20  # bend: rotation growing along x
    rot = torch.stack([d[:, 0] * torch.cos(ang) - d[:, 1] * torch.sin(ang),
                       d[:, 0] * torch.sin(ang) + d[:, 1] * torch.cos(ang)], dim=1)  # fmt: skip
    return c + rot * torch.tensor([1.1, 0.9], dtype=cage.dtype)


@pytest.mark.parametrize("method", ["mvc", "gc"])
def test_forward_mapping_inverts_the_point_deformation(method):
    """For a non-affine pose, the source point x of each output pixel y satisfies f(x) = y with f
    the deformation the coordinate modules apply to points, up to the pixel mesh's linear
    interpolation error."""
    cage = torchcage.Cage(star_cage())
    moved = bent_pose(cage.vertices)
    grid, inside = CageWarp(cage, H, W, method=method).sampling_grid(moved)
    x = grid[0][inside[0]]
    y = pixel_centres(H, W).reshape(H, W, 2)[inside[0]]
    interior = inside_polygon(x, cage.vertices, cage.edges)  # f is defined inside the rest cage
    module = torchcage.MeanValueCoordinates if method == "mvc" else torchcage.GreenCoordinates
    fx = module(cage, x[interior])(moved)
    assert float((fx - y[interior]).norm(dim=1).max()) <= 0.05
    if method == "mvc":  # MVC interpolate on the cage: the output mask is the moved cage's interior
        ins = inside_polygon(pixel_centres(H, W), moved, cage.edges).reshape(H, W)
        wrong = pixel_centres(H, W)[(inside[0] != ins).reshape(-1)]
        assert wrong.numel() == 0 or float(distance_to_polygon(wrong, moved, cage.edges).max()) <= 0.05


def distance_to_polygon(p: torch.Tensor, verts: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    a, b = verts[edges[:, 0]][None], verts[edges[:, 1]][None]
    d = b - a
    t = (((p[:, None] - a) * d).sum(-1) / (d * d).sum(-1)).clamp(0, 1)
    return (p[:, None] - a - t[..., None] * d).norm(dim=-1).amin(dim=1)


def test_backward_mapping_inverts_approximately():
    """The backward map (coordinates with respect to the deformed cage) and the forward map agree
    to second order for a small non-affine pose."""
    cage = torchcage.Cage(star_cage())
    rest = cage.vertices
    moved = rest + 0.05 * (bent_pose(rest) - rest)
    gf, inf = CageWarp(cage, H, W).sampling_grid(moved)
    gb, inb = CageWarp(cage, H, W, mapping="backward").sampling_grid(moved)
    both = inf & inb
    assert float((gf - gb)[both].abs().max()) <= 0.05


def test_outside_modes_and_shapes():
    cage = star_cage()
    img = test_image().expand(2, -1, -1, -1)
    moved = torch.stack([cage * 0.8 + 4, cage + 1])
    keep = CageWarp(cage, H, W, outside="keep")(img, moved)
    zero = CageWarp(cage, H, W, outside="zero")(img, moved)
    masked, mask = CageWarp(cage, H, W, outside="mask")(img, moved)
    assert keep.shape == img.shape and mask.shape == (2, 1, H, W) and mask.dtype == torch.bool
    m = mask.expand_as(img)
    assert torch.equal(keep[~m], img[~m]) and bool((zero[~m] == 0).all())
    assert torch.equal(zero, masked) and torch.equal(keep[m], zero[m])
    # unbatched in, unbatched out; one image broadcast over poses
    assert CageWarp(cage, H, W)(img[0], cage).shape == img.shape[1:]
    assert CageWarp(cage, H, W)(img[:1], moved).shape == (2, 3, H, W)
    nearest = CageWarp(cage, H, W, mode="nearest")(img, cage.expand(2, -1, -1))
    assert torch.equal(nearest, img)


def test_one_shot_function_matches_the_module():
    cage = star_cage()
    img = test_image()
    moved = bent_pose(cage)
    for mapping in ("forward", "backward"):
        a = warp_image(img, cage, moved, mapping=mapping)
        b = CageWarp(cage, H, W, mapping=mapping)(img, moved)
        assert torch.equal(a, b)


@pytest.mark.parametrize(("method", "mapping"), CASES)
def test_gradcheck_vertices_and_image(method, mapping):
    h, w = 9, 10
    k = torch.arange(5, dtype=torch.float64) * 2 * math.pi / 5
    cage = torch.stack([4.5 + 4.6 * torch.cos(k), 4.0 + 4.1 * torch.sin(k)], dim=1)
    warp = CageWarp(cage, h, w, method=method, mapping=mapping)
    gen = torch.Generator().manual_seed(3)
    img = torch.rand(1, 2, h, w, dtype=torch.float64, generator=gen, requires_grad=True)
    verts = (cage + 0.3 * torch.rand(cage.shape, dtype=torch.float64, generator=gen)).requires_grad_()
    assert torch.autograd.gradcheck(lambda i, v: warp(i, v), (img, verts), eps=1e-6, atol=1e-6)


def test_gradients_flow_and_fit_a_pose():
    """A few Adam steps on the vertices reduce the distance to a target warp."""
    cage = star_cage()
    img = test_image()
    warp = CageWarp(cage, H, W, outside="zero")
    target = warp(img, bent_pose(cage)).detach()
    verts = cage.clone().requires_grad_()
    opt = torch.optim.Adam([verts], lr=0.3)
    losses = []
    for _ in range(30):
        opt.zero_grad()
        loss = (warp(img, verts) - target).square().mean()
        loss.backward()
        assert torch.isfinite(verts.grad).all()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]


def test_state_dict_round_trip():
    cage = star_cage()
    a = CageWarp(cage, H, W, method="gc")
    b = CageWarp(cage + 0.0, H, W, method="gc")
    b.load_state_dict(a.state_dict())
    moved = bent_pose(cage)
    assert torch.equal(a(test_image(), moved), b(test_image(), moved))
    assert {"weights", "mesh_pixels", "mesh_triangles", "interior", "rest_vertices", "edges"} <= set(a.state_dict())


def test_native_and_torch_rasterisers_agree():
    gen = torch.Generator().manual_seed(0)
    cage = torchcage.Cage(star_cage())
    warp = CageWarp(cage, H, W)
    moved = torch.matmul(warp.weights, bent_pose(cage.vertices))[None]
    moved = moved + 0.2 * torch.rand(moved.shape, dtype=torch.float64, generator=gen)
    src = pixel_centres(H, W)[warp.mesh_pixels]
    which, val = rasterize_triangles(moved, warp.mesh_triangles, H, W, src)
    ref = _rasterize_one(moved[0], warp.mesh_triangles, H, W)
    covered = which[0] >= 0
    assert torch.equal(covered, ref >= 0)
    # shared edges may go to either triangle; the interpolated values agree regardless
    ref_val = _interpolate(moved, warp.mesh_triangles, ref[None], src)
    assert float((val - ref_val)[0][covered].abs().max()) <= 1e-9


def test_inside_polygon_matches_winding_number():
    gen = torch.Generator().manual_seed(1)
    cage = torchcage.Cage(star_cage())
    pts = torch.rand(2000, 2, dtype=torch.float64, generator=gen) * torch.tensor([W, H]) - 0.5
    a = cage.vertices[cage.edges[:, 0]][None] - pts[:, None]
    b = cage.vertices[cage.edges[:, 1]][None] - pts[:, None]
    ang = torch.atan2(a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0], (a * b).sum(-1)).sum(1)
    assert torch.equal(inside_polygon(pts, cage.vertices, cage.edges), ang.abs() > math.pi)


def test_errors():
    cage = star_cage()
    img = test_image()
    with pytest.raises(ValueError, match="method must be one of"):
        CageWarp(cage, H, W, method="bogus")
    with pytest.raises(ValueError, match="only mapping='forward'"):
        CageWarp(cage, H, W, method="lbc", mapping="backward")
    with pytest.raises(ValueError, match="outside must be one of"):
        CageWarp(cage, H, W, outside="crop")
    warp = CageWarp(cage, H, W)
    with pytest.raises(ValueError, match=r"image must have shape \(B, C, 40, 48\)"):
        warp(img[..., :-1], cage)
    with pytest.raises(ValueError, match=r"vertices must have shape \(B, 12, 2\)"):
        warp(img, cage[:-1])
    with pytest.raises(ValueError, match="NaN or inf"):
        warp(img, torch.full_like(cage, math.nan))
    with pytest.raises(TypeError, match="floating-point"):
        warp(img, cage.long())
    with pytest.raises(ValueError, match="do not broadcast"):
        warp(img.expand(3, -1, -1, -1), torch.stack([cage, cage]))
    with pytest.raises(torchcage.CageError, match="no pixel centre"):
        CageWarp(cage + 1000, H, W)
    with pytest.raises(torchcage.CageError, match="2D cage"):
        CageWarp(torchcage.load_cage(torchcage.data.path("cube.obj")), H, W)
