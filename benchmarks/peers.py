"""torchcage against the papers' authors' code, side by side in one process, on one thread.

The authors' code is not in this repository: each peer is built from a checkout whose path the
user gives in an environment variable, through a small driver of ours (``benchmarks/peers/``)
compiled with ``-O3 -march=native -DNDEBUG`` (a release build) into a shared library that this
script calls through ctypes with numpy arrays. A peer whose variable is unset, or whose build
fails, is skipped with a message (the script still exits 0).

=====================  ==========================================  ===========================
variable               checkout of                                 methods
=====================  ==========================================  ===========================
TORCHCAGE_PEER_QMVC    https://github.com/superboubek/QMVC         MVC, GC, QMVC (n = 4)
                       (Thiery, Memari, Boubekeur 2018; header-only
                       C++; ``coordinates/`` is read)
TORCHCAGE_PEER_        https://github.com/DanStroeter/CageModeler  QGC (n = 2, their fixed
CAGEMODELER            (``cagedeformations/``; needs the Eigen 3    grid); goal: at most 2x
                       headers: libeigen3-dev or                    torchcage's QMVC (n = 4),
                       ``EIGEN3_INCLUDE_DIR``)                      timed in the same turns
TORCHCAGE_PEER_LBC     https://github.com/bldeng/LBC (the LBC       LBC, seconds per ADMM
                       authors' solver; Eigen 3 and OpenMP)         iteration (2D cages of
                                                                    ``<data>/lbc2d``)
=====================  ==========================================  ===========================

LBC runs both solvers on torchcage's mesh of each 2D cage with the same settings (quadratic
weights, penalty 10, relaxation 1.65, tolerances 0), for ``--lbc-iterations`` and for 10
iterations; the difference of the times over the difference of the counts is the time per
iteration (the setup cancels).

Timing: one thread for both (``torch.set_num_threads(1)``; the native kernels take their thread
count from torch; ``OMP_NUM_THREADS=1`` is set before torch loads). For each model and method the
authors' code and torchcage run alternately ``--repeat`` times after one untimed alternated round
at full size (the warm-up: tables, libraries, and the memory allocator's heap, whose first calls
fault in fresh pages for torchcage's outputs, while the authors' code writes into arrays made
once); the table gives the minimum CPU time (``time.process_time``) of each, the ratio of the
minima, the ratio of the minimum wall times beside it, and the largest absolute difference between
the two results (the same coordinates, computed twice). The machine's load average is printed
before and after. Mesh vertices are the points; cages are triangulated along ``q0-q2`` for MVC and
GC, triquad for QMVC and QGC. Both QMVC and QGC are quadratures of the same integrals, by
different rules (the authors' n and torchcage's n are not the same points), so for them the script
also prints each one's largest error to the exact coordinates (torchcage's ``tol=1e-10``). Green
coordinates are compared as bare integrals (``exterior="none"``, what the authors' code computes at
every point).

Usage::

    export TORCHCAGE_PEER_QMVC=/path/to/QMVC TORCHCAGE_PEER_CAGEMODELER=/path/to/CageModeler
    export TORCHCAGE_PEER_LBC=/path/to/LBC
    python benchmarks/peers.py [--models FireHydrant Beast] [--methods mvc gc qmvc qgc lbc]
        [--repeat 5] [--lbc-models cactus Gil_Gecko] [--lbc-iterations 1000] [--data ../shared/data]
"""

from __future__ import annotations

import os

if __name__ == "__main__":
    os.environ["OMP_NUM_THREADS"] = "1"  # before torch and the native kernels load

import argparse
import ctypes
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import add_data_argument, load_model, qmvc_root

import torchcage
from torchcage import functional as F
from torchcage.backends import native as _native
from torchcage.solvers.domain import Domain, mesh_domain
from torchcage.solvers.lbc import solve_lbc

HERE = Path(__file__).resolve().parent / "peers"
#: ``-DNDEBUG`` as in a release build: the peers' ``assert`` (and Eigen's index checks) compiled out.
FLAGS = ("-O3", "-march=native", "-DNDEBUG", "-shared", "-fPIC")

