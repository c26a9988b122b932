"""Benchmark of the cage editor (``torchcage view``): where the time of one pose goes.

For the bundled bar (2,562 mesh vertices, 16 cage vertices) and larger meshes (the bar and, when
the data set is found, Beast with its 152-vertex cage, each refined by midpoint subdivision to
about 10^5 vertices), with mean value coordinates:

- the coordinates, once (module construction);
- one pose: the product alone (the floor, the baseline in the same run), ``POST /api/pose`` with a
  JSON answer (what scripts get) and with the raw float32 answer (what the page asks for), and the
  size of each answer; ``GET /api/scene`` (the page's first load);
- with ``--browser`` (headless Chromium): the page's own round trip for a drag (request, answer,
  new mesh), the part of it spent taking the new mesh (copy, vertex normals), and the time from a
  drag's first event to the updated mesh;
- the start of ``torchcage view`` on the bundled data to a served page, cold and warm.

Usage: ``python benchmarks/viewer.py [--data ../shared/data] [--browser] [--repeat 5]``
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import add_data_argument, qmvc_root

import torchcage
from torchcage._timing import best_of


def subdivide(v: torch.Tensor, f: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """One midpoint subdivision: every triangle into four, ``V + E`` vertices."""
    e = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).sort(dim=1).values
    edges, inverse = torch.unique(e, dim=0, return_inverse=True)
    mid = v.shape[0] + inverse.view(3, -1)  # (3, F): midpoints of edges 01, 12, 20
    vertices = torch.cat([v, v[edges].mean(dim=1)])
    a, b, c = f.unbind(1)
    m01, m12, m20 = mid
    faces = torch.cat(
        [
            torch.stack([a, m01, m20], 1),
            torch.stack([m01, b, m12], 1),
            torch.stack([m20, m12, c], 1),
            torch.stack([m01, m12, m20], 1),
        ]
    )
    return vertices, faces


def refined(v: torch.Tensor, f: torch.Tensor, target: int) -> tuple[torch.Tensor, torch.Tensor]:
    while v.shape[0] < 0.6 * target:
        v, f = subdivide(v, f)
    return v, f


def post(url: str, body: bytes, headers: dict[str, str]) -> bytes:
    with urllib.request.urlopen(urllib.request.Request(url, data=body, headers=headers), timeout=120) as r:
        return r.read()


def get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=120) as r:
        return r.read()


def cases(data: str | None) -> list[tuple[str, torchcage.Cage, torch.Tensor, torch.Tensor]]:
    d = torchcage.data
    cage = torchcage.load_cage(d.path("bar_cage.obj"))
    v, f = torchcage.load_mesh(d.path("bar.obj"))
    out = [("bar", cage, v, f)]
    out.append(("bar, subdivided", cage, *refined(v, f, 100_000)))
    try:
        root = qmvc_root(data)
        beast = torchcage.load_cage(root / "Beast_Cage.obj")
        bv, bf = torchcage.load_mesh(root / "Beast.obj")
        out.append(("Beast, subdivided", beast, *refined(bv, bf, 100_000)))
    except (FileNotFoundError, OSError, SystemExit):
        print("(the QMVC data set is not here: the Beast rows are left out)")
    return out


def measure(name, cage, v, f, repeat: int, browser) -> dict[str, str]:
    t = time.perf_counter()
    viewer = torchcage.view((v, f), cage)
    viewer.wait()
    coords = time.perf_counter() - t
    g = torch.Generator().manual_seed(0)
    pose = cage.vertices + 0.02 * cage.scale * torch.randn(cage.vertices.shape, generator=g, dtype=torch.float64)
    module = viewer.session._module
    _, product, _ = best_of(lambda: module(pose), repeat, warmup=1)
    body = json.dumps({"vertices": pose.tolist()}).encode()
    head = viewer.headers  # the session's token and the JSON content type
    _, rt_json, answer_json = best_of(lambda: post(viewer.url + "api/pose", body, head), repeat, warmup=1)
    _, rt_f32, answer_f32 = best_of(lambda: post(viewer.url + "api/pose?format=f32", body, head), repeat, warmup=1)
    _, scene, answer_scene = best_of(lambda: get(viewer.url + "api/scene"), 2)
    row = {
        "mesh": name,
        "N": f"{v.shape[0]:,}",
        "V": str(cage.num_vertices),
        "coords s": f"{coords:.2f}",
        "product ms": f"{1e3 * product:.1f}",
        "pose JSON ms": f"{1e3 * rt_json:.1f}",
        "JSON MB": f"{len(answer_json) / 1e6:.2f}",
        "pose f32 ms": f"{1e3 * rt_f32:.1f}",
        "f32 MB": f"{len(answer_f32) / 1e6:.2f}",
        "scene s": f"{scene:.2f} ({len(answer_scene) / 1e6:.0f} MB)",
    }
    if browser is not None:
        browser.open(viewer.url, "window.torchcage && window.torchcage.ready", timeout=300)
        browser.evaluate("window.torchcage.idle()")
        trips, drags, updates = [], [], []
        for k in range(repeat):
            t = time.perf_counter()
            browser.evaluate(f"window.torchcage.dragVertex({k % cage.num_vertices}, 12, -8, 1)")
            drags.append(time.perf_counter() - t)
            trips.append(browser.evaluate("window.torchcage.roundTrip"))
            updates.append(browser.evaluate("window.torchcage.meshUpdate"))
        row["page round trip ms"] = f"{min(trips):.0f}"
        row["of which mesh update ms"] = f"{min(updates):.0f}"
        row["drag to mesh ms"] = f"{1e3 * min(drags):.0f}"
    viewer.close()
    return row


def startup() -> list[float]:
    """Seconds from launching ``torchcage view`` to a served page, and to ready coordinates."""
    t = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "torchcage.cli", "view", "--no-browser", "--port", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        line = proc.stdout.readline()
        url = line[line.index("http://") :].split()[0]
        get(url)
        page = time.perf_counter() - t
        while json.loads(get(url + "api/status"))["state"] == "computing":
            time.sleep(0.01)
        return [page, time.perf_counter() - t]
    finally:
        proc.terminate()
        proc.wait(10)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_data_argument(parser)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--browser", action="store_true", help="also time the page in headless Chromium")
    args = parser.parse_args()
    browser = None
    if args.browser:
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
        from browser import Browser, find_chromium

        browser = Browser(find_chromium() or "chromium")
    print(f"torchcage view, mean value coordinates, {torch.get_num_threads()} threads; best of {args.repeat}")
    rows = [measure(*case, args.repeat, browser) for case in cases(args.data)]
    if browser is not None:
        browser.close()
    keys = list(rows[0])
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for row in rows:
        print("| " + " | ".join(row.get(k, "") for k in keys) + " |")
    runs = [startup() for _ in range(3)]
    print("\nstart of `torchcage view` (bundled bar): served page / coordinates ready, seconds")
    for k, (page, ready) in enumerate(runs):
        print(f"  run {k + 1} ({'cold' if k == 0 else 'warm'}): {page:.2f} / {ready:.2f}")


if __name__ == "__main__":
    main()
