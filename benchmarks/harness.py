"""The benchmarks' shared harness: the timer, a child process for peak memory, the data set's
model list and loader, and the table printer. Every benchmark script imports it from here.

A measurement that reports peak memory runs in a fresh child process
(:func:`run_in_child`), so that ``ru_maxrss`` belongs to it alone.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import torch

import torchcage
from torchcage._timing import best_of
from torchcage.testing import QMVC_MODELS

__all__ = ["MODELS", "add_data_argument", "best_of", "load_model", "peak_mb", "peak_since", "present_models",
           "qmvc_root", "reset_peak", "rss_mb", "run_in_child"]  # fmt: skip

#: The QMVC paper's models (the data set is not shipped: ``--data`` points at it).
MODELS = list(QMVC_MODELS)
DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def add_data_argument(ap: argparse.ArgumentParser) -> None:
    """``--data``: the shared data folder (default: ``../shared/data`` beside the checkout)."""
    ap.add_argument("--data", default=os.environ.get("TORCHCAGE_DATA", str(DEFAULT_DATA)))


def model_parser(doc: str, repeat: int) -> argparse.ArgumentParser:
    """The model benchmarks' parser: ``--models`` (default FireHydrant and Beast), ``--repeat`` and
    :func:`add_data_argument`'s ``--data``; described by the first paragraph of ``doc``."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--models", nargs="+", default=["FireHydrant", "Beast"], choices=MODELS)
    ap.add_argument("--repeat", type=int, default=repeat)
    add_data_argument(ap)
    return ap


def qmvc_root(data: str | Path) -> Path:
    """``<data>/qmvc``; exits with a message naming the folder when it is absent."""
    root = Path(data) / "qmvc"
    if not root.exists():
        raise SystemExit(f"data folder {root} not found (pass --data or set TORCHCAGE_DATA)")
    return root


def load_model(data: str | Path, model: str) -> tuple[torch.Tensor, torchcage.Cage] | None:
    """A model's mesh vertices ``(N, 3)`` float64 and its (triquad) cage, or ``None`` if absent."""
    root = Path(data) / "qmvc"
    mesh, cage_file = root / f"{model}.obj", root / f"{model}_Cage.obj"
    if not mesh.exists() or not cage_file.exists():
        return None
    return torchcage.load_mesh(mesh)[0].to(torch.float64), torchcage.load_cage(cage_file)


def present_models(data: str | Path, models: Sequence[str]) -> Iterator[tuple[str, torch.Tensor, torchcage.Cage]]:
    """``(model, points, cage)`` of each of ``models`` found in ``data`` (:func:`load_model`); for
    each absent one, a table row saying so is printed instead."""
    for model in models:
        loaded = load_model(data, model)
        if loaded is None:
            print(f"| {model} | (not in {data}) |")
            continue
        yield model, *loaded


def cpu_best(fns: Sequence[Callable[[], object]], repeat: int) -> list[float]:
    """The best CPU time of each of ``fns``, called in turn in each of ``repeat`` rounds (each
    result dropped before the next call)."""
    best = [float("inf")] * len(fns)
    for _ in range(repeat):
        for i, fn in enumerate(fns):
            t = time.process_time()
            fn()
            best[i] = min(best[i], time.process_time() - t)
    return best


def rss_mb() -> float:
    """This process's resident memory now, in MB (Linux)."""
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def peak_mb() -> float:
    """This process's peak resident memory so far, in MB (``ru_maxrss``; KiB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def reset_peak() -> float:
    """Start a peak-memory measurement: hand freed memory back to the system (glibc's
    ``malloc_trim``), reset the kernel's resident high-water mark (``/proc/self/clear_refs``) and
    return the resident memory now, in MB. :func:`peak_since` then gives the peak above it, even
    after warm-up calls whose own peak was higher (``ru_maxrss`` cannot be reset)."""
    import ctypes
    import gc

    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
    except OSError:
        pass
    return rss_mb()


def peak_since(before: float) -> float:
    """Peak resident memory (``VmHWM``) above ``before`` (from :func:`reset_peak`), in MB."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return max(0.0, int(line.split()[1]) / 1024 - before)
    return max(0.0, peak_mb() - before)


def run_in_child(script: str | Path, args: Sequence[str]) -> dict:
    """Run ``python script *args`` in a fresh process and return the JSON object that its last
    line of output holds (the script's measurement, peak memory its own)."""
    res = subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"{script} {' '.join(args)} failed:\n{res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])