#: The goal of the issue for each method (torchcage's speed-up over the authors' code).
GOALS = {"mvc": ">= 8x", "gc": ">= 8x", "qmvc": ">= 5x", "qgc": "<= 2x our QMVC", "lbc": ">= 3x"}
LABELS = {"mvc": "MVC", "gc": "GC", "qmvc": "QMVC, n=4", "qgc": "QGC, n=2", "lbc": "LBC"}
#: The LBC comparison's models (``<data>/lbc2d/<name>-control-edgeset.obj``, the LBC authors' 2D cages).
LBC_MODELS = ["cactus", "Gil_Gecko"]

_d = ctypes.POINTER(ctypes.c_double)
_l = ctypes.POINTER(ctypes.c_long)
_n = ctypes.c_long


class PeerUnavailableError(Exception):
    """A peer cannot be used (variable unset, files missing, build failed); the text says why."""


@dataclass
class Peer:
    """One authors' code base: where its checkout comes from and how our driver is built on it.

    Attributes:
        name: short name used in messages.
        env: the environment variable that names the checkout.
        url: the repository the checkout comes from.
        methods: the methods its driver serves (keys of :data:`GOALS`).
        driver: our driver source, under ``benchmarks/peers/``.
        needs: files that must exist in the checkout (relative paths).
        includes: include folders, relative to the checkout.
        sources: the checkout's source files compiled with the driver.
        extra_includes: include folders of ours (stand-in headers).
        eigen: whether the Eigen 3 headers are needed.
        flags: further compiler flags.
    """

    name: str
    env: str
    url: str
    methods: tuple[str, ...]
    driver: str = ""
    needs: tuple[str, ...] = ()
    includes: tuple[str, ...] = ()
    sources: tuple[str, ...] = ()
    extra_includes: tuple[Path, ...] = field(default_factory=tuple)
    eigen: bool = False
    flags: tuple[str, ...] = ()


PEERS = [
    Peer(
        "QMVC authors' C++",
        "TORCHCAGE_PEER_QMVC",
        "https://github.com/superboubek/QMVC",
        ("mvc", "gc", "qmvc"),
        driver="qmvc_driver.cpp",
        needs=tuple(f"coordinates/{h}" for h in ("mvc/mvc.h", "gc/gc.h", "qmvc/qmvc.h", "shared/point3.h")),
        includes=("coordinates", "coordinates/shared", "coordinates/qmvc"),
        extra_includes=(HERE / "shim",),
    ),
    Peer(
        "CageModeler",
        "TORCHCAGE_PEER_CAGEMODELER",
        "https://github.com/DanStroeter/CageModeler",
        ("qgc",),
        driver="cagemodeler_driver.cpp",
        needs=(
            "cagedeformations/include/cagedeformations/GreenCoordinates.h",
            "cagedeformations/src/GreenCoordinates.cpp",
        ),
        includes=("cagedeformations/include",),
        sources=("cagedeformations/src/GreenCoordinates.cpp",),
        eigen=True,
    ),
    Peer(
        "LBC authors' solver",
        "TORCHCAGE_PEER_LBC",
        "https://github.com/bldeng/LBC",
        ("lbc",),
        driver="lbc_driver.cpp",
        needs=("DataSetup.h", "DataSetup.cpp", "LBCSolver.h", "LBCSolver.cpp", "common.h"),
        includes=(".",),
        sources=("DataSetup.cpp", "LBCSolver.cpp"),
        eigen=True,
        flags=("-fopenmp",),  # their solver's parallel regions (one thread here)
    ),
]


