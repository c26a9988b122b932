"""``benchmarks/peers.py`` without the authors' code: absent or broken peers are skipped with a
message and the script exits 0; the ctypes plumbing, the alternated timing and the difference
column are checked with a fake peer of ours, compiled from a few lines of C++ (on a tetrahedron
cage, mean value coordinates of an inside point are its barycentric coordinates, which the fake
computes by Cramer's rule)."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest
import torch

import torchcage

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import peers

needs_cxx = pytest.mark.skipif(shutil.which("c++") is None, reason="no C++ compiler")

TET = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
TET_FACES = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]  # outward

# Barycentric coordinates in the tetrahedron (vertices 0-3 of the cage): the MVC of inside points.
FAKE = r"""
extern "C" void peer_mvc(const double *c, long nv, const long *t, long nt, const double *x, long n,
                         double *out) {
    for (long i = 0; i < n; ++i) {
        double a[3][3], b[3], d;
        for (int r = 0; r < 3; ++r) {
            for (int k = 0; k < 3; ++k) a[r][k] = c[3 * (k + 1) + r] - c[r];
            b[r] = x[3 * i + r] - c[r];
        }
        d = a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1]) - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
          + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0]);
        double s = 0;
        for (int k = 0; k < 3; ++k) {
            double m[3][3];
            for (int r = 0; r < 3; ++r)
                for (int j = 0; j < 3; ++j) m[r][j] = j == k ? b[r] : a[r][j];
            double dk = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
                      - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
                      + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
            out[i * nv + k + 1] = dk / d;
            s += dk / d;
        }
        out[i * nv] = 1.0 - s;
    }
}
"""


def _fake_peer(tmp_path: Path, source: str = FAKE, stem: str = "fake") -> peers.Peer:
    (tmp_path / f"{stem}.cpp").write_text(source)
    (tmp_path / "checkout").mkdir(exist_ok=True)
    (tmp_path / "checkout" / "README").write_text("a fake checkout\n")
    return peers.Peer("fake peer", "TORCHCAGE_PEER_FAKE", "https://example.invalid/fake", ("mvc",),
                      driver=str(tmp_path / f"{stem}.cpp"), needs=("README",))  # fmt: skip


def _inside(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    w = torch.rand(n, 4, generator=g, dtype=torch.float64) + 0.05
    w = w / w.sum(1, keepdim=True)
    return w @ torch.tensor(TET, dtype=torch.float64)


def test_absent_peers_are_skipped_with_a_message(monkeypatch, capsys, tmp_path):
    for peer in peers.PEERS:
        monkeypatch.delenv(peer.env, raising=False)
    assert peers.main(["--data", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    for peer in peers.PEERS:
        assert f"skipping {peer.name}: {peer.env} is not set" in out
    assert "no peer available" in out


def test_checkout_without_the_files_is_named(monkeypatch, capsys, tmp_path):
    monkeypatch.setenv("TORCHCAGE_PEER_QMVC", str(tmp_path))
    assert peers.main(["--data", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert f"TORCHCAGE_PEER_QMVC={tmp_path} lacks coordinates/mvc/mvc.h" in out


@needs_cxx
def test_failed_build_is_skipped_with_the_compiler_message(monkeypatch, capsys, tmp_path):
    peer = next(p for p in peers.PEERS if p.env == "TORCHCAGE_PEER_QMVC")
    for name in peer.needs:
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text("#error not the authors' header\n")
    monkeypatch.setenv("TORCHCAGE_PEER_QMVC", str(tmp_path))
    assert peers.main(["--data", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert f"skipping {peer.name}: build failed" in out and "not the authors' header" in out


@needs_cxx
def test_fake_peer_agrees_and_a_wrong_one_shows_its_error(tmp_path):
    cage = torchcage.Cage(torch.tensor(TET, dtype=torch.float64), torch.tensor(TET_FACES))
    env = {"TORCHCAGE_PEER_FAKE": str(tmp_path / "checkout")}
    lib = peers.build_peer(_fake_peer(tmp_path), tmp_path, env)
    row = peers.compare(lib, "mvc", _inside(300), cage, repeat=2)
    assert row["diff"] < 1e-12
    assert row["peer"] >= 0 and row["torchcage"] > 0 and row["peer_wall"] > 0
    # a peer off by 1e-3 in one coordinate: the difference column reports that error
    wrong = FAKE.replace("out[i * nv] = 1.0 - s;", "out[i * nv] = 1.0 - s + 1e-3;")
    lib = peers.build_peer(_fake_peer(tmp_path, wrong, "wrong"), tmp_path, env)
    assert peers.compare(lib, "mvc", _inside(300), cage, repeat=1)["diff"] == pytest.approx(1e-3, rel=1e-9)


@needs_cxx
def test_table_from_a_fake_peer_on_a_small_data_set(monkeypatch, capsys, tmp_path):
    peer = _fake_peer(tmp_path)
    monkeypatch.setattr(peers, "PEERS", [peer])
    monkeypatch.setenv(peer.env, str(tmp_path / "checkout"))
    data = tmp_path / "data"
    (data / "qmvc").mkdir(parents=True)
    x = _inside(60, seed=1)
    mesh = "".join(f"v {a:.17g} {b:.17g} {c:.17g}\n" for a, b, c in x.tolist())
    mesh += "".join(f"f {3 * i + 1} {3 * i + 2} {3 * i + 3}\n" for i in range(20))
    (data / "qmvc" / "Tet.obj").write_text(mesh)
    cage = "".join(f"v {a} {b} {c}\n" for a, b, c in TET)
    cage += "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in TET_FACES)
    (data / "qmvc" / "Tet_Cage.obj").write_text(cage)
    threads = torch.get_num_threads()
    try:
        assert peers.main(["--data", str(data), "--models", "Tet", "Absent", "--methods", "mvc", "--repeat", "2"]) == 0
    finally:
        torch.set_num_threads(threads)
    out = capsys.readouterr().out
    assert "skipping Absent: not in" in out
    row = next(line for line in out.splitlines() if line.startswith("| Tet (60 pts)"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "MVC, 4 triangles" and cells[6] == ">= 8x"
    assert float(cells[7]) < 1e-12  # the largest difference between the two results
    assert cells[4].endswith("x") and cells[5].endswith("x")  # ratios (the fake takes microseconds)


# Checks what benchmarks/peers.py hands the LBC driver: each cage vertex is its own mesh vertex, and
# each edge's inner boundary points lie on that edge, ordered from its first end; returns the
# number of violations and writes the mesh vertex index into out[:, 0] (so the caller can tell
# rows apart).
FAKE_LBC = r"""
#include <cmath>
extern "C" int peer_lbc2d(const double *x, long n, const long *cells, long nc, const long *ctrl, long nv,
                          const long *ep, const long *off, int scheme, int iters, double alpha, double mu,
                          double *out) {
    int bad = 0;
    for (long v = 0; v < nv; ++v) {
        long a = ctrl[v], b = ctrl[(v + 1) % nv];
        double ex = x[2 * b] - x[2 * a], ey = x[2 * b + 1] - x[2 * a + 1], len = std::hypot(ex, ey), last = 0;
        for (long k = off[v]; k < off[v + 1]; ++k) {
            double px = x[2 * ep[k]] - x[2 * a], py = x[2 * ep[k] + 1] - x[2 * a + 1];
            double along = (px * ex + py * ey) / len, across = (px * ey - py * ex) / len;
            if (std::fabs(across) > 1e-9 * len || along <= last || along >= len) ++bad;
            last = along;
        }
    }
    for (long i = 0; i < n; ++i)
        for (long v = 0; v < nv; ++v) out[i * nv + v] = v == 0 ? (double)i : 0.0;
    return bad;
}
"""


@needs_cxx
def test_lbc_driver_gets_each_edges_boundary_points_in_order(tmp_path):
    from torchcage.solvers.domain import mesh_domain

    peer = _fake_peer(tmp_path, FAKE_LBC, "fake_lbc")
    lib = peers.build_peer(peer, tmp_path, {peer.env: str(tmp_path / "checkout")})
    square = torch.tensor([[0.0, 0.0], [2.0, 0.0], [2.0, 1.0], [1.0, 1.5], [0.0, 1.0]], dtype=torch.float64)
    cage = torchcage.Cage(square)
    domain = mesh_domain(cage, 200)
    assert domain.boundary.numel() > 2 * cage.vertices.shape[0]  # edges hold inner boundary points
    call = peers.lbc_calls(lib, domain, cage)[0]
    out = call(5)  # raises RuntimeError when the driver counts a violation
    assert out.shape == (domain.vertices.shape[0], 5)
    assert (out[:, 0] == range(domain.vertices.shape[0])).all()
