"""The native vector-Jacobian product of 3D mean value coordinates (``mvc3d_vjp.c``) takes four
points side by side: a point's product must not depend on the points that share its block (regular
or not: on a vertex, near a face's plane, beside a thin face, far away), points that are not regular
must add nothing to the vertex gradients, and the products must agree with the torch form of the
same derivation (``vjp3d.direct_vjp``) and with plain autograd of the coordinates."""

from __future__ import annotations

import pytest
import torch

import torchcage
from torchcage.families.mean_value.ops import _torch_coordinates
from torchcage.families.mean_value.vjp3d import direct_vjp
from torchcage.families.mean_value.vjp3d_native import native_vjp, native_vjp_batch
from torchcage.testing import icosphere, twisted_bar

D64 = torch.float64


def _mixed_points(cage: torchcage.Cage, seed: int) -> torch.Tensor:
    """Regular points interleaved with every kind that is not: on vertices, on a face, 1e-9 of the
    size off a face's plane, beside its edge, and far outside (taken by other kernels)."""
    g = torch.Generator().manual_seed(seed)
    V, tri = cage.vertices.to(D64), cage.triangles
    c, size = V.mean(0), cage.scale
    inside = c + 0.2 * size * (torch.rand(40, 3, generator=g, dtype=D64) - 0.5)
    p = V[tri[:6]]
    on_face = p.mean(1)
    nrm = torch.nn.functional.normalize(torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1), dim=-1)
    odd = torch.cat(
        [
            V[:4],
            on_face[:2],
            on_face[2:4] - 1e-9 * size * nrm[2:4],
            0.5 * (p[4:, 0] + p[4:, 1]),
            c + 1e6 * size * nrm[:2],
        ]
    )
    out = torch.empty(inside.shape[0] + odd.shape[0], 3, dtype=D64)
    out[::4][: odd.shape[0]] = odd  # one odd point in every block of four
    mask = torch.ones(out.shape[0], dtype=torch.bool)
    mask[::4][: odd.shape[0]] = False
    out[mask] = inside[: int(mask.sum())]
    return out


@pytest.mark.native
@pytest.mark.parametrize("make", [icosphere, lambda: twisted_bar(quads=False)])
def test_a_point_does_not_depend_on_its_block(lib, make):
    cage = make()
    x = _mixed_points(cage, seed=3)
    V, tri = cage.vertices.to(D64), cage.triangles
    g = torch.randn(x.shape[0], V.shape[0], generator=torch.Generator().manual_seed(4), dtype=D64)
    tol = 1e-14 * cage.scale
    gx, gP, reg = native_vjp(lib, x, V, tri, g, tol)
    assert 0 < int(reg.sum()) < x.shape[0] and bool(torch.isfinite(gP).all())
    assert bool((gx[~reg] == 0).all())
    # each point alone (blocks of one, its lanes repeating it), and the points in another order
    alone = [native_vjp(lib, x[i : i + 1], V, tri, g[i : i + 1], tol) for i in range(x.shape[0])]
    assert torch.equal(torch.cat([a[0] for a in alone]), gx)
    assert torch.equal(torch.cat([a[2] for a in alone]), reg)
    perm = torch.randperm(x.shape[0], generator=torch.Generator().manual_seed(5))
    gx_p, gP_p, reg_p = native_vjp(lib, x[perm], V, tri, g[perm], tol)
    assert torch.equal(gx_p, gx[perm]) and torch.equal(reg_p, reg[perm])
    # the vertex gradients: the regular points' only (sums in another order: rounding apart)
    total = sum(a[1] for a, r in zip(alone, reg, strict=True) if r)
    scale = float(gP.abs().max())
    assert float((gP - total).abs().max()) <= 1e-13 * scale and float((gP_p - gP).abs().max()) <= 1e-13 * scale
    # the torch form of the same derivation: the same points regular, the same products
    a = direct_vjp(x, V, tri, g, tol)
    assert torch.equal(a[2], reg)
    assert float((a[0] - gx).abs().max()) <= 1e-11 * float(a[0].abs().max())
    assert float((a[1] - gP).abs().max()) <= 1e-11 * float(a[1].abs().max())


@pytest.mark.native
def test_the_product_is_autograd_of_the_coordinates(lib):
    cage = icosphere()
    g = torch.Generator().manual_seed(6)
    x = 0.6 * (torch.rand(37, 3, generator=g, dtype=D64) - 0.5)  # (37: a last block of one point)
    cot = torch.randn(37, 42, generator=g, dtype=D64)
    V, tri = cage.vertices.to(D64), cage.triangles
    gx, gP, reg = native_vjp(lib, x, V, tri, cot, 1e-14 * cage.scale)
    assert bool(reg.all())
    xr, Vr = x.clone().requires_grad_(), V.clone().requires_grad_()
    lam = _torch_coordinates(xr, Vr, tri)  # plain autograd through the torch kernel (no custom backward)
    rx, rP = torch.autograd.grad((lam * cot).sum(), [xr, Vr])
    assert float((gx - rx).abs().max()) <= 1e-10 * float(rx.abs().max())
    assert float((gP - rP).abs().max()) <= 1e-10 * float(rP.abs().max())


@pytest.mark.native
def test_a_batch_of_cages_in_one_call_equals_each_cage_alone(lib):
    base = icosphere()
    g = torch.Generator().manual_seed(8)
    V = base.vertices.to(D64)[None] * (1 + 0.2 * torch.rand(3, 1, 1, generator=g, dtype=D64))
    V = V + 0.02 * torch.randn(V.shape, generator=g, dtype=D64)
    tri = base.triangles
    x = torch.stack([_mixed_points(torchcage.Cage(V[b], tri), seed=b) for b in range(3)])  # (mixed lanes)
    cot = torch.randn(3, x.shape[1], 42, generator=g, dtype=D64)
    tol = torch.tensor([1e-14 * torchcage.Cage(V[b], tri).scale for b in range(3)], dtype=D64)
    gx, gP, reg = native_vjp_batch(lib, x, V, tri, cot, tol)
    for b in range(3):
        ex, eP, er = native_vjp(lib, x[b], V[b], tri, cot[b], float(tol[b]))
        assert torch.equal(gx[b], ex) and torch.equal(reg[b], er) and 0 < int(er.sum()) < x.shape[1]
        assert float((gP[b] - eP).abs().max()) <= 1e-13 * float(eP.abs().max())
