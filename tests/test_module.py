"""The MeanValueCoordinates module: buffers, batching, gradients, errors."""

from __future__ import annotations

import io

import pytest
import torch
from support import HANDMADE

import torchcage


def make(device="cpu"):
    cage = HANDMADE["l_shape"]().to(device=device)
    g = torch.Generator().manual_seed(0)
    pts = (torch.rand(64, 3, generator=g, dtype=torch.float64) * torch.tensor([1.8, 0.8, 0.9]).double() - 0.9).to(
        device
    )
    return cage, pts, torchcage.MeanValueCoordinates(cage, pts)


def test_rest_pose_and_batching(device):
    cage, pts, m = make(device)
    assert torch.allclose(m(cage.vertices), pts, atol=1e-12)
    rot = torch.linalg.matrix_exp(torch.tensor([[0, -0.4, 0.1], [0.4, 0, -0.2], [-0.1, 0.2, 0]]).double()).to(device)
    poses = torch.stack([cage.vertices, cage.vertices @ rot.T + 1.0, 2 * cage.vertices])  # (3, V, 3)
    out = m(poses.reshape(3, 1, -1, 3).expand(3, 2, -1, 3))
    assert out.shape == (3, 2, 64, 3)
    assert torch.allclose(out[1, 0], pts @ rot.T + 1.0, atol=1e-12)  # rigid motions are reproduced
    assert torch.allclose(out[2, 1], 2 * pts, atol=1e-12)
    assert m(cage.vertices.float()).dtype == torch.float32


def test_state_dict_round_trip():
    cage, pts, m = make()
    buf = io.BytesIO()
    torch.save(m.state_dict(), buf)
    assert set(m.state_dict()) == {"rest_vertices", "points", "weights", "faces"}  # faces: derivatives on demand
    m2 = torchcage.MeanValueCoordinates(cage, pts + 0.01)
    buf.seek(0)
    m2.load_state_dict(torch.load(buf))
    assert torch.equal(m2.weights, m.weights)
    assert "points=64" in repr(m)


def test_gradients_to_vertices():
    cage, _, m = make()
    v = cage.vertices.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: m(x), (v,))
    loss = m(v).square().sum()
    loss.backward()
    assert v.grad is not None and torch.isfinite(v.grad).all()


def test_module_to_float32_and_device():
    _, _, m = make()
    m32 = m.to(torch.float32)
    assert m32.weights.dtype == torch.float32
    if torch.cuda.is_available():
        mc = m.to("cuda")
        assert mc(mc.rest_vertices).device.type == "cuda"


def test_errors():
    _, pts, m = make()
    with pytest.raises(ValueError, match=r"\(\*, 12, 3\)"):
        m(torch.zeros(11, 3, dtype=torch.float64))
    with pytest.raises(TypeError, match="floating point"):
        m(torch.zeros(12, 3, dtype=torch.int64))
    with pytest.raises(ValueError, match=r"module\.to"):
        m(torch.zeros(12, 3, dtype=torch.float64, device="meta"))
    with pytest.raises(torchcage.CageError, match="triangulated"):
        torchcage.MeanValueCoordinates(torchcage.load_cage(torchcage.data.path("cube.obj")), pts)


def test_2d_module():
    cage = torchcage.Cage([[0.0, 0], [2, 0], [2, 1], [1, 1.5], [0, 1]])
    pts = torch.tensor([[0.5, 0.5], [1.5, 0.4], [1.0, 1.2]], dtype=torch.float64)
    m = torchcage.MeanValueCoordinates(cage, pts)
    A = torch.tensor([[1.2, 0.3], [-0.1, 0.8]], dtype=torch.float64)
    assert torch.allclose(m(cage.vertices @ A.T + 0.5), pts @ A.T + 0.5, atol=1e-12)
