"""Green coordinates outside the cage: Lipman et al.'s exterior extension.

Properties: outside points are reproduced at rest (partition of unity and linear precision); under
a deformation the extended map continues the interior one across a face (continuous, and as smooth
as inside: its second differences across the face match those inside); it is continuous around
convex edges, where the continuations of two faces are blended; gradients agree with finite
differences; the data set's mesh vertices that poke out of their cage are reproduced.
"""

from __future__ import annotations

import warnings

import pytest
import torch
from support import data_path, l_shape, notched

import torchcage as tc
from torchcage import functional as F
from torchcage.testing import sliver_cube

D64 = torch.float64


def _cube() -> tc.Cage:
    return tc.load_cage(tc.data.path("cube.obj")).triangulated().to(D64)


def _reproduction(x: torch.Tensor, cage: tc.Cage) -> tuple[float, float]:
    phi, psi = F.green_coordinates(x, cage)
    n = cage.triangle_normals() if cage.dim == 3 else cage.edge_normals()
    rec = phi @ cage.vertices + psi @ n
    return float((phi.sum(-1) - 1).abs().max()), float((rec - x).norm(dim=-1).max()) / cage.scale


@pytest.mark.parametrize("name", ["cube", "sliver", "l_shape", "notched"])
def test_outside_points_are_reproduced_at_rest(name: str, backend: str) -> None:
    cage = {"cube": _cube, "sliver": sliver_cube, "l_shape": l_shape, "notched": notched}[name]()
    g = torch.Generator().manual_seed(0)
    lo, hi = cage.vertices.min(0).values, cage.vertices.max(0).values
    x = lo - 0.5 + (hi - lo + 1.0) * torch.rand(3000, 3, generator=g, dtype=D64)
    phi, psi = F.green_coordinates(x, cage, backend=backend)
    n = cage.triangle_normals()
    assert torch.isfinite(phi).all() and torch.isfinite(psi).all()
    assert float((phi.sum(-1) - 1).abs().max()) < 1e-12
    assert float((phi @ cage.vertices + psi @ n - x).norm(dim=-1).max()) < 1e-9 * cage.scale
    # the bare integrals: 0 outside (what the extension adds to)
    phi0, psi0 = F.green_coordinates(x, cage, backend=backend, exterior="none")
    out = phi0.sum(-1) < 0.5
    assert bool(out.any()) and float((phi0[out] @ cage.vertices + psi0[out] @ n).norm(dim=-1).max()) < 1e-9


def test_polygon_outside_points_are_reproduced() -> None:
    P = torch.tensor([[0, 0], [2, 0], [2, 1], [1, 0.4], [0, 1]], dtype=D64)  # concave
    cage = tc.Cage(P, None)
    x = torch.rand(2000, 2, generator=torch.Generator().manual_seed(1), dtype=D64) * 4 - 1
    pu, lp = _reproduction(x, cage)
    assert pu < 1e-12 and lp < 1e-12