def compile_library(
    sources: Sequence[Path],
    out: Path,
    includes: Sequence[Path] = (),
    cxx: str | None = None,
    flags: Sequence[str] = (),
) -> Path:
    """Compile ``sources`` into the shared library ``out`` with ``-O3 -march=native``.

    Args:
        sources: C or C++ files (the compiler is ``$CXX``, else ``c++``, unless ``cxx`` is given).
        out: the library's path.
        includes: include folders.
        cxx: the compiler command.
        flags: further flags (after :data:`FLAGS`).

    Returns:
        ``out``.

    Raises:
        PeerUnavailableError: no compiler, or the build failed (with the compiler's last lines).
    """
    cxx = cxx or os.environ.get("CXX", "c++")
    if shutil.which(cxx) is None:
        raise PeerUnavailableError(f"no C++ compiler {cxx!r} on PATH (set CXX)")
    cmd = [cxx, *FLAGS, *flags, *(f"-I{p}" for p in includes), *map(str, sources), "-o", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        tail = "\n".join(proc.stderr.strip().splitlines()[-8:])
        raise PeerUnavailableError(f"build failed ({' '.join(cmd)}):\n{tail}")
    return out


def build_peer(peer: Peer, build_dir: Path, environ: dict[str, str] | None = None) -> ctypes.CDLL:
    """Build ``peer``'s driver on the checkout its variable names, and load it.

    Raises:
        PeerUnavailableError: the variable is unset, the checkout lacks a file, or the build failed.
    """
    environ = os.environ if environ is None else environ
    root = environ.get(peer.env)
    if not root:
        raise PeerUnavailableError(f"{peer.env} is not set (a checkout of {peer.url})")
    checkout = Path(root).expanduser()
    missing = [n for n in peer.needs if not (checkout / n).is_file()]
    if missing:
        raise PeerUnavailableError(f"{peer.env}={checkout} lacks {', '.join(missing)} (a checkout of {peer.url}?)")
    includes = [*peer.extra_includes, *(checkout / p for p in peer.includes)]
    if peer.eigen:
        includes.append(eigen_include(environ))
    out = build_dir / f"lib{Path(peer.driver).stem}.so"
    compile_library([HERE / peer.driver, *(checkout / p for p in peer.sources)], out, includes, flags=peer.flags)
    return bind(ctypes.CDLL(str(out)))


def eigen_include(environ: dict[str, str] | os._Environ[str]) -> Path:
    """The Eigen 3 include folder: ``$EIGEN3_INCLUDE_DIR``, else the usual system places.

    Raises:
        PeerUnavailableError: no ``Eigen/Dense`` found.
    """
    places = [environ.get("EIGEN3_INCLUDE_DIR", ""), "/usr/include/eigen3", "/usr/local/include/eigen3"]
    for place in places:
        if place and (Path(place) / "Eigen" / "Dense").is_file():
            return Path(place)
    raise PeerUnavailableError("the Eigen 3 headers are not found (install libeigen3-dev or set EIGEN3_INCLUDE_DIR)")


def bind(lib: ctypes.CDLL) -> ctypes.CDLL:
    """Declare the driver ABI (``benchmarks/peers/qmvc_driver.cpp``) on the functions ``lib`` has."""
    sig = {
        "peer_mvc": [_d, _n, _l, _n, _d, _n, _d],
        "peer_gc": [_d, _n, _l, _n, _d, _n, _d, _d],
        "peer_qmvc": [_d, _n, _l, _n, _l, _n, _d, _n, _d],
        "peer_qgc": [_d, _n, _l, _n, _l, _n, _d, _n, _d, _d],
        "peer_lbc2d": [
            _d,
            _n,
            _l,
            _n,
            _l,
            _n,
            _l,
            _l,
            ctypes.c_int,
            ctypes.c_int,
            ctypes.c_double,
            ctypes.c_double,
            _d,
        ],
    }
    for name, args in sig.items():
        if hasattr(lib, name):
            getattr(lib, name).argtypes = args
            getattr(lib, name).restype = ctypes.c_int if name == "peer_lbc2d" else None
    return lib


def _ptr(a: np.ndarray, kind: type) -> ctypes._Pointer:  # type: ignore[type-arg]
    return a.ctypes.data_as(ctypes.POINTER(kind))


def _np(t: torch.Tensor, dtype: type) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=dtype)


#: What a timed call returns: the ``(N, V)`` coordinates, or ``(phi, psi)`` as each side computes
#: them (joined by :func:`joined` after the timing: neither side needs the copy).
Result = np.ndarray | tuple[np.ndarray, np.ndarray]


def joined(r: Result) -> np.ndarray:
    """``r`` as one array ``(N, V)`` or ``(N, V + T)`` (``phi`` then ``psi``), for the comparisons."""
    return np.concatenate(r, 1) if isinstance(r, tuple) else r


