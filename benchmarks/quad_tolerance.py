"""Error against cost of the quad coordinates: the paper's Riemann sums (n = 1..32) and the
error-controlled quadrature (tol = 1e-4..1e-10), on the eight cages of the QMVC data set.

For every model, up to ``--points`` of its mesh vertices (Cactus: points sampled inside its cage);
QMVC and QGC (native kernels, float64) at each setting; the error is the largest coordinate error
against ``tol = 1e-12`` (QGC: of ``phi`` and of ``psi`` relative to the cage's size), which the tests
check against an independent reference (tests/test_quad_tolerance.py). Prints one table per family
(time summed over the models, worst error over them) and, with ``--plot``, writes the figure of
docs/qmvc.md (``docs/images/quad_tolerance.png``; needs matplotlib).

Usage: ``python benchmarks/quad_tolerance.py [--data ../shared/data] [--points 3000] [--plot]``
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import add_data_argument, load_model, qmvc_root

from torchcage import functional as F
from torchcage.testing import QMVC_MODELS

SETTINGS = [*({"n": n} for n in (1, 2, 4, 8, 16, 32)), *({"tol": t} for t in (1e-4, 1e-6, 1e-8, 1e-10))]


def _timed(f: Callable[[], Any]) -> tuple[Any, float]:
    t = time.perf_counter()
    out = f()
    return out, time.perf_counter() - t


def measure(data: str, points: int) -> dict[str, list[tuple[str, float, float]]]:
    """Per family (``"qmvc"``, ``"qgc"``): ``(setting, seconds, worst error)`` per setting."""
    rows: dict[str, dict[str, list[float]]] = {"qmvc": {}, "qgc": {}}
    for model in QMVC_MODELS:
        loaded = load_model(data, model)
        if loaded is None:
            continue
        x, cage = loaded
        x = x[torch.randperm(x.shape[0], generator=torch.Generator().manual_seed(0))[:points]]
        F.quad_mean_value_coordinates(x[:4], cage)  # (the native library's build outside the timings)
        ref_m = F.quad_mean_value_coordinates(x, cage, tol=1e-12)
        ref_g = F.quad_green_coordinates(x, cage, tol=1e-12)
        for kw in SETTINGS:
            key = ", ".join(f"{k} = {v:g}" for k, v in kw.items())
            w, t = _timed(lambda kw=kw, x=x, cage=cage: F.quad_mean_value_coordinates(x, cage, **kw))
            err = float((w - ref_m).abs().max())
            acc = rows["qmvc"].setdefault(key, [0.0, 0.0])
            acc[0], acc[1] = acc[0] + t, max(acc[1], err)
            kw_g = kw if "tol" in kw else {"n": min(kw["n"], 16)}  # (QGC's cost grows like n^2: up to 16)
            (phi, psi), t = _timed(lambda kw=kw_g, x=x, cage=cage: F.quad_green_coordinates(x, cage, **kw))
            err = max(float((phi - ref_g[0]).abs().max()), float((psi - ref_g[1]).abs().max()) / cage.scale)
            key_g = ", ".join(f"{k} = {v:g}" for k, v in kw_g.items())
            acc = rows["qgc"].setdefault(key_g, [0.0, 0.0])
            if key_g == key:
                acc[0], acc[1] = acc[0] + t, max(acc[1], err)
    return {fam: [(k, v[0], v[1]) for k, v in r.items()] for fam, r in rows.items()}


def plot(results: dict[str, list[tuple[str, float, float]]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, (fam, rows) in zip(axes, results.items(), strict=True):
        for kind, marker in (("n", "o"), ("tol", "s")):
            pts = [(t, e, k) for k, t, e in rows if k.startswith(kind)]
            ax.loglog([p[0] for p in pts], [max(p[1], 1e-16) for p in pts], marker=marker,
                      label="Riemann sum (n)" if kind == "n" else "quadrature (tol)")  # fmt: skip
            for t, e, k in pts:
                label = k.split(" = ")[1]
                ax.annotate(label, (t, max(e, 1e-16)), textcoords="offset points", xytext=(4, 4), fontsize=7)
        ax.set_title(f"{fam.upper()}: eight data-set cages")
        ax.set_xlabel("seconds (native kernel, 2 cores)")
        ax.set_ylabel("largest coordinate error")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_data_argument(ap)
    ap.add_argument("--points", type=int, default=3000, help="points per model")
    ap.add_argument("--plot", action="store_true", help="write docs/images/quad_tolerance.png")
    args = ap.parse_args()
    qmvc_root(args.data)
    results = measure(args.data, args.points)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, float64, native kernels, "
          f"{args.points} points per model")  # fmt: skip
    for fam, rows in results.items():
        print(f"\n{fam.upper():<6} {'setting':<12} {'seconds':>8} {'max error':>10}")
        for key, t, err in rows:
            print(f"{'':<6} {key:<12} {t:>8.2f} {err:>10.1e}")
    if args.plot:
        out = Path(__file__).resolve().parents[1] / "docs" / "images" / "quad_tolerance.png"
        plot(results, out)
        print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