def _pose(cage: tc.Cage, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return cage.vertices + 0.15 * torch.randn(cage.vertices.shape, generator=g, dtype=D64)


def _deform(cage: tc.Cage, x: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tc.OutsideCageWarning)
        return tc.GreenCoordinates(cage, x)(pose)


def test_deformed_map_continues_across_a_face() -> None:
    """The extended map is the analytic continuation: across the face z = 1 its second differences
    are those of the smooth interior map (a jump or a kink would dominate them)."""
    cage = _cube()
    pose = _pose(cage)
    h = 1e-3
    t = torch.arange(-6, 7, dtype=D64) * h
    x = torch.stack([torch.full_like(t, 0.3), torch.full_like(t, -0.2), 1 + t], dim=1)
    y = _deform(cage, x, pose)
    d1 = (y[1:] - y[:-1]).norm(dim=1)
    d2 = (y[2:] - 2 * y[1:-1] + y[:-2]).norm(dim=1)
    inside = d2[:4].max()
    assert float(d1.max()) < 2 * float(d1.min())  # no jump
    assert float(d2.max()) < 1.5 * float(inside) + 1e-12  # no kink at the face (index 5)
    # and the values on both sides converge to the value on the face
    for eps in (1e-6, 1e-9):
        z = torch.tensor([[0.3, -0.2, 1 - eps], [0.3, -0.2, 1 + eps]], dtype=D64)
        yz = _deform(cage, z, pose)
        assert float((yz[1] - yz[0]).norm()) < 10 * eps


@pytest.mark.parametrize("radius", [0.3, 1e-3])
def test_deformed_map_is_continuous_around_a_convex_edge(radius: float) -> None:
    """Around the edge x = z = 1 the continuations of its two faces are blended: refining the path
    halves the largest step (a discontinuity would keep it)."""
    cage = _cube()
    pose = _pose(cage, 1)

    def largest_step(n: int) -> float:
        th = torch.linspace(-0.3, torch.pi / 2 + 0.3, n, dtype=D64)
        x = torch.stack([1 + radius * torch.cos(th), torch.full_like(th, 0.1), 1 + radius * torch.sin(th)], dim=1)
        return float((_deform(cage, x, pose).diff(dim=0)).norm(dim=1).max())

    a, b = largest_step(200), largest_step(400)
    assert b < 0.6 * a, (a, b)


def test_gradients_outside_agree_with_finite_differences() -> None:
    from torch.autograd import gradcheck

    cage = _cube()
    # in a face's prism, in a convex edge's wedge (two faces blended), beyond a corner, far out
    x = torch.tensor([[0.2, 0.1, 1.3], [1.2, 0.3, 1.25], [1.3, 1.2, 1.1], [0.1, -4.0, 0.5]], dtype=D64)
    assert gradcheck(lambda p: F.green_coordinates(p, cage), (x.clone().requires_grad_(),))
    V = cage.vertices.clone().requires_grad_()
    assert gradcheck(lambda P: F.green_coordinates(x, tc.Cage(P, cage.faces, validate=False)), (V,))


def test_band_and_none() -> None:
    cage = _cube()
    x = torch.tensor([[0.0, 0.0, 1.5], [0.0, 0.0, 3.0]], dtype=D64)  # 0.5 and 2.0 outside (size 3.46)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tc.OutsideCageWarning)
        tc.GreenCoordinates(cage, x[:1])  # within the default band (0.25 of the size): no warning
        tc.GreenCoordinates(cage, x, exterior_band=1.0)
    with pytest.warns(tc.OutsideCageWarning, match="1 of 2 points lie farther"):
        tc.GreenCoordinates(cage, x)
    with pytest.raises(ValueError, match="exterior"):
        F.green_coordinates(x, cage, exterior="mirror")


def test_batched_cages_extend_each_element() -> None:
    cage = _cube()
    batch = tc.Cage(torch.stack([cage.vertices, 2 * cage.vertices]), cage.faces)
    x = torch.tensor([[0.0, 0.0, 1.5], [1.2, 1.1, 0.0]], dtype=D64)
    phi, psi = F.green_coordinates(x, batch)
    for b in range(2):
        p1, s1 = F.green_coordinates(x, batch[b])
        assert torch.equal(phi[b], p1) and torch.equal(psi[b], s1)
    m = tc.GreenCoordinates(batch, x)
    assert torch.allclose(m(batch.vertices), x.expand(2, -1, -1), atol=1e-12)


def test_ogre_mesh_vertices_outside_their_cage_are_reproduced() -> None:
    """Reproducer 14: 90 of the Ogre's 26,155 mesh vertices lie outside its cage."""
    cage = tc.load_cage(data_path("qmvc", "Ogre_Cage.obj")).triangulated()
    v = tc.load_mesh(data_path("qmvc", "Ogre.obj"))[0].to(D64)
    m = tc.GreenCoordinates(cage, v)
    assert float((m(cage.vertices) - v).norm(dim=1).max()) < 1e-9 * cage.scale


def test_in_place_continuation_equals_the_copy_and_leaves_the_inputs_alone() -> None:
    """``extend_outside(inplace=True)`` (the plain path: the kernel's fresh tables) gives the same
    tables as the copying form, bit for bit; the copying form leaves the caller's tensors as they
    were. The continuation terms (dot products component by component, the vertices' sums by rows of
    the transpose) agree with a direct computation of the blend: the continued coordinates of an
    outside point reproduce it at rest."""
    from torchcage.families.green.exterior import extend_outside

    cage = _cube()
    g = torch.Generator().manual_seed(3)
    x = torch.cat([0.3 * torch.randn(20, 3, generator=g, dtype=D64), 1.5 + torch.rand(20, 3, generator=g, dtype=D64)])
    phi, psi = F.green_coordinates(x, cage, exterior="none")
    before = phi.clone(), psi.clone()
    a_phi, a_psi, a_d = extend_outside(x, cage, phi, psi)
    assert torch.equal(phi, before[0]) and torch.equal(psi, before[1])
    b_phi, b_psi, b_d = extend_outside(x, cage, phi, psi, inplace=True)
    assert b_phi is phi and b_psi is psi
    assert torch.equal(a_phi, b_phi) and torch.equal(a_psi, b_psi) and torch.equal(a_d, b_d)
    assert bool((a_d[20:] > 0).all()) and bool((a_d[:20] == 0).all())
    rec = a_phi @ cage.vertices + a_psi @ cage.triangle_normals()
    assert float((rec - x).norm(dim=-1).max()) <= 1e-12 * cage.scale
    assert float((a_phi.sum(-1) - 1).abs().max()) <= 1e-12
