"""Mirror symmetry: a symmetric cage and a symmetric deformation give a symmetric result."""

from __future__ import annotations

import pytest
import torch
from support import centred_cube

import torchcage


@pytest.mark.parametrize("module", [torchcage.MeanValueCoordinates, torchcage.GreenCoordinates])
def test_mirror_symmetry(module):
    cage = centred_cube()
    g = torch.Generator().manual_seed(0)
    x = torch.rand(200, 3, generator=g, dtype=torch.float64) * 1.8 - 0.9
    mirror = torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    both = torch.cat([x, x * mirror])
    m = module(cage, both)
    v = cage.vertices
    # A deformation symmetric under x -> -x: bulge in y that depends on x^2, twist-free.
    deformed = v + torch.stack([0.3 * v[:, 0] * v[:, 2], 0.4 * v[:, 0] ** 2, 0.2 * v[:, 1]], dim=1)
    out = m(deformed)
    a, b = out[:200], out[200:]
    assert (a * mirror - b).abs().max() < 1e-10


def test_degenerate_deformed_face_stays_finite():
    cage = centred_cube()
    x = torch.rand(20, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 1.6 - 0.8
    gc = torchcage.GreenCoordinates(cage, x)
    v = cage.vertices.clone()
    t = cage.triangles[0]
    v[t[1]] = v[t[0]]  # collapse one face to a segment
    v = v.requires_grad_(True)
    out = gc(v)
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(v.grad).all()
