"""Reading and writing cages and meshes.

Cages need their quads kept as quads, which trimesh does not do (it triangulates on load), so OBJ
files are read by a small polygon-preserving reader here. Meshes in other formats go through
trimesh, imported lazily (``pip install torchcage[mesh]``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchcage.cage import Cage
from torchcage.errors import CageError

__all__ = ["load_cage", "load_mesh", "read_obj", "save_cage", "save_mesh"]

PathLike = str | os.PathLike


def read_obj(path: PathLike) -> tuple[np.ndarray, list[list[int]], list[list[int]]]:
    """Read the vertices, polygon faces and polylines of an OBJ file, keeping polygons intact.

    Understands ``v x y z [w]``, ``f`` with ``i``, ``i/t``, ``i//n`` and ``i/t/n`` corners, negative
    (relative) indices, ``l`` polylines, comments and blank lines; other statements are ignored.

    Args:
        path: file to read.

    Returns:
        ``(vertices (V, 3) float64, faces, lines)``: faces and polylines as lists of 0-based
        index lists.

    Raises:
        CageError: a malformed ``v``, ``f`` or ``l`` line, or an index out of range (with the line number).
    """
    vertices: list[list[float]] = []
    faces: list[list[int]] = []
    lines: list[list[int]] = []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, raw in enumerate(fh, 1):
            parts = raw.split("#", 1)[0].split()
            if not parts:
                continue
            tag = parts[0]
            try:
                if tag == "v":
                    if len(parts) < 4:
                        raise ValueError("a vertex needs three coordinates")
                    vertices.append([float(parts[1]), float(parts[2]), float(parts[3])])
                elif tag in ("f", "l"):
                    idx = []
                    for tok in parts[1:]:
                        i = int(tok.split("/", 1)[0])
                        if i == 0:
                            raise ValueError("OBJ indices start at 1")
                        idx.append(i - 1 if i > 0 else len(vertices) + i)
                    if any(i < 0 or i >= len(vertices) for i in idx):
                        raise ValueError(f"index out of range (only {len(vertices)} vertices defined so far)")
                    (faces if tag == "f" else lines).append(idx)
            except ValueError as err:
                raise CageError(f"{path}:{lineno}: cannot read {raw.strip()!r}: {err}") from None
    return np.asarray(vertices, dtype=np.float64).reshape(-1, 3), faces, lines


def load_cage(
    path: PathLike,
    *,
    dim: int | None = None,
    dtype: torch.dtype = torch.float64,
    check_intersections: bool | None = None,
) -> Cage:
    """Load a cage from an OBJ file, keeping quads as quads.

    A file with ``f`` faces is a 3D cage (triangles and quads). A file without faces is a 2D
    polygon: its ``v`` lines, in order, are the polygon's vertices (z must be 0; ``l`` lines are
    ignored). ``dim`` forces either reading.

    Args:
        path: an ``.obj`` file.
        dim: 2 or 3, or ``None`` to decide from the file's content.
        dtype: vertex dtype.
        check_intersections: refuse a self-intersecting cage (see :class:`~torchcage.Cage`; by
            default cages of up to 2,048 faces are tested); pass ``False`` to read a deformed
            pose, which may fold through itself (the data set's deformed Beast cage does).

    Returns:
        A validated :class:`~torchcage.Cage`.

    Raises:
        CageError: a face with more than four corners, a 2D polygon with non-zero z, or any
            validation error of :class:`~torchcage.Cage`.

    Examples:
        >>> import torchcage
        >>> cage = torchcage.load_cage(torchcage.data.path("bar_cage.obj"))
        >>> cage.quads.shape
        torch.Size([14, 4])
    """
    v, faces, _ = read_obj(path)
    if v.shape[0] == 0:
        raise CageError(f"{path}: the file holds no vertices ('v x y z' lines); is it an OBJ cage?")
    if dim is None:
        dim = 3 if faces else 2
    if dim == 2:
        if np.abs(v[:, 2]).max(initial=0.0) > 0:
            raise CageError(f"{path}: a 2D cage needs z = 0 on every vertex; pass dim=3 for a surface cage")
        return Cage(torch.as_tensor(v[:, :2], dtype=dtype), check_intersections=check_intersections)
    if dim != 3:
        raise CageError(f"dim must be 2 or 3, got {dim}")
    big = [k for k, f in enumerate(faces) if len(f) > 4]
    if big:
        raise CageError(f"{path}: faces {big[:10]} have more than four corners; cages support triangles and quads only")
    return Cage(torch.as_tensor(v, dtype=dtype), faces, check_intersections=check_intersections)


def _format_rows(prefix: str, rows: np.ndarray, fmt: str) -> str:
    if rows.size == 0:
        return ""
    line = prefix + " " + " ".join([fmt] * rows.shape[1]) + "\n"
    return "".join(line % tuple(r) for r in rows.tolist())


def save_cage(path: PathLike, cage: Cage, vertices: torch.Tensor | None = None) -> None:
    """Write a cage as OBJ, quads kept as quads (2D cages as a polyline with z = 0).

    Args:
        path: output ``.obj`` file.
        cage: the cage whose faces are written.
        vertices: optional ``(V, D)`` positions to write instead of ``cage.vertices`` (a deformed pose).
    """
    if cage.is_batched and vertices is None:
        raise CageError(
            f"a batch of cages (batch shape {tuple(cage.batch_shape)}) is written one element at a time: "
            "save_cage(path, cage[b])"
        )
    v = (cage.vertices if vertices is None else vertices).detach().cpu().to(torch.float64).numpy()
    if v.shape != tuple(cage.vertices.shape[-2:]):
        raise CageError(f"vertices must have shape {tuple(cage.vertices.shape[-2:])}, got {v.shape}")
    if cage.dim == 2:
        v = np.concatenate([v, np.zeros((v.shape[0], 1))], axis=1)
    text = _format_rows("v", v, "%.17g")
    if cage.dim == 3:
        text += _format_rows("f", cage.triangles.cpu().numpy() + 1, "%d")
        text += _format_rows("f", cage.quads.cpu().numpy() + 1, "%d")
    else:
        text += _format_rows("l", cage.edges.cpu().numpy() + 1, "%d")
    Path(path).write_text(text)


def _trimesh(action: str = "reading") -> Any:
    try:
        import trimesh
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError(f"{action} this mesh format needs trimesh: pip install 'torchcage[mesh]'") from err
    return trimesh


def load_mesh(path: PathLike, *, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """Load a triangle mesh.

    OBJ files are read directly, keeping every vertex in file order (polygons are fan-triangulated);
    other formats (PLY, STL, OFF, GLB, ...) go through trimesh without processing.

    Args:
        path: mesh file.
        dtype: vertex dtype.

    Returns:
        ``(vertices (N, 3), faces (F, 3) int64)``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: a file with no vertices or content that cannot be read (the message names it).

    Examples:
        >>> import torchcage
        >>> v, f = torchcage.load_mesh(torchcage.data.path("bar.obj"))
        >>> v.shape[1], f.shape[1]
        (3, 3)
    """
    if not Path(path).is_file():
        raise FileNotFoundError(f"no such mesh file: {path}")
    if str(path).lower().endswith(".obj"):
        v, faces, _ = read_obj(path)
        tris = [[f[0], f[k], f[k + 1]] for f in faces for k in range(1, len(f) - 1)]
        verts, tri = torch.as_tensor(v, dtype=dtype), torch.as_tensor(tris, dtype=torch.long).reshape(-1, 3)
    else:
        trimesh = _trimesh()
        try:
            mesh = trimesh.load(path, process=False, force="mesh")
        except Exception as err:  # trimesh raises many kinds on unreadable content
            raise ValueError(f"{path}: cannot read this mesh ({err})") from err
        verts = torch.as_tensor(np.asarray(mesh.vertices), dtype=dtype).reshape(-1, 3)
        tri = torch.as_tensor(np.asarray(mesh.faces), dtype=torch.long).reshape(-1, 3)
    if verts.shape[0] == 0:
        raise ValueError(f"{path}: no vertices found (an empty or unreadable mesh file)")
    return verts, tri


def save_mesh(path: PathLike, vertices: torch.Tensor, faces: torch.Tensor) -> None:
    """Write a triangle (or quad) mesh: OBJ directly, other formats through trimesh.

    Args:
        path: output file; the extension picks the format.
        vertices: ``(N, 3)`` positions.
        faces: ``(F, 3)`` or ``(F, 4)`` integer corners (0-based).

    Raises:
        TypeError: faces that are not integers.
        ValueError: wrong shapes, or face indices out of range.
    """
    v = torch.as_tensor(vertices).detach().cpu().to(torch.float64).numpy()
    ft = torch.as_tensor(faces).detach().cpu()
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must have shape (N, 3), got {v.shape}")
    if ft.is_floating_point() or ft.is_complex() or ft.dtype == torch.bool:
        raise TypeError(f"faces must be integer vertex indices, got dtype {ft.dtype}")
    if ft.ndim != 2 or ft.shape[1] not in (3, 4):
        raise ValueError(f"faces must have shape (F, 3) or (F, 4), got {tuple(ft.shape)}")
    if ft.numel() and (int(ft.min()) < 0 or int(ft.max()) >= v.shape[0]):
        raise ValueError(
            f"face indices must lie in [0, {v.shape[0]}) for {v.shape[0]} vertices, "
            f"got {int(ft.min())}..{int(ft.max())}"
        )
    f = ft.numpy()
    if str(path).lower().endswith(".obj"):
        Path(path).write_text(_format_rows("v", v, "%.17g") + _format_rows("f", f + 1, "%d"))
        return
    _trimesh("writing").Trimesh(vertices=v, faces=f, process=False).export(path)
