"""Splat scenes: the 3D Gaussian splatting PLY file (bit-exact round trips) and the exact rotation
of spherical-harmonic colours."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcage.splats import GaussianScene, PlyError, eval_sh, quaternion_to_matrix, read_ply, rotate_sh, write_ply
from torchcage.splats.sh import sh_basis

D64 = torch.float64


def _random_rotations(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return quaternion_to_matrix(torch.randn(n, 4, generator=g, dtype=D64))


def _unit(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=D64), dim=-1)


def _file_like_reference(path, n: int, k: int, seed: int, *, crlf: bool = False, big: bool = False) -> bytes:
    """A splat PLY written field by field with numpy (the reference layout plus normals, an extra
    uchar field and a trailing element), independent of write_ply."""
    rng = np.random.default_rng(seed)
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    order = ">" if big else "<"
    dt = [(nm, order + "f4") for nm in names] + [("label", "u1")]
    rec = np.zeros(n, dtype=dt)
    for nm in names:
        rec[nm] = rng.standard_normal(n).astype(np.float32)
    rec["label"] = rng.integers(0, 255, n)
    end = "\r\n" if crlf else "\n"
    fmt = "binary_big_endian" if big else "binary_little_endian"
    header = ["ply", f"format {fmt} 1.0", "comment made by a test", f"element vertex {n}"]
    header += [f"property float {nm}" for nm in names] + ["property uchar label"]
    header += ["element camera 1", "property double fx", "end_header"]
    data = "".join(line + end for line in header).encode() + rec.tobytes() + np.array([500.5], order + "f8").tobytes()
    path.write_bytes(data)
    return data


@pytest.mark.parametrize(("k", "crlf", "big"), [(16, False, False), (4, True, False), (1, False, True)])
def test_round_trip_is_bit_exact(tmp_path, k: int, crlf: bool, big: bool) -> None:
    src, dst = tmp_path / "in.ply", tmp_path / "out.ply"
    data = _file_like_reference(src, 257, k, seed=k, crlf=crlf, big=big)
    scene = read_ply(src)
    assert scene.num_gaussians == 257 and scene.degree == math.isqrt(k) - 1
    assert set(scene.extra) == {"nx", "ny", "nz", "label"}
    write_ply(dst, scene)
    assert dst.read_bytes() == data


def test_fields_land_where_the_format_says(tmp_path) -> None:
    """f_rest is channel-major: f_rest[c (K-1) + j] is coefficient 1 + j of channel c."""
    src = tmp_path / "in.ply"
    _file_like_reference(src, 5, 16, seed=3)
    rec = np.fromfile(src, dtype=np.uint8)  # (only to locate the records)
    scene = read_ply(src)
    header_end = bytes(rec).index(b"end_header\n") + len(b"end_header\n")
    names = [f"f_rest_{i}" for i in range(45)]
    cols = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", *names]
    cols += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    arr = np.frombuffer(bytes(rec[header_end:]), dtype=[(c, "<f4") for c in cols] + [("label", "u1")], count=5)
    for c in range(3):
        for j in range(15):
            assert np.array_equal(scene.sh[:, 1 + j, c].numpy(), arr[f"f_rest_{c * 15 + j}"])
        assert np.array_equal(scene.sh[:, 0, c].numpy(), arr[f"f_dc_{c}"])
    assert np.array_equal(scene.rotations[:, 0].numpy(), arr["rot_0"])
    assert np.array_equal(scene.means[:, 2].numpy(), arr["z"])


def test_a_new_scene_writes_the_standard_layout(tmp_path) -> None:
    scene = GaussianScene.random(33, degree=3, seed=1)
    write_ply(tmp_path / "s.ply", scene)
    text = (tmp_path / "s.ply").read_bytes().split(b"end_header\n")[0].decode()
    props = [line.split()[-1] for line in text.splitlines() if line.startswith("property")]
    assert props[:6] == ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert props[-8:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    back = read_ply(tmp_path / "s.ply")
    for name in ("means", "log_scales", "rotations", "opacity_logits", "sh"):
        assert torch.equal(getattr(back, name), getattr(scene, name))


def test_bad_files_are_refused_with_a_reason(tmp_path) -> None:
    f = tmp_path / "a.ply"
    f.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    with pytest.raises(PlyError, match="binary"):
        read_ply(f)
    f.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n\0\0\0\0")
    with pytest.raises(PlyError, match="lacks the Gaussian fields"):
        read_ply(f)
    f.write_bytes(b"solid x\n")
    with pytest.raises(PlyError, match="not a PLY"):
        read_ply(f)
    scene = GaussianScene.random(3, degree=0)
    scene.means[1, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        write_ply(tmp_path / "b.ply", scene)


def test_basis_degree_blocks_are_harmonic_polynomials() -> None:
    """Independent of the rotation code: each degree-l block is orthogonal to the others on the
    sphere (a fine quadrature), with the normalisation of real orthonormal harmonics."""
    n = 200_000
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=torch.Generator().manual_seed(0), dtype=D64), dim=-1)
    Y = sh_basis(d, 3)
    gram = 4 * math.pi * (Y.T @ Y) / n  # Monte Carlo: orthonormal up to about 1/sqrt(n)
    assert torch.allclose(gram, torch.eye(16, dtype=D64), atol=0.03)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_rotation_agrees_with_direct_evaluation(degree: int) -> None:
    """c'(d) = c(R^T d) in random directions, to 1e-12, for random rotations and coefficients."""
    n = 64
    g = torch.Generator().manual_seed(degree)
    sh = torch.randn(n, (degree + 1) ** 2, 3, generator=g, dtype=D64)
    R = _random_rotations(n, seed=degree + 10)
    rotated = rotate_sh(sh, R)
    for seed in range(3):
        d = _unit(n, seed)
        direct = eval_sh(sh, (R.transpose(-1, -2) @ d[..., None])[..., 0])
        assert float((eval_sh(rotated, d) - direct).abs().max()) < 1e-12


def test_rotation_composes_and_inverts() -> None:
    """X(R1 R2) = X(R1) X(R2) in effect, X(I) = I, X(R^T) undoes X(R); batched poses broadcast."""
    sh = torch.randn(10, 16, 3, dtype=D64, generator=torch.Generator().manual_seed(5))
    R1, R2 = _random_rotations(10, 1), _random_rotations(10, 2)
    assert torch.allclose(rotate_sh(sh, torch.eye(3, dtype=D64).expand(10, 3, 3)), sh, atol=1e-13)
    assert torch.allclose(rotate_sh(rotate_sh(sh, R2), R1), rotate_sh(sh, R1 @ R2), atol=1e-12)
    assert torch.allclose(rotate_sh(rotate_sh(sh, R1), R1.transpose(-1, -2)), sh, atol=1e-12)
    poses = torch.stack([R1, R2])  # (2, 10, 3, 3) with one coefficient set
    both = rotate_sh(sh, poses)
    assert both.shape == (2, 10, 16, 3) and torch.allclose(both[1], rotate_sh(sh, R2), atol=1e-14)


def test_rotation_is_differentiable() -> None:
    sh = torch.randn(3, 9, 3, dtype=D64, requires_grad=True)
    q = torch.randn(3, 4, dtype=D64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda s, q: rotate_sh(s, quaternion_to_matrix(q)), (sh, q))