def peer_call(lib: ctypes.CDLL, method: str, points: torch.Tensor, cage: torchcage.Cage) -> Callable[[], Result]:
    """A no-argument function that runs ``method`` of the peer library on ``points``.

    The arrays are converted once, outside the timed call. ``mvc`` and ``gc`` take the cage
    triangulated along ``q0-q2``; ``qmvc`` the triquad cage. The result is ``(N, V)``, or for
    ``gc`` and ``qgc`` the pair ``(phi, psi)`` the peer wrote.
    """
    x = _np(points, np.float64)
    n = x.shape[0]
    if method in ("mvc", "gc"):
        tri = cage.triangulated()
        v, t = _np(tri.vertices, np.float64), _np(tri.triangles, np.int64)
        nv, nt = v.shape[0], t.shape[0]
        if method == "mvc":
            out = np.empty((n, nv))
            return lambda: (lib.peer_mvc(_ptr(v, ctypes.c_double), nv, _ptr(t, ctypes.c_long), nt,
                                         _ptr(x, ctypes.c_double), n, _ptr(out, ctypes.c_double)), out)[1]  # fmt: skip
        phi, psi = np.empty((n, nv)), np.empty((n, nt))
        return lambda: (lib.peer_gc(_ptr(v, ctypes.c_double), nv, _ptr(t, ctypes.c_long), nt,
                                    _ptr(x, ctypes.c_double), n, _ptr(phi, ctypes.c_double),
                                    _ptr(psi, ctypes.c_double)), (phi, psi))[1]  # fmt: skip
    v = _np(cage.vertices, np.float64)
    t = _np(cage.triangles, np.int64).reshape(-1, 3)
    q = _np(cage.quads, np.int64).reshape(-1, 4)
    nv, nt, nq = v.shape[0], t.shape[0], q.shape[0]
    if method == "qmvc":
        out = np.empty((n, nv))
        return lambda: (lib.peer_qmvc(_ptr(v, ctypes.c_double), nv, _ptr(t, ctypes.c_long), nt,
                                      _ptr(q, ctypes.c_long), nq, _ptr(x, ctypes.c_double), n,
                                      _ptr(out, ctypes.c_double)), out)[1]  # fmt: skip
    if method == "qgc":
        phi, psi = np.empty((n, nv)), np.empty((n, nt + 4 * nq))
        return lambda: (lib.peer_qgc(_ptr(v, ctypes.c_double), nv, _ptr(t, ctypes.c_long), nt,
                                     _ptr(q, ctypes.c_long), nq, _ptr(x, ctypes.c_double), n,
                                     _ptr(phi, ctypes.c_double), _ptr(psi, ctypes.c_double)),
                        (phi, psi))[1]  # fmt: skip
    raise ValueError(f"unknown method {method!r}; expected one of {sorted(GOALS)}")


def torchcage_call(method: str, points: torch.Tensor, cage: torchcage.Cage) -> Callable[[], Result]:
    """The same as :func:`peer_call`, computed by torchcage (default backend, float64; the tensors
    as NumPy views, no copy)."""
    if method == "mvc":
        tri = cage.triangulated()
        return lambda: F.mean_value_coordinates(points, tri).numpy()
    if method == "gc":
        tri = cage.triangulated()
        return lambda: _views(F.green_coordinates(points, tri, exterior="none"))
    if method == "qmvc":
        return lambda: F.quad_mean_value_coordinates(points, cage, n=4).numpy()
    if method == "qgc":
        return lambda: _views(F.quad_green_coordinates(points, cage, n=2))
    raise ValueError(f"unknown method {method!r}; expected one of {sorted(GOALS)}")


def _views(r: tuple[torch.Tensor, torch.Tensor]) -> tuple[np.ndarray, np.ndarray]:
    return r[0].numpy(), r[1].numpy()


