"""Small software renderer for pictures of meshes and cages (Pillow + NumPy, no display needed).

Flat-shaded triangles drawn back to front (painter's algorithm) in an orthographic view, with the
cage's edges and vertices drawn on top. Good enough for the demo and the docs; not a 3D viewer.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from PIL import Image

__all__ = ["Panel", "render_field_2d", "render_panels", "view_rotation"]


def view_rotation(azimuth: float = 35.0, elevation: float = 20.0) -> np.ndarray:
    """Rotation ``(3, 3)`` that maps world coordinates (z up) to view coordinates (x right, y up,
    z towards the viewer), for a camera at the given azimuth and elevation in degrees."""
    a, e = np.radians(azimuth), np.radians(elevation)
    # Turn z-up into y-up, then spin about the vertical and tilt.
    to_y_up = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
    ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    rx = np.array([[1, 0, 0], [0, np.cos(e), -np.sin(e)], [0, np.sin(e), np.cos(e)]])
    return rx @ ry @ to_y_up


@dataclass
class Panel:
    """One picture in a row: a triangle mesh and optionally a cage.

    Attributes:
        vertices: ``(N, 3)`` mesh vertices.
        faces: ``(F, 3)`` mesh triangles.
        cage_vertices: ``(V, 3)`` cage vertices, or ``None``.
        cage_edges: ``(E, 2)`` cage edges to draw (e.g. from quads), or ``None``.
        title: caption drawn above the panel.
        color: mesh RGB colour in ``[0, 1]``.
        vertex_colors: ``(N, 3)`` per-vertex RGB colours in ``[0, 1]`` (faces get their mean),
            overriding ``color``; or ``None``.
    """

    vertices: torch.Tensor | np.ndarray
    faces: torch.Tensor | np.ndarray
    cage_vertices: torch.Tensor | np.ndarray | None = None
    cage_edges: torch.Tensor | np.ndarray | None = None
    title: str = ""
    color: Sequence[float] = field(default=(0.45, 0.62, 0.85))
    vertex_colors: torch.Tensor | np.ndarray | None = None


def _np(x: torch.Tensor | np.ndarray) -> np.ndarray:
    return x.detach().cpu().double().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, dtype=np.float64)


def render_panels(
    panels: Sequence[Panel],
    *,
    size: int = 480,
    azimuth: float = 35.0,
    elevation: float = 20.0,
    background: tuple[int, int, int] = (255, 255, 255),
    legend: Sequence[tuple[str, Sequence[float]]] = (),
) -> Image.Image:
    """Render panels side by side into one image, all with the same view and scale.

    Args:
        panels: the pictures, left to right.
        size: height (and width) of each panel in pixels.
        azimuth: camera azimuth in degrees.
        elevation: camera elevation in degrees.
        background: RGB background colour.
        legend: ``(label, rgb in [0, 1])`` entries drawn as swatches along the bottom edge.

    Returns:
        A ``PIL.Image.Image``; save it with ``.save("out.png")``.

    Examples:
        >>> import torchcage
        >>> from torchcage.viz import Panel, render_panels
        >>> v, f = torchcage.load_mesh(torchcage.data.path("bar.obj"))
        >>> render_panels([Panel(v, f), Panel(2 * v, f)], size=64).size   # two panels, no titles
        (128, 64)
    """
    from PIL import ImageDraw

    rot = view_rotation(azimuth, elevation)
    pts = [(_np(p.vertices) @ rot.T) for p in panels]
    cages = [None if p.cage_vertices is None else _np(p.cage_vertices) @ rot.T for p in panels]
    allxy = np.concatenate([q[:, :2] for q in pts] + [c[:, :2] for c in cages if c is not None])
    lo, hi = allxy.min(0), allxy.max(0)
    centre_y = (lo[1] + hi[1]) / 2
    span = max(float((hi - lo).max()), 1e-12)
    scale = 0.82 * size / span
    font = _font(max(11, size // 28))
    line = font.size + 10 if hasattr(font, "size") else 24
    top = line if any(p.title for p in panels) else 0
    bottom = line if legend else 0
    image = Image.new("RGB", (size * len(panels), size + top + bottom), background)
    draw = ImageDraw.Draw(image)
    light = np.array([0.3, 0.5, 1.0])
    light /= np.linalg.norm(light)
    for k, (panel, p, c) in enumerate(zip(panels, pts, cages, strict=True)):
        own = p if c is None else np.concatenate([p, c])
        cx = (own[:, 0].min() + own[:, 0].max()) / 2

        def to_px(q: np.ndarray, k: int = k, cx: float = cx) -> np.ndarray:
            return np.stack(
                [(q[:, 0] - cx) * scale + size * (k + 0.5), top + size / 2 - (q[:, 1] - centre_y) * scale], 1
            )

        f = _np(panel.faces).astype(np.int64)
        tri = p[f]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        shade = 0.25 + 0.75 * np.abs(n @ light)
        order = np.argsort(tri[:, :, 2].mean(1))  # far to near
        px = to_px(p)
        if panel.vertex_colors is not None:
            base = _np(panel.vertex_colors)[f].mean(axis=1)  # (F, 3)
        else:
            base = np.broadcast_to(np.asarray(panel.color, dtype=np.float64), (f.shape[0], 3))
        for t in order:
            col = tuple(int(255 * min(1.0, s)) for s in base[t] * shade[t])
            draw.polygon([tuple(px[i]) for i in f[t]], fill=col)
        if c is not None:
            cpx = to_px(c)
            if panel.cage_edges is not None:
                for a, b in _np(panel.cage_edges).astype(np.int64):
                    draw.line([tuple(cpx[a]), tuple(cpx[b])], fill=_rgb(CAGE_EDGE_COLOR), width=max(2, size // 240))
            r = max(3.5, size / 140)
            for x, y in cpx:
                draw.ellipse([x - r, y - r, x + r, y + r], fill=_rgb(CAGE_VERTEX_COLOR))
        if panel.title:
            draw.text((size * k + 10, 5), panel.title, fill=(30, 30, 30), font=font)
    x = 10
    for label, rgb in legend:
        y = size + top + 4
        sw = line - 12
        draw.rectangle([x, y, x + sw, y + sw], fill=tuple(int(255 * c) for c in rgb), outline=(60, 60, 60))
        draw.text((x + sw + 6, y - 1), label, fill=(30, 30, 30), font=font)
        x += sw + 20 + int(draw.textlength(label, font=font))
    return image


#: Colours of the pictures: the cage's edges and vertices, the default mesh.
CAGE_EDGE_COLOR, CAGE_VERTEX_COLOR, MESH_COLOR = (0.9, 0.47, 0.08), (0.78, 0.24, 0.04), (0.45, 0.62, 0.85)


def _rgb(c: Sequence[float]) -> tuple[int, ...]:
    return tuple(round(255 * v) for v in c)


def _font(px: int):
    """A scalable font of ``px`` pixels (Pillow >= 10.1 ships one), else Pillow's small bitmap font."""
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=px)
    except TypeError:  # older Pillow: fixed-size bitmap font
        return ImageFont.load_default()


