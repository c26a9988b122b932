#!/usr/bin/env bash
# The install-time build (issue 22, item 1): build a wheel, install it into a fresh venv, and run
# torchcage there with no C compiler on PATH. The native kernels must come from the wheel (no
# compilation at first use); the first call's time is printed.
set -euo pipefail
cd "$(dirname "$0")/.."
repo="$(pwd)"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

python -m pip install --quiet build
python -m build --wheel --outdir "$work/dist" "$repo" > "$work/build.log" 2>&1 || { tail -50 "$work/build.log"; exit 1; }
wheel="$(ls "$work"/dist/torchcage-*.whl)"
echo "built $(basename "$wheel")"
python -c "import sys, zipfile; names = [n for n in zipfile.ZipFile(sys.argv[1]).namelist() if '_kernels' in n]; print(*names, sep='\n'); sys.exit(0 if names else 'the wheel holds no native library')" "$wheel"

python3 -m venv "$work/venv"
"$work/venv/bin/pip" install --quiet "torch==2.13.0"
"$work/venv/bin/pip" install --quiet "$wheel"

# No compiler anywhere: PATH is the venv's bin folder only, CC unset; run outside the checkout.
cd "$work"
env -i HOME="$work" PATH="$work/venv/bin" TORCHCAGE_CACHE="$work/cache" "$work/venv/bin/python" - <<'PY'
import shutil
import time

import torch

import torchcage
from torchcage.backends import native as _native
from torchcage import functional as F

assert shutil.which("cc") is None and shutil.which("gcc") is None and _native._compiler() is None, "a compiler is visible"
cage = torchcage.load_cage(torchcage.data.path("bar_cage.obj")).triangulated()
x = (torch.rand(10_000, 3, dtype=torch.float64) - 0.5) * torch.tensor([1.0, 1.0, 3.0], dtype=torch.float64)
start = time.perf_counter()
w = F.mean_value_coordinates(x, cage)
first = time.perf_counter() - start
assert _native.library() is not None, _native.failure_reason()
assert _native.variant().startswith("prebuilt"), _native.variant()
assert torch.allclose(w @ cage.vertices, x, atol=1e-10)
print(f"native kernels: {_native.variant()}; first call (10,000 points, library load included): {first * 1e3:.0f} ms")
PY