def alternate(fns: Sequence[Callable[[], Result]], repeat: int) -> tuple[list[float], list[float], list[Result]]:
    """Run ``fns`` in turn ``repeat`` times: the minimum CPU and wall seconds of each, and each
    one's last result. (The results are held, not copied between the calls: a copy of every
    result made the allocator's heap grow and shrink, and torchcage, which returns fresh arrays
    where the authors' drivers write into arrays made once, then faulted in fresh pages on every
    call; the peers' arrays are rewritten by each call, and each one's last call is its last.)"""
    cpu, wall = [float("inf")] * len(fns), [float("inf")] * len(fns)
    outs: list[Result] = [np.empty(0)] * len(fns)
    for _ in range(repeat):
        for i, fn in enumerate(fns):
            c, w = time.process_time(), time.perf_counter()
            outs[i] = fn()
            w, c = time.perf_counter() - w, time.process_time() - c
            cpu[i], wall[i] = min(cpu[i], c), min(wall[i], w)
    return cpu, wall, outs


def compare(lib: ctypes.CDLL, method: str, points: torch.Tensor, cage: torchcage.Cage, repeat: int) -> dict[str, float]:
    """Time ``method`` of the peer and of torchcage alternately; the row's figures."""
    fns = [peer_call(lib, method, points, cage), torchcage_call(method, points, cage)]
    if method == "qgc":  # the goal of QGC is relative to torchcage's QMVC: timed in the same turns
        fns.append(torchcage_call("qmvc", points, cage))
    alternate(fns, 1)  # (warm-up at full size, both sides: tables, libraries, the allocator's heap)
    cpu, wall, outs = alternate(fns, repeat)
    po, to = joined(outs[0]), joined(outs[1])
    row = {"peer": cpu[0], "torchcage": cpu[1], "peer_wall": wall[0], "torchcage_wall": wall[1],
           "diff": float(np.abs(po - to).max()) if po.size else 0.0}  # fmt: skip
    if method == "qgc":
        row["torchcage_qmvc"] = cpu[2]
    if method in ("qmvc", "qgc"):  # both are quadratures of the same integrals: their errors to the exact ones
        if method == "qmvc":
            exact = F.quad_mean_value_coordinates(points, cage, tol=1e-10).numpy()
        else:
            exact = torch.cat(F.quad_green_coordinates(points, cage, tol=1e-10), 1).numpy()
        row["peer_err"], row["torchcage_err"] = float(np.abs(po - exact).max()), float(np.abs(to - exact).max())
    return row


def load_polygon(data: str | Path, name: str) -> torchcage.Cage | None:
    """The LBC authors' 2D cage ``<data>/lbc2d/<name>-control-edgeset.obj`` (``None`` if absent)."""
    path = Path(data) / "lbc2d" / f"{name}-control-edgeset.obj"
    if not path.is_file():
        return None
    with open(path) as fh:
        v = [[float(t) for t in line.split()[1:3]] for line in fh if line.startswith("v ")]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a clockwise polygon is flipped (both solvers get the same one)
        return torchcage.Cage(torch.tensor(v, dtype=torch.float64))


def lbc_calls(
    lib: ctypes.CDLL, domain: Domain, cage: torchcage.Cage, mu: float = 10.0, alpha: float = 1.65
) -> tuple[Callable[[int], np.ndarray], Callable[[int], np.ndarray]]:
    """Two functions ``f(iterations) -> (Nv, V) coordinates``: the peer's and torchcage's LBC solve
    on ``domain`` with the same settings (quadratic weights, fixed penalty ``mu``, relaxation
    ``alpha``, all tolerances 0 so that exactly ``iterations`` ADMM iterations run)."""
    nv = cage.vertices.shape[0]
    x = _np(domain.vertices, np.float64)
    cells = _np(domain.cells, np.int64)
    vals = domain.boundary_values.numpy()
    edges: list[list[int]] = [[] for _ in range(nv)]
    for k, i in enumerate(domain.boundary.tolist()):  # boundary samples inside cage edge (a, a + 1)
        if i < nv:
            continue
        a, b = sorted(np.nonzero(np.abs(vals[k]) > 1e-12)[0].tolist())
        edges[a if (a + 1) % nv == b else b].append(i)
    for a, inner in enumerate(edges):
        inner.sort(key=lambda i: float(np.linalg.norm(x[i] - x[a])))
    offsets = np.cumsum([0] + [len(e) for e in edges]).astype(np.int64)
    points = np.array([i for e in edges for i in e], dtype=np.int64)
    ctrl = np.arange(nv, dtype=np.int64)  # the mesh's first V vertices are the cage's
    out = np.empty((x.shape[0], nv))

    def peer(iterations: int) -> np.ndarray:
        rc = lib.peer_lbc2d(_ptr(x, ctypes.c_double), x.shape[0], _ptr(cells, ctypes.c_long), cells.shape[0],
                            _ptr(ctrl, ctypes.c_long), nv, _ptr(points, ctypes.c_long), _ptr(offsets, ctypes.c_long),
                            2, iterations, alpha, mu, _ptr(out, ctypes.c_double))  # fmt: skip
        if rc != 0:
            raise RuntimeError(f"the LBC peer returned {rc}")
        return out

    def ours(iterations: int) -> np.ndarray:
        r = solve_lbc(domain, cage.vertices, weighting="quadratic", mu=mu, alpha=alpha, eps_primal=0, eps_dual=0,
                      max_iter=iterations, adaptive=False, report_every=10)  # fmt: skip
        return r.weights.numpy()

    return peer, ours


