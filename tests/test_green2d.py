"""2D Green coordinates (groundwork for conformal image warps): identity, similarity, mpmath."""

from __future__ import annotations

import math

import mpmath as mp
import torch

import torchcage
from torchcage.families.green.kernel2d import green2d_coordinates


def inside_polygon(x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Even-odd ray casting, independent of the coordinates."""
    a, b = v, v.roll(-1, 0)
    xs, ys = x[:, None, 0], x[:, None, 1]
    crosses = ((a[:, 1] > ys) != (b[:, 1] > ys)) & (
        xs < (b[:, 0] - a[:, 0]) * (ys - a[:, 1]) / (b[:, 1] - a[:, 1]) + a[:, 0]
    )
    return crosses.sum(1) % 2 == 1


def blob() -> torchcage.Cage:
    return torchcage.load_cage(torchcage.data.path("blob2d.obj"))


def test_identity_inside_zero_outside_and_similarity():
    cage = blob()
    x = (torch.rand(3000, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 2 - 1) * 1.5
    inside = inside_polygon(x, cage.vertices)
    phi, psi = green2d_coordinates(x, cage)
    rec = phi @ cage.vertices + psi @ cage.edge_normals()
    assert (rec[inside] - x[inside]).abs().max() < 1e-12
    assert rec[~inside].abs().max() < 1e-12  # Green's identity outside: zero
    assert (phi[inside].sum(1) - 1).abs().max() < 1e-12
    # Rotation, uniform scale and translation of the cage, with the stretch factors |a'| / |a|.
    th, s, t = 0.7, 1.8, torch.tensor([0.3, -1.2], dtype=torch.float64)
    rot = torch.tensor([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]], dtype=torch.float64)
    moved = torchcage.Cage(cage.vertices @ rot.T * s + t)
    e = cage.edges
    stretch = (moved.vertices[e[:, 1]] - moved.vertices[e[:, 0]]).norm(dim=1) / (
        cage.vertices[e[:, 1]] - cage.vertices[e[:, 0]]
    ).norm(dim=1)
    out = phi @ moved.vertices + psi @ (moved.edge_normals() * stretch[:, None])
    assert (out[inside] - (x[inside] @ rot.T * s + t)).abs().max() < 1e-12


def test_public_function_and_module_2d():
    cage = blob()
    x = (torch.rand(500, 2, generator=torch.Generator().manual_seed(5), dtype=torch.float64) * 2 - 1) * 1.2
    x = x[inside_polygon(x, cage.vertices)]
    phi, psi = torchcage.functional.green_coordinates(x, cage)
    assert phi.shape == (x.shape[0], cage.num_vertices) and psi.shape == (x.shape[0], cage.edges.shape[0])
    gc = torchcage.GreenCoordinates(cage, x)
    th, s, t = -1.1, 0.4, torch.tensor([2.0, 1.0], dtype=torch.float64)
    rot = torch.tensor([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]], dtype=torch.float64)
    assert (gc(cage.vertices @ rot.T * s + t) - (x @ rot.T * s + t)).abs().max() < 1e-12
    v = cage.vertices.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(torchcage.GreenCoordinates(cage, x[:4]), (v,))


def test_near_and_on_edges():
    cage = blob()
    v, e = cage.vertices, cage.edges
    n = cage.edge_normals()
    mid = 0.3 * v[e[:, 0]] + 0.7 * v[e[:, 1]]
    for d in [0.0, 1e-15, 1e-9, 1e-4]:
        x = torch.cat([mid - d * n, v])  # on the edges, then just inside; and the vertices
        phi, psi = green2d_coordinates(x, cage)
        assert torch.isfinite(phi).all() and torch.isfinite(psi).all()
        assert (phi @ v + psi @ n - x).abs().max() < 1e-12
        assert (phi.sum(1) - 1).abs().max() < 1e-12


@mp.workdps(30)
def test_agrees_with_quadrature_of_the_definition():
    cage = blob()
    v = cage.vertices.tolist()
    E = len(v)
    x = torch.tensor([[0.1, 0.2], [-0.5, 0.3], [0.9, -0.1]], dtype=torch.float64)
    phi, psi = green2d_coordinates(x, cage)
    for p in range(x.shape[0]):
        eta = [mp.mpf(float(c)) for c in x[p]]
        ref_phi = [mp.mpf(0)] * E
        for j in range(E):
            a0, a1 = v[j], v[(j + 1) % E]
            ax, ay = mp.mpf(a1[0]) - a0[0], mp.mpf(a1[1]) - a0[1]
            length = mp.sqrt(ax * ax + ay * ay)
            nx, ny = ay / length, -ax / length

            def xi(t, a0=a0, ax=ax, ay=ay, eta=eta):
                return a0[0] + t * ax - eta[0], a0[1] + t * ay - eta[1]

            def log_r(t, xi=xi):
                dx, dy = xi(t)
                return mp.log(dx * dx + dy * dy) / 2

            def dn(t, xi=xi, nx=nx, ny=ny):
                dx, dy = xi(t)
                return (dx * nx + dy * ny) / (dx * dx + dy * dy) / (2 * mp.pi)

            ref_psi = -length * mp.quad(log_r, [0, 1]) / (2 * mp.pi)
            assert abs(float(ref_psi) - float(psi[p, j])) < 1e-12
            ref_phi[j] += length * mp.quad(lambda t, dn=dn: (1 - t) * dn(t), [0, 1])
            ref_phi[(j + 1) % E] += length * mp.quad(lambda t, dn=dn: t * dn(t), [0, 1])
        assert max(abs(float(r) - float(c)) for r, c in zip(ref_phi, phi[p], strict=True)) < 1e-12
