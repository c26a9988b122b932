"""The 3D Gaussian splatting PLY file: read and write with numpy alone, bit-exact round trips.

The file is a binary PLY whose ``vertex`` element holds one Gaussian per record: ``x y z``,
``f_dc_0..2`` (degree-0 colour), ``f_rest_0..(3 (K - 1) - 1)`` (higher degrees, channel-major),
``opacity``, ``scale_0..2`` (log standard deviations), ``rot_0..3`` (quaternion ``w x y z``), and
often ``nx ny nz`` or other fields, which are kept as they are. The header (comments, property
order and types, byte order) and any other elements are remembered, so a file read and written
back is the same file byte for byte.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field

import numpy as np
import torch

from torchcage.splats.scene import GaussianScene

__all__ = ["PlyLayout", "read_ply", "write_ply"]

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_CORE = ("x", "y", "z", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")


@dataclass
class PlyLayout:
    """How a splat PLY stores its Gaussians: the header lines, the ``vertex`` properties in order
    with their PLY types, the byte order, and the bytes before and after the vertex records (other
    elements), so that :func:`write_ply` can write the same file back."""

    header: list[str]  # the header's lines, each with its line ending
    properties: list[tuple[str, str]]
    byte_order: str  # "<" or ">"
    before: bytes = b""
    after: bytes = b""
    other_counts: dict[str, int] = field(default_factory=dict)

    def dtype(self) -> np.dtype:
        return np.dtype([(name, self.byte_order + _TYPES[t]) for name, t in self.properties])


class PlyError(ValueError):
    """A file that is not a splat PLY this reader handles; the message says why."""


def _parse_header(fh) -> tuple[list[str], list[tuple[str, int, list[tuple[str, str]]]], str]:
    first = fh.readline()
    if first.rstrip(b"\r\n") != b"ply":
        raise PlyError("not a PLY file (it does not start with 'ply')")
    lines, elements, fmt = [first.decode("latin-1")], [], None
    while True:
        raw = fh.readline()
        if not raw:
            raise PlyError("the PLY header has no 'end_header' line")
        lines.append(raw.decode("latin-1"))  # with its line ending: written back as it was
        line = lines[-1].rstrip("\r\n")
        words = line.split()
        if not words:
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise PlyError(f"a property before any element: {line!r}")
            if words[1] == "list":
                elements[-1][2].append(("list", line))
            else:
                if words[1] not in _TYPES:
                    raise PlyError(f"unknown PLY property type {words[1]!r} in {line!r}")
                elements[-1][2].append((words[2], words[1]))
        elif words[0] == "end_header":
            break
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        raise PlyError(
            f"PLY format {fmt!r}: splat files are binary (binary_little_endian); convert an ASCII file first"
        )
    return lines, elements, "<" if fmt == "binary_little_endian" else ">"


def _element_size(props: list[tuple[str, str]], order: str, name: str) -> int:
    if any(t == "list" for _, t in props):
        raise PlyError(f"element {name!r} has list properties, which this reader does not skip; remove the element")
    return np.dtype([(p, order + _TYPES[t]) for p, t in props]).itemsize


def read_ply(path: str | os.PathLike) -> GaussianScene:
    """Read a 3D Gaussian splatting PLY file.

    Args:
        path: the file.

    Returns:
        A :class:`GaussianScene` whose tensors have the file's types (float32 for a standard
        file); ``scene.layout`` remembers the file's layout for :func:`write_ply`.

    Raises:
        PlyError: not a binary PLY, no ``vertex`` element, or a missing Gaussian field (named).

    Examples:
        >>> import tempfile, pathlib
        >>> from torchcage.splats import GaussianScene, read_ply, write_ply
        >>> f = pathlib.Path(tempfile.mkdtemp()) / "scene.ply"
        >>> write_ply(f, GaussianScene.random(10, degree=2))
        >>> read_ply(f).degree
        2
    """
    with open(path, "rb") as fh:
        header, elements, order = _parse_header(fh)
        body = fh.read()
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise PlyError(f"no 'vertex' element in {os.fspath(path)!r} (elements: {names})")
    offset, before_end = 0, None
    layout_props, count = None, 0
    for name, n, props in elements:
        size = _element_size(props, order, name) * n
        if name == "vertex" and layout_props is None:
            before_end, layout_props, count = offset, props, n
        offset += size
    if offset > len(body):
        raise PlyError(f"the file is truncated: the header describes {offset} bytes of data, the file has {len(body)}")
    layout = PlyLayout(
        header=header,
        properties=layout_props,
        byte_order=order,
        before=body[:before_end],
        after=body[before_end + np.dtype([(p, order + _TYPES[t]) for p, t in layout_props]).itemsize * count :],
    )
    records = np.frombuffer(body, dtype=layout.dtype(), count=count, offset=before_end)
    return _scene_from_records(records, [p for p, _ in layout_props]).replace(layout=layout)


def _column(records: np.ndarray, name: str) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(records[name]).astype(records[name].dtype.newbyteorder("=")))


def _stack(records: np.ndarray, names: list[str]) -> torch.Tensor:
    cols = [_column(records, n) for n in names]
    dtype = cols[0].dtype if all(c.dtype == cols[0].dtype for c in cols) else torch.float64
    return torch.stack([c.to(dtype) for c in cols], dim=-1)


def _scene_from_records(records: np.ndarray, names: list[str]) -> GaussianScene:
    present = set(names)
    missing = [n for n in (*_CORE, "f_dc_0", "f_dc_1", "f_dc_2") if n not in present]
    if missing:
        raise PlyError(f"the vertex element lacks the Gaussian fields {missing}: not a 3D Gaussian splatting file")
    rest = sorted((n for n in names if re.fullmatch(r"f_rest_\d+", n)), key=lambda n: int(n[7:]))
    if len(rest) % 3 or [int(n[7:]) for n in rest] != list(range(len(rest))):
        raise PlyError(f"f_rest fields must be f_rest_0..f_rest_(3m-1), got {len(rest)} of them")
    k = 1 + len(rest) // 3
    dc = _stack(records, ["f_dc_0", "f_dc_1", "f_dc_2"])  # (N, 3)
    if rest:
        r = _stack(records, rest).reshape(-1, 3, k - 1).transpose(1, 2)  # channel-major -> (N, K-1, 3)
        sh = torch.cat([dc[:, None, :].to(r.dtype), r.to(dc.dtype) if r.dtype != dc.dtype else r], dim=1)
    else:
        sh = dc[:, None, :]
    known = set(_CORE) | {"f_dc_0", "f_dc_1", "f_dc_2"} | set(rest)
    return GaussianScene(
        means=_stack(records, ["x", "y", "z"]),
        log_scales=_stack(records, ["scale_0", "scale_1", "scale_2"]),
        rotations=_stack(records, ["rot_0", "rot_1", "rot_2", "rot_3"]),
        opacity_logits=_column(records, "opacity"),
        sh=sh,
        extra={n: _column(records, n) for n in names if n not in known},
    )


def _standard_layout(scene: GaussianScene) -> PlyLayout:
    k = scene.sh.shape[1]
    props = ["x", "y", "z", *[n for n in ("nx", "ny", "nz") if n in scene.extra]]
    props += ["f_dc_0", "f_dc_1", "f_dc_2", *[f"f_rest_{i}" for i in range(3 * (k - 1))], "opacity"]
    props += ["scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    props += [n for n in scene.extra if n not in props]
    types = []
    for n in props:
        t = scene.extra[n].dtype if n in scene.extra else scene.means.dtype
        types.append({torch.float64: "double", torch.int32: "int", torch.uint8: "uchar"}.get(t, "float"))
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {scene.num_gaussians}"]
    header += [f"property {t} {n}" for n, t in zip(props, types, strict=True)] + ["end_header"]
    header = [line + "\n" for line in header]
    return PlyLayout(header=header, properties=list(zip(props, types, strict=True)), byte_order="<")


def write_ply(path: str | os.PathLike, scene: GaussianScene) -> None:
    """Write a scene as a 3D Gaussian splatting PLY (binary little endian, float32 fields, the
    standard property order) or, for a scene read by :func:`read_ply` with the same fields, in the
    file's own layout (a read file written back is the same bytes).

    Args:
        path: the file to write.
        scene: the Gaussians (any float dtype; cast to the file's field types).

    Raises:
        ValueError: non-finite values in a field (a splat renderer would fail on them).
    """
    k = scene.sh.shape[1]
    values = {
        **{a: scene.means[:, i] for i, a in enumerate("xyz")},
        **{f"scale_{i}": scene.log_scales[:, i] for i in range(3)},
        **{f"rot_{i}": scene.rotations[:, i] for i in range(4)},
        "opacity": scene.opacity_logits,
        **{f"f_dc_{c}": scene.sh[:, 0, c] for c in range(3)},
        **{f"f_rest_{c * (k - 1) + j}": scene.sh[:, 1 + j, c] for c in range(3) for j in range(k - 1)},
        **scene.extra,
    }
    for name, t in values.items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise ValueError(f"field {name!r} holds NaN or inf; fix the scene before writing it")
    layout = getattr(scene, "layout", None)
    if layout is None or {n for n, _ in layout.properties} != set(values):
        layout = _standard_layout(scene)
    header = list(layout.header)
    for i, line in enumerate(header):
        words = line.split()
        if words[:2] == ["element", "vertex"] and int(words[2]) != scene.num_gaussians:
            header[i] = f"element vertex {scene.num_gaussians}" + line[len(line.rstrip("\r\n")) :]
    records = np.empty(scene.num_gaussians, dtype=layout.dtype())
    for name, _ in layout.properties:
        records[name] = values[name].detach().cpu().numpy()
    with open(path, "wb") as fh:
        fh.write("".join(header).encode("latin-1"))
        fh.write(layout.before)
        fh.write(records.tobytes())
        fh.write(layout.after)