def render_field_2d(
    values: torch.Tensor | np.ndarray,
    cage: Any,
    lo: Sequence[float],
    hi: Sequence[float],
    *,
    mask: torch.Tensor | np.ndarray | None = None,
    vertex: int | None = None,
    title: str = "",
) -> Image.Image:
    """Picture of a scalar field sampled on a square grid over a 2D cage: red positive, blue
    negative, white zero, iso-bands every 0.1, the polygon drawn over it.

    Args:
        values: ``(S * S,)`` or ``(S, S)`` samples, rows from top (``y = hi[1]``) to bottom, columns
            from ``x = lo[0]`` to ``hi[0]``.
        cage: the 2D :class:`torchcage.Cage` to draw.
        lo: lower corner ``(x, y)`` of the grid.
        hi: upper corner ``(x, y)`` of the grid.
        mask: ``(S * S,)`` bool, samples to show (others are grey), or ``None`` for all.
        vertex: a cage vertex to circle, or ``None``.
        title: caption in the top-left corner.

    Returns:
        An ``S x S`` ``PIL.Image.Image``.

    Examples:
        >>> import torch, torchcage
        >>> cage = torchcage.load_cage(torchcage.data.path("blob2d.obj"))
        >>> render_field_2d(torch.zeros(16, 16), cage, (-1.5, -1.5), (1.5, 1.5), vertex=0).size
        (16, 16)
    """
    from PIL import ImageDraw

    w = _np(torch.as_tensor(values)).reshape(-1)
    size = round(w.shape[0] ** 0.5)
    t = np.clip(w, -1, 1)
    rgb = np.stack([1 - np.clip(-t, 0, 1), 1 - np.abs(t), 1 - np.clip(t, 0, 1)], -1)
    rgb = rgb * np.where(np.floor(w * 10) % 2 == 0, 1.0, 0.93)[:, None]  # iso-bands every 0.1
    if mask is not None:
        rgb[~np.asarray(torch.as_tensor(mask).reshape(-1).cpu().numpy(), dtype=bool)] = 0.85
    image = Image.fromarray((255 * rgb.reshape(size, size, 3)).astype(np.uint8))
    draw = ImageDraw.Draw(image)
    v = _np(cage.vertices)

    def px(p: np.ndarray) -> tuple[float, float]:
        return (
            float((p[0] - lo[0]) / (hi[0] - lo[0]) * (size - 1)),
            float((hi[1] - p[1]) / (hi[1] - lo[1]) * (size - 1)),
        )

    for a, b in cage.edges.tolist():
        draw.line([px(v[a]), px(v[b])], fill=(20, 20, 20), width=2)
    if vertex is not None:
        x, y = px(v[vertex])
        draw.ellipse([x - 6, y - 6, x + 6, y + 6], outline=(0, 0, 0), width=3)
    if title:
        draw.text((6, 4), title, fill=(0, 0, 0))
    return image
