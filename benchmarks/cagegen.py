"""Benchmark of the cage maker on the data set of the QMVC paper.

For each model, the hand-made cage of the data set (the baseline, measured in the same run) and
cages made by ``torchcage.make_cage`` at the issue's vertex targets, both kinds. Prints, per cage:
vertices, quad fraction, invalid quads, self-intersections, mesh vertices outside, the least
clearance, the mean and max distance from the cage (vertices and face centroids) to the mesh (all
distances as fractions of the mesh's bounding-box diagonal) and the time to make it.

First, the distance kernel the maker measures with (``torchcage.geometry.nearest_triangle``):
native against torch, on a quarter of FireHydrant's vertices and its hand-made cage's patch grids.

Usage: ``python benchmarks/cagegen.py [--data ../shared/data] [--models FireHydrant Ogre Beast ManHead]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import add_data_argument, qmvc_root

import torchcage
from torchcage.cagegen import measure_cage

#: The issue's vertex targets per model.
TARGETS = {"FireHydrant": 60, "Ogre": 150, "Beast": 200, "ManHead": 40}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_data_argument(ap)
    ap.add_argument("--models", nargs="*", default=list(TARGETS))
    ap.add_argument("--kinds", nargs="*", default=["triangle", "quad"])
    args = ap.parse_args()
    root = qmvc_root(args.data)
    _distance_kernels(root)
    head = f"{'model':12} {'cage':10} {'V':>5} {'quads':>6} {'inval':>5} {'cross':>5} {'out':>5} "
    head += f"{'clear':>7} {'mean':>7} {'max':>7} {'time s':>7}"
    print(head)
    print("-" * len(head))
    for model in args.models:
        v, f = torchcage.load_mesh(root / f"{model}.obj")
        rows = [("hand-made", torchcage.load_cage(root / f"{model}_Cage.obj"), 0.0)]
        for kind in args.kinds:
            t = time.perf_counter()
            cage = torchcage.make_cage(v, f, target_vertices=TARGETS.get(model, 150), kind=kind)
            rows.append((kind, cage, time.perf_counter() - t))
        for name, cage, seconds in rows:
            r = measure_cage(cage, v, f)
            print(
                f"{model:12} {name:10} {r.vertices:5d} {r.quad_fraction:6.2f} {r.invalid_quads:5d} "
                f"{r.self_intersections:5d} {r.outside:5d} {r.min_clearance:7.4f} {r.mean_distance:7.4f} "
                f"{r.max_distance:7.4f} {seconds:7.1f}"
            )


def _distance_kernels(root: Path) -> None:
    """Time ``nearest_triangle`` native vs torch on FireHydrant's vertices against its hand-made
    cage's measured surfaces (the q0-q2 split, then the patch grids)."""
    import torch

    from torchcage.backends import native as _native
    from torchcage.cagegen.checks import measured_surfaces
    from torchcage.geometry import nearest_triangle

    v, _ = torchcage.load_mesh(root / "FireHydrant.obj")
    cage = torchcage.load_cage(root / "FireHydrant_Cage.obj")
    x = v.to(torch.float64)[::4]  # (a quarter of the vertices: the torch kernel takes long)
    print(f"{'distances':28} {'pairs':>10} {'torch s':>8} {'native s':>8} {'speed-up':>8} {'max diff':>9}")
    surfaces = measured_surfaces(cage.vertices, cage.triangles, cage.quads)
    for name, (p, t, slack) in zip(("q0-q2 split", "patch grids"), surfaces, strict=True):
        times, out = [], []
        for backend in ("torch", "native") if _native.available() else ("torch",):
            start = time.perf_counter()
            out.append(nearest_triangle(x, p, t, slack=slack, backend=backend)[0])
            times.append(time.perf_counter() - start)
        if len(times) == 1:
            times.append(float("nan"))
            out.append(out[0])
        print(
            f"{name:28} {x.shape[0] * t.shape[0]:10,d} {times[0]:8.2f} {times[1]:8.3f} {times[0] / times[1]:7.0f}x "
            f"{float((out[0] - out[1]).abs().max()):9.1e}"
        )
    print()


if __name__ == "__main__":
    main()