def compare_lbc(lib: ctypes.CDLL, cage: torchcage.Cage, iterations: int, repeat: int) -> dict[str, float]:
    """Seconds per ADMM iteration of both solvers on the same mesh: the minima over ``repeat``
    alternated runs of ``iterations`` and of 10 iterations, differenced (setup cancels)."""
    domain = mesh_domain(cage)
    peer, ours = lbc_calls(lib, domain, cage)
    k = 10
    fns = [lambda: peer(k), lambda: ours(k), lambda: peer(iterations), lambda: ours(iterations)]
    cpu, wall, outs = alternate(fns, repeat)
    per = [(cpu[i + 2] - cpu[i]) / (iterations - k) for i in (0, 1)]
    per_wall = [(wall[i + 2] - wall[i]) / (iterations - k) for i in (0, 1)]
    return {"peer": per[0], "torchcage": per[1], "peer_wall": per_wall[0], "torchcage_wall": per_wall[1],
            "diff": float(np.abs(outs[2] - outs[3]).max()), "mesh": domain.vertices.shape[0]}  # fmt: skip


def _s(t: float) -> str:
    if t < 0.1:
        return f"{t * 1e3:.2f} ms"
    return f"{t:.3f} s" if t < 10 else f"{t:.1f} s"


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_data_argument(ap)
    ap.add_argument("--models", nargs="+", default=["FireHydrant", "Beast"], help="models of the QMVC data set")
    ap.add_argument("--methods", nargs="+", default=list(GOALS), choices=list(GOALS), help="methods to compare")
    ap.add_argument("--repeat", type=int, default=5, help="alternated runs per method (minimum taken)")
    ap.add_argument("--lbc-models", nargs="+", default=LBC_MODELS, help="2D cages of <data>/lbc2d for LBC")
    ap.add_argument("--lbc-iterations", type=int, default=1000, help="ADMM iterations per LBC run")
    args = ap.parse_args(argv)
    if args.repeat < 1:
        ap.error(f"--repeat must be at least 1, got {args.repeat}")
    if args.lbc_iterations <= 10:
        ap.error(f"--lbc-iterations must be above 10, got {args.lbc_iterations}")

    build_dir = Path(tempfile.mkdtemp(prefix="torchcage-peers-"))
    libs: list[tuple[Peer, ctypes.CDLL]] = []
    for peer in PEERS:
        try:
            libs.append((peer, build_peer(peer, build_dir)))
            print(f"{peer.name}: built from {os.environ[peer.env]} ({peer.env})")
        except PeerUnavailableError as e:
            print(f"skipping {peer.name}: {e}")
    if not libs:
        print("no peer available: nothing to compare")
        return 0

    root = qmvc_root(args.data) if any(m != "lbc" for m in args.methods) else Path(args.data) / "qmvc"
    torch.set_num_threads(1)  # the native kernels take their thread count from torch
    kernel = _native.variant() or f"none ({_native.failure_reason()}): torch kernels"
    omp = os.environ.get("OMP_NUM_THREADS", "unset")
    print(f"torchcage {torchcage.__version__}, native library: {kernel}; torch threads {torch.get_num_threads()}; "
          f"OMP_NUM_THREADS={omp}; load average {os.getloadavg()[0]:.2f}")  # fmt: skip
    rows, notes = [], []
    for model in args.models if any(m != "lbc" for m in args.methods) else []:
        loaded = load_model(args.data, model)
        if loaded is None:
            print(f"skipping {model}: not in {root}")
            continue
        x, cage = loaded
        tri = cage.triangulated()
        for peer, lib in libs:
            for method in (m for m in args.methods if m in peer.methods and m != "lbc"):
                r = compare(lib, method, x, cage, args.repeat)
                nq, nt = cage.quads.shape[0], cage.triangles.shape[0]
                quads = method in ("qmvc", "qgc")
                faces = f"{nq} quads + {nt} triangles" if quads else f"{tri.triangles.shape[0]} triangles"
                goal = GOALS[method]
                if "torchcage_qmvc" in r:
                    goal += f" (now {r['torchcage'] / r['torchcage_qmvc']:.1f}x)"
                ratio, wall = r["peer"] / r["torchcage"], r["peer_wall"] / r["torchcage_wall"]
                times = (_s(r["peer"]), _s(r["torchcage"]), f"{ratio:.1f}x", f"{wall:.1f}x")
                rows.append((f"{model} ({x.shape[0]:,} pts)", f"{LABELS[method]}, {faces}", *times, goal,
                             f"{r['diff']:.1e}"))  # fmt: skip
                if "peer_err" in r:
                    notes.append(f"{model} {LABELS[method]}: largest error to the exact coordinates (tol=1e-10): "
                                 f"authors' code {r['peer_err']:.1e}, torchcage {r['torchcage_err']:.1e}")  # fmt: skip
                print(f"  {model} {method}: done (load average {os.getloadavg()[0]:.2f})", flush=True)
    lbc_libs = [lib for peer, lib in libs if "lbc" in peer.methods and "lbc" in args.methods]
    for model in args.lbc_models if lbc_libs else []:
        polygon = load_polygon(args.data, model)
        if polygon is None:
            print(f"skipping LBC on {model}: not in {Path(args.data) / 'lbc2d'}")
            continue
        r = compare_lbc(lbc_libs[0], polygon, args.lbc_iterations, args.repeat)
        ratio, wall = r["peer"] / r["torchcage"], r["peer_wall"] / r["torchcage_wall"]
        rows.append((f"{model} (2D, {polygon.vertices.shape[0]} vertices)",
                     f"LBC, per iteration, {r['mesh']:,} mesh vertices", _s(r["peer"]), _s(r["torchcage"]),
                     f"{ratio:.1f}x", f"{wall:.1f}x", GOALS["lbc"], f"{r['diff']:.1e}"))  # fmt: skip
        print(f"  {model} lbc: done (load average {os.getloadavg()[0]:.2f})", flush=True)
    if lbc_libs:
        notes.append(f"LBC: seconds per ADMM iteration, (time of {args.lbc_iterations} - time of 10 iterations) / "
                     f"{args.lbc_iterations - 10}; same mesh, quadratic weights, penalty 10, relaxation 1.65, "
                     "tolerances 0; neither solve has converged at that penalty, so the two results differ "
                     "(max abs. diff) by how far each is from the optimum")  # fmt: skip
    heads = ("model", "method", "authors' code", "torchcage", "ratio", "wall ratio", "goal", "max abs. diff")
    print()
    print("| " + " | ".join(heads) + " |")
    print("|" + "---|" * len(heads))
    last = None
    for row in rows:
        print("| " + " | ".join((row[0] if row[0] != last else "", *row[1:])) + " |")
        last = row[0]
    for note in notes:
        print(note)
    print(f"\nminimum of {args.repeat} alternated runs, CPU time, one thread; load average at the end "
          f"{os.getloadavg()[0]:.2f}")  # fmt: skip
    shutil.rmtree(build_dir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
