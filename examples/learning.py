"""Learning with cages, the Neural Cages pattern: fit, for a batch of shapes, both a source cage
(around each shape) and its deformation so that the cage-deformed shapes match their targets.

Four source shapes (ellipsoids of different proportions), each with a target (the source bent and
twisted). The source cages start as one icosphere template (42 vertices, 80 triangles) around
every shape; per-shape offsets of the source cage and of the deformed cage are the learnable
parameters (a network predicting them would slot in here). Every step recomputes the mean value
coordinates of the points with respect to the current source cages (``torchcage.deform``, batched
over the shapes, differentiable with respect to both cages), deforms, and takes an Adam step on
the squared distance to the targets plus a small pull of the source cage towards the template.

Writes ``learning.png`` (top: sources in their learned source cages; bottom: the deformed shapes
in their deformed cages over the targets, grey) into the output folder.

Usage: ``python examples/learning.py [out_dir] [--steps 150]``
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

import torchcage
from torchcage.testing import icosphere
from torchcage.viz import Panel, render_panels


def shapes(B: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Source points ``(B, N, 3)`` (ellipsoid meshes), targets ``(B, N, 3)`` and the mesh faces."""
    mesh = icosphere(3)  # 642 vertices, 1280 faces
    v, f = mesh.vertices, mesh.triangles
    axes = torch.tensor([[1.0, 0.5, 0.4], [0.8, 0.8, 0.4], [0.5, 1.0, 0.6], [0.9, 0.4, 0.8]], dtype=torch.float64)
    src = v[None] * axes[:B, None] * 0.7
    tgt = []
    for b in range(B):
        p = src[b].clone()
        bend = 0.6 + 0.2 * b  # bend around z, twist around x
        p[:, 1] = p[:, 1] + bend * p[:, 0] ** 2
        a = 0.8 * p[:, 0]
        y, z = p[:, 1] * torch.cos(a) - p[:, 2] * torch.sin(a), p[:, 1] * torch.sin(a) + p[:, 2] * torch.cos(a)
        tgt.append(torch.stack([p[:, 0], y, z], dim=1))
    return src, torch.stack(tgt), f


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir", nargs="?", default=".")
    ap.add_argument("--steps", type=int, default=150)
    args = ap.parse_args()
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    B = 4
    src, tgt, faces = shapes(B)
    template = icosphere(1)
    rest0 = template.vertices.expand(B, -1, -1) * 0.9  # encloses every source shape
    rest_offset = torch.zeros(B, 42, 3, dtype=torch.float64, requires_grad=True)
    deformed_offset = torch.zeros(B, 42, 3, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([rest_offset, deformed_offset], lr=0.02)
    start = time.perf_counter()
    for step in range(args.steps + 1):
        rest = rest0 + rest_offset
        cage = torchcage.Cage(rest, template.triangles, validate="topology")  # one topology, B cages
        # (mean value coordinates are defined outside the cage too: points a learnt cage leaves behind
        # are not worth a warning every step)
        moved = torchcage.deform(src, cage, rest + deformed_offset, method="mvc", outside="ignore")  # (B, N, 3)
        fit = (moved - tgt).square().sum(-1).mean()
        loss = fit + 1e-3 * rest_offset.square().sum(-1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % 50 == 0:
            print(f"step {step:4d}  fit {float(fit.detach()):.2e}  ({time.perf_counter() - start:.1f} s)", flush=True)
    cage_edges = torchcage.Cage(template.vertices, template.triangles).unique_edges()
    top, bottom = [], []
    with torch.no_grad():
        rest = rest0 + rest_offset
        final = rest + deformed_offset
        # the learnt cages, checked as in training (topology; a learnt cage may touch itself)
        learnt = torchcage.Cage(rest, template.triangles, validate="topology")
        moved = torchcage.deform(src, learnt, final, outside="ignore")
    for b in range(B):
        top.append(Panel(src[b], faces, cage_vertices=rest[b], cage_edges=cage_edges, title=f"source {b}"))
        both = torch.cat([tgt[b], moved[b]])
        f2 = torch.cat([faces, faces + src.shape[1]])
        colours = torch.cat(
            [torch.full((src.shape[1], 3), 0.75), torch.tensor([0.3, 0.55, 0.9]).expand(src.shape[1], 3)]
        )
        bottom.append(Panel(both, f2, cage_vertices=final[b], cage_edges=cage_edges, vertex_colors=colours,
                            title="deformed (blue), target (grey)"))  # fmt: skip
    img_top = render_panels(top, size=240)
    img_bottom = render_panels(bottom, size=240)
    from PIL import Image

    image = Image.new("RGB", (img_top.width, img_top.height + img_bottom.height), (255, 255, 255))
    image.paste(img_top, (0, 0))
    image.paste(img_bottom, (0, img_top.height))
    image.save(out / "learning.png")
    print(f"final fit {float((moved - tgt).square().sum(-1).mean()):.2e}; wrote {out / 'learning.png'}")


if __name__ == "__main__":
    main()
