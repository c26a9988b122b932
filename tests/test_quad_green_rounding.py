"""Quad Green coordinates of points given in float32 on the cage: they round to
just off it, half of them outside, where the bare integrals give 0; within the rounding of their
dtype they are on the cage. Points that are truly outside warn with their count."""

from __future__ import annotations

import warnings

import pytest
import torch

import torchcage
from torchcage import functional as F


def _turned_cube(g: torch.Generator) -> torchcage.Cage:
    """The quad cube turned at random, scaled by 1e-6..1e6 and moved by up to 1e3 sizes, in float32."""
    cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    q = q * torch.linalg.det(q)
    scale = 10 ** (float(torch.rand(1, generator=g)) * 12 - 6)
    shift = (torch.rand(3, generator=g, dtype=torch.float64) * 2 - 1) * 1e3 * scale
    V = cube.vertices.to(torch.float64) @ q.T * scale + shift
    return torchcage.Cage(V.float(), cube.quads)


def _on_quads(cage: torchcage.Cage, m: int, g: torch.Generator) -> torch.Tensor:
    """``m`` points on the bilinear quads of ``cage`` (float64 from its float32 corners)."""
    V, quads = cage.vertices.to(torch.float64), cage.quads
    f = torch.randint(0, quads.shape[0], (m,), generator=g)
    u, v = torch.rand(2, m, 1, generator=g, dtype=torch.float64)
    P = V[quads[f]]
    return (1 - u) * (1 - v) * P[:, 0] + u * (1 - v) * P[:, 1] + u * v * P[:, 2] + (1 - u) * v * P[:, 3]


def test_float32_points_on_the_cage_are_on_it():
    g = torch.Generator().manual_seed(4)
    for _ in range(4):
        cage = _turned_cube(g)
        x = _on_quads(cage, 100, g).float()  # rounded: half of them just outside
        with warnings.catch_warnings():
            warnings.simplefilter("error", torchcage.OutsideCageWarning)
            phi, psi = F.quad_green_coordinates(x, cage)
        assert phi.dtype == torch.float32
        assert float((phi.double().sum(1) - 1).abs().max()) < 1e-5  # (was 0 for about half)
        c = (cage.vertices.double().amax(0) + cage.vertices.double().amin(0)) / 2
        N = cage.quad_corner_normals().reshape(-1, 3).double()
        rec = phi.double() @ (cage.vertices.double() - c) + psi.double() @ N
        err = float((rec - (x.double() - c)).norm(dim=1).max()) / cage.scale
        # float32 results: their rounding times the distance of the cage from the origin
        assert err < 1e-5 * (1 + float(c.norm()) / cage.scale), err


def test_points_outside_warn_from_the_function():
    g = torch.Generator().manual_seed(5)
    cage = _turned_cube(g)
    c = (cage.vertices.double().amax(0) + cage.vertices.double().amin(0)) / 2
    x = _on_quads(cage, 40, g)
    x[:7] = c + 1.5 * (x[:7] - c)  # outside, half a cage radius and more
    with pytest.warns(torchcage.OutsideCageWarning, match="7 of 40 points lie outside"):
        F.quad_green_coordinates(x.float(), cage)
