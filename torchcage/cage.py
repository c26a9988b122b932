"""The :class:`Cage`: a closed triangle/quad surface in 3D or a closed polygon in 2D.

A cage is validated once, when it is built: finite vertices, indices in range, no repeated index
in a face, no zero-area face, closed and manifold (every edge shared by exactly two faces in 3D,
every vertex on exactly one incoming and one outgoing edge in 2D), consistent orientation. A cage
that is consistently oriented *inward* (negative signed volume or area) is flipped, with a warning,
so that normals point outward; vertex order is never changed.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import torch

from torchcage.errors import CageError, CageOrientationError, CageTopologyError, DegenerateFaceError

__all__ = ["Cage"]

#: Faces whose area (3D) or edge length (2D) is below this fraction of the squared (plain)
#: bounding-box diagonal are rejected as degenerate.
DEGENERATE_TOLERANCE = 1e-12
#: By default, cages with up to this many faces (triangles, quads counted twice, or 2D edges) are
#: tested for self-intersections (about 0.4 s at this size on 2 cores).
INTERSECTION_CHECK_FACES = 2048
#: Cage coordinates beyond this magnitude are refused: the kernels' products (squared lengths, triple
#: products, up to sixth powers in the far-field rule) would overflow float64.
_MAX_COORDINATE = 1e50

#: Topologies already validated, with their unique edges: ``(V, triangles, quads)`` (their bytes) ->
#: ``(E, 2)`` edges. A training step builds a ``Cage`` on the same faces at every call; the
#: topology (a pure function of the faces) is then checked once. CPU index tensors only; at most
#: ``_TOPOLOGY_CACHE_SIZE`` entries, the oldest dropped first.
_TOPOLOGY_SEEN: dict[tuple[int, bytes, bytes], torch.Tensor] = {}
_TOPOLOGY_CACHE_SIZE = 64


def _as_vertices(vertices: Any) -> torch.Tensor:
    if isinstance(vertices, torch.Tensor) or hasattr(vertices, "__array__"):
        v = torch.as_tensor(vertices)
    else:  # nested lists: float64, the library's working precision
        v = torch.as_tensor(vertices, dtype=torch.float64)
    if not (v.is_floating_point()):
        if v.dtype.is_complex or v.dtype == torch.bool:
            raise TypeError(f"cage vertices must be real numbers, got dtype {v.dtype}")
        v = v.to(torch.float64)
    if v.ndim < 2 or v.shape[-1] not in (2, 3):
        raise CageError(
            f"cage vertices must have shape (V, 3) or (V, 2), or (*B, V, D) for a batch of cages with one "
            f"topology, got {tuple(v.shape)}"
        )
    if v.shape[-2] < v.shape[-1] + 1:
        raise CageError(f"a {v.shape[-1]}D cage needs at least {v.shape[-1] + 1} vertices, got {v.shape[-2]}")
    return v


def _check_finite_vertices(v: torch.Tensor) -> None:
    """Raise a CageError naming the batch element and the vertices that hold NaN or inf."""
    bad = ~torch.isfinite(v).all(dim=-1)
    if bool(bad.any()):
        where = torch.nonzero(bad)
        if v.ndim == 2:
            idx = where.flatten()[:10].tolist()
            raise CageError(f"cage vertices contain NaN or inf (vertex indices {idx}); remove or fix them")
        first = tuple(where[0, :-1].tolist())
        idx = where[(where[:, :-1] == where[0, :-1]).all(dim=1), -1][:10].tolist()
        raise CageError(
            f"cage vertices contain NaN or inf: batch element {first}, vertex indices {idx} "
            f"({int(bad.flatten(0, -2).any(dim=1).sum())} element(s) affected); remove or fix them"
        )


def _unit(n: torch.Tensor) -> torch.Tensor:
    """``n / |n|`` along the last axis for vectors of order-one size (zero vectors stay zero)."""
    norm = torch.linalg.vector_norm(n, dim=-1, keepdim=True)
    return n / norm.clamp_min(torch.finfo(n.dtype).tiny)


def _batch_name(index: torch.Tensor, batch_shape: torch.Size) -> str:
    """``" in batch element (i, j)"`` for a flat index into ``batch_shape`` (empty when unbatched)."""
    if len(batch_shape) == 0:
        return ""
    rest, idx = int(index), []
    for n in reversed(batch_shape):
        idx.append(rest % n)
        rest //= n
    return f" in batch element {tuple(reversed(idx))}"


def _split_faces(faces: Any, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Split faces given as a tensor or a list of index lists into triangles (T, 3) and quads (Q, 4)."""
    if isinstance(faces, torch.Tensor) or hasattr(faces, "__array__"):
        f = torch.as_tensor(faces, device=device)
        if f.is_floating_point() or f.dtype == torch.bool or f.dtype.is_complex:
            raise TypeError(f"faces must be integer indices, got dtype {f.dtype}")
        f = f.long()
        if f.ndim != 2 or f.shape[1] not in (3, 4):
            raise CageError(
                f"faces must have shape (F, 3) or (F, 4), got {tuple(f.shape)}; "
                "for a mix of triangles and quads pass a list of index lists"
            )
        empty3 = torch.zeros((0, 3), dtype=torch.long, device=device)
        empty4 = torch.zeros((0, 4), dtype=torch.long, device=device)
        return (f, empty4) if f.shape[1] == 3 else (empty3, f)
    if not isinstance(faces, Sequence):
        raise TypeError(f"faces must be a LongTensor or a list of index lists, got {type(faces).__name__}")
    tris, quads = [], []
    for k, face in enumerate(faces):
        idx = [int(i) for i in face]
        if len(idx) == 3:
            tris.append(idx)
        elif len(idx) == 4:
            quads.append(idx)
        else:
            raise CageError(
                f"face {k} has {len(idx)} corners; cages support triangles and quads only "
                "(split larger polygons into triangles or quads)"
            )
    t = torch.tensor(tris, dtype=torch.long, device=device).reshape(-1, 3)
    q = torch.tensor(quads, dtype=torch.long, device=device).reshape(-1, 4)
    return t, q


def _polygon_edges(n: int, device: torch.device) -> torch.Tensor:
    i = torch.arange(n, device=device)
    return torch.stack([i, (i + 1) % n], dim=1)


class Cage:
    """A closed cage: a triangle/quad surface in 3D or a closed polygon in 2D, or a batch of such
    cages sharing one topology.

    Args:
        vertices: ``(V, 3)`` or ``(V, 2)`` vertex positions, or ``(*B, V, D)`` for a batch of cages
            with the same faces (a network predicting a cage per shape): a tensor or array keeps its
            floating dtype (integers become float64); nested lists become float64. The cage keeps a
            copy (differentiable: gradients still reach the caller's tensor).
        faces: in 3D, a LongTensor ``(F, 3)`` or ``(F, 4)``, or a list of index lists of length 3
            or 4 (a triquad cage). In 2D, the directed edges ``(E, 2)``, or ``None`` for one closed
            polygon whose vertices are given in order.
        validate: ``True`` (default): check the topology (indices, closed, manifold, consistently
            oriented) and every batch element's geometry (finite vertices, no zero-area face,
            outward orientation); ``"topology"``: the topology only, no check of the vertex values and
            no host synchronisation on a GPU (for a hot loop; see also :meth:`with_vertices`);
            ``False``: nothing (the caller guarantees a valid cage).
        check_intersections: with ``validate=True``, also refuse a cage that intersects itself
            (an edge passing through a face in 3D, crossing edges in 2D; the pair is named). The
            test is vectorised but grows with the square of the number of faces (about 0.2 s for
            1,300 triangles, 2.4 s for 5,000 here). ``None`` (default): test cages of up to
            ``INTERSECTION_CHECK_FACES`` faces (cages are coarse; a dense mesh given as a cage is
            not tested); ``True``: test any size; ``False``: never.

    Attributes:
        vertices: ``(*B, V, D)`` vertex positions (``B`` empty for one cage).
        triangles: ``(T, 3)`` int64 triangle corners (3D; empty in 2D).
        quads: ``(Q, 4)`` int64 quad corners (3D; empty in 2D).
        edges: ``(E, 2)`` int64 directed polygon edges (2D; empty in 3D).

    Raises:
        CageError: bad shapes, non-finite vertices, indices out of range or repeated in a face.
        DegenerateFaceError: a face of zero area (3D) or an edge of zero length (2D).
        CageTopologyError: an open or non-manifold cage (the offending edges are named).
        CageOrientationError: inconsistently oriented faces (a face pair is named), or a batch
            whose elements disagree in orientation (some inside out).
        CageTopologyError: a self-intersecting cage (with ``check_intersections``).

    Every error about the geometry of a batch names the batch element.

    Examples:
        >>> import torch, torchcage
        >>> v = torch.tensor([[0., 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        >>> cage = torchcage.Cage(v, [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        >>> cage.num_vertices, cage.dim, round(float(cage.signed_volume()), 4)
        (4, 3, 0.1667)
        >>> square = torchcage.Cage([[0., 0], [1, 0], [1, 1], [0, 1]])  # 2D polygon, in order
        >>> square.edges.tolist()
        [[0, 1], [1, 2], [2, 3], [3, 0]]
        >>> batch = torchcage.Cage(torch.stack([v, 2 * v, v + 1]), cage.triangles)  # 3 cages, one topology
        >>> batch.batch_shape, batch[1].vertices.shape, batch.signed_volume().shape
        (torch.Size([3]), torch.Size([4, 3]), torch.Size([3]))
    """

    def __init__(
        self,
        vertices: Any,
        faces: Any = None,
        *,
        validate: bool | str = True,
        check_intersections: bool | None = None,
    ) -> None:
        if validate not in (True, False, "topology"):
            raise ValueError(f'validate must be True, False or "topology", got {validate!r}')
        v = _as_vertices(vertices)
        if isinstance(vertices, torch.Tensor) or hasattr(vertices, "__array__"):
            # the cage owns its vertices: editing the caller's tensor (or array) in place afterwards
            # cannot change a validated cage (clone keeps the autograd graph)
            v = v.clone()
        self.vertices: torch.Tensor = v
        dev = v.device
        empty3 = torch.zeros((0, 3), dtype=torch.long, device=dev)
        empty4 = torch.zeros((0, 4), dtype=torch.long, device=dev)
        if v.shape[-1] == 3:
            if faces is None:
                raise CageError("a 3D cage needs faces: a LongTensor (F, 3) / (F, 4) or a list of index lists")
            self.triangles, self.quads = _split_faces(faces, dev)
            self.edges = torch.zeros((0, 2), dtype=torch.long, device=dev)
            if self.triangles.shape[0] + self.quads.shape[0] == 0:
                raise CageError("a 3D cage needs at least one face")
        else:
            self.triangles, self.quads = empty3, empty4
            if faces is None:
                self.edges = _polygon_edges(v.shape[-2], dev)
            else:
                e = torch.as_tensor(faces, device=dev)
                if e.is_floating_point() or e.ndim != 2 or e.shape[1] != 2:
                    raise CageError(
                        f"2D cage edges must be an integer tensor of shape (E, 2), got {tuple(e.shape)} "
                        f"({e.dtype}); or pass faces=None for one closed polygon given in order"
                    )
                self.edges = e.long()
        self._geometry_checked = False
        if validate is True:
            _check_finite_vertices(v)
            self._validate(geometry=True)
            self._geometry_checked = True
            n_faces = self.triangles.shape[0] + 2 * self.quads.shape[0] + self.edges.shape[0]
            if check_intersections or (check_intersections is None and n_faces <= INTERSECTION_CHECK_FACES):
                self._check_intersections()
        elif validate == "topology":
            self._validate(geometry=False)

    def with_vertices(self, vertices: torch.Tensor, *, validate: bool = False) -> Cage:
        """The same topology around other vertex positions ``(*B, V, D)`` (a network's output each
        step): no topology check, and by default no geometric check either, so no host
        synchronisation on a GPU here. With ``validate=True`` the geometry is checked as in the
        constructor (orientation included: this cage's faces are not flipped again). The functions
        that compute coordinates check an unchecked cage once (:meth:`check_geometry`: one pass over
        the faces and a host synchronisation); a module's ``forward`` does not. Unlike the
        constructor, which copies, the new cage holds ``vertices`` itself (no copy in a hot loop).

        Examples:
            >>> import torch, torchcage
            >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
            >>> moved = cube.with_vertices(cube.vertices.expand(4, -1, -1) * 2)
            >>> moved.batch_shape
            torch.Size([4])
        """
        v = _as_vertices(vertices)
        if tuple(v.shape[-2:]) != tuple(self.vertices.shape[-2:]):
            raise CageError(
                f"vertices must have shape (*B, {self.num_vertices}, {self.dim}) for this cage's faces, "
                f"got {tuple(v.shape)}"
            )
        dev = v.device
        c = Cage._trusted(v, self.triangles.to(dev), self.quads.to(dev), self.edges.to(dev))
        if validate:
            _check_finite_vertices(v)
            c._validate_geometry(flip=False)
            c._geometry_checked = True
        return c

    def check_geometry(self) -> Cage:
        """Check every batch element's geometry, once: finite vertices, coordinates whose products stay
        finite, no zero-area face and no coincident vertices (zero-length edge). Orientation is not
        checked here (a learnt pose may turn a cage inside out; the coordinates stay defined).

        The constructor (``validate=True``) and ``with_vertices(..., validate=True)`` run these checks;
        cages built without them (``validate=False`` or ``"topology"``, :meth:`with_vertices` in a loop)
        are checked by every function that computes coordinates, so no path answers silently for a
        cage that cannot be computed with. A cage that passed is remembered (no second check).

        Returns:
            This cage.

        Raises:
            CageError: NaN or inf vertices, or coordinates too large for float64 products.
            DegenerateFaceError: a zero-area face or zero-length edge (the batch element is named).

        Examples:
            >>> import torch, torchcage
            >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
            >>> bad = cube.vertices.clone(); bad[1] = bad[0]
            >>> cube.with_vertices(bad).check_geometry()
            Traceback (most recent call last):
            ...
            torchcage.errors.DegenerateFaceError: ...
        """
        if not getattr(self, "_geometry_checked", False):
            _check_finite_vertices(self.vertices.detach())
            self._check_degenerate()
            self._geometry_checked = True
        return self

    def _like(self, v: torch.Tensor, tri: torch.Tensor | None = None, quads: torch.Tensor | None = None) -> Cage:
        """This cage's topology around ``v`` (a part or a view of its vertices): the geometry check
        carries over."""
        c = Cage._trusted(v, self.triangles if tri is None else tri, self.quads if quads is None else quads, self.edges)
        # (as in .to(): a lower precision can round vertices together or overflow: checked again then)
        c._geometry_checked = getattr(self, "_geometry_checked", False) and v.dtype == self.vertices.dtype
        return c

    # ------------------------------------------------------------------ basic properties
    @property
    def dim(self) -> int:
        """Ambient dimension, 2 or 3."""
        return int(self.vertices.shape[-1])

    @property
    def num_vertices(self) -> int:
        """Number of cage vertices ``V``."""
        return int(self.vertices.shape[-2])

    @property
    def batch_shape(self) -> torch.Size:
        """Leading batch shape ``B`` of the vertices (``torch.Size([])`` for one cage)."""
        return self.vertices.shape[:-2]

    @property
    def is_batched(self) -> bool:
        """True when the vertices hold a batch of cages ``(*B, V, D)``."""
        return self.vertices.ndim > 2

    def __len__(self) -> int:
        if not self.is_batched:
            raise TypeError("len() of an unbatched cage; use cage.num_vertices")
        return int(self.vertices.shape[0])

    def __getitem__(self, index: Any) -> Cage:
        """Batch elements: ``cage[b]`` is one cage (or a smaller batch), sharing the topology
        (no validation: the elements of a validated batch are valid). Differentiable: its vertices
        are ``cage.vertices[b]``."""
        if not self.is_batched:
            raise TypeError("indexing an unbatched cage; index cage.vertices for vertex positions")
        v = self.vertices[index]
        if v.ndim < 2 or tuple(v.shape[-2:]) != tuple(self.vertices.shape[-2:]):
            raise IndexError(
                f"cage[{index!r}] must select batch elements only (batch shape {tuple(self.batch_shape)}), "
                f"got vertices of shape {tuple(v.shape)}"
            )
        return self._like(v)

    def unbind(self) -> list[Cage]:
        """The batch elements as a list of cages, over the flattened batch shape."""
        flat = self.vertices.reshape(-1, self.num_vertices, self.dim)
        return [self._like(v) for v in flat.unbind(0)]

    @property
    def dtype(self) -> torch.dtype:
        return self.vertices.dtype

    @property
    def device(self) -> torch.device:
        return self.vertices.device

    @property
    def has_quads(self) -> bool:
        """True when the cage has at least one quad face."""
        return self.quads.shape[0] > 0

    @property
    def faces(self) -> torch.Tensor | list[list[int]]:
        """Faces as given: ``(F, 3)`` or ``(F, 4)`` tensor, or a list (triangles then quads) for a
        triquad cage; the edges ``(E, 2)`` in 2D."""
        if self.dim == 2:
            return self.edges
        if not self.has_quads:
            return self.triangles
        if self.triangles.shape[0] == 0:
            return self.quads
        return self.triangles.tolist() + self.quads.tolist()

    @property
    def scale(self) -> float:
        """Length of the bounding-box diagonal (the scale every tolerance is relative to); for a
        batch, the largest over its elements."""
        return float(self._scales().max())

    def _scales(self) -> torch.Tensor:
        """``(*B,)`` bounding-box diagonals of the batch elements, float64."""
        v = self.vertices.detach().to(torch.float64)
        return (v.amax(dim=-2) - v.amin(dim=-2)).norm(dim=-1)

    def __repr__(self) -> str:
        if self.dim == 2:
            body = f"edges={self.edges.shape[0]}"
        else:
            body = f"triangles={self.triangles.shape[0]}, quads={self.quads.shape[0]}"
        batch = f"batch_shape={tuple(self.batch_shape)}, " if self.is_batched else ""
        return (
            f"Cage(dim={self.dim}, {batch}vertices={self.num_vertices}, {body}, dtype={self.dtype}, "
            f"device={self.device})"
        )

    # ------------------------------------------------------------------ derived geometry
    def triangulated(self) -> Cage:
        """A triangle-only cage: each quad ``(q0, q1, q2, q3)`` is split along ``q0``–``q2`` into
        ``(q0, q1, q2)`` and ``(q0, q2, q3)``; triangles come first, in their order.

        Returns:
            A new :class:`Cage` sharing the vertices (``T + 2Q`` triangles).
        """
        if self.dim == 2 or not self.has_quads:
            return self
        q = self.quads
        split = torch.stack([q[:, [0, 1, 2]], q[:, [0, 2, 3]]], dim=1).reshape(-1, 3)
        return self._like(self.vertices, torch.cat([self.triangles, split]), self.quads[:0])

    def unique_edges(self) -> torch.Tensor:
        """The undirected edges of the faces as given (quad diagonals excluded), ``(E, 2)`` int64
        with ``E[:, 0] < E[:, 1]``; in 2D, the polygon edges as directed."""
        if self.dim == 2:
            return self.edges
        key = self._topology_key()
        if key is not None and key in _TOPOLOGY_SEEN:
            return _TOPOLOGY_SEEN[key].clone()  # (a copy: the cache is never changed by a caller)
        return self._unique_edges()

    def _topology_key(self) -> tuple[int, bytes, bytes] | None:
        """The key of this cage's faces in ``_TOPOLOGY_SEEN`` (``None`` off the CPU)."""
        tri, quads = self.triangles, self.quads
        if tri.device.type != "cpu" or quads.device.type != "cpu":
            return None
        return self.num_vertices, tri.numpy().tobytes(), quads.numpy().tobytes()

    def _unique_edges(self) -> torch.Tensor:
        parts = [f for f in (self.triangles, self.quads) if f.shape[0]]
        e = torch.cat([torch.stack([f, f.roll(-1, dims=1)], dim=-1).reshape(-1, 2) for f in parts])
        return torch.unique(e.sort(dim=1).values, dim=0)

    def invalid_quads(self) -> torch.Tensor:
        """Indices of the quads that are not *valid* in the sense of quad mean value coordinates
        (Thiery, Memari, Boubekeur 2018, Definition 1): a quad is valid when its orthogonal
        projection onto each of the four planes of its corner triangles ``(q_{i-1}, q_i, q_{i+1})``
        is a convex quad. For planar quads this is plain convexity; it rules out fold-overs of
        the bilinear interpolant.

        The projection onto the plane of corner ``i`` turns by ``(e_{k-1} x e_k) . c_i`` at corner
        ``k`` (``e_k = q_{k+1} - q_k``, ``c_i = e_{i-1} x e_i``), so the test is that all pairwise
        dot products of the four corner normals are positive (a relative margin of 1e-12 treats
        numerically degenerate corners as invalid).

        Returns:
            ``(K,)`` int64 indices into ``cage.quads`` (empty when all are valid, or in 2D).

        Examples:
            >>> import torch, torchcage
            >>> cube = torchcage.load_cage(torchcage.data.path("cube.obj"))
            >>> cube.invalid_quads().tolist()
            []
        """
        if self.dim == 2 or not self.has_quads:
            return torch.zeros(0, dtype=torch.long, device=self.device)
        bad = self._invalid_quad_mask()  # (*B, Q): invalid in any batch element
        return torch.nonzero(bad.reshape(-1, bad.shape[-1]).any(dim=0)).flatten()

    def _invalid_quad_mask(self) -> torch.Tensor:
        """``(*B, Q)`` bool: the quads of each batch element that fail :meth:`invalid_quads`'s test
        (a 3D cage with quads)."""
        p = self.vertices.detach().to(torch.float64)[..., self.quads, :]  # (*B, Q, 4, 3)
        e = p.roll(-1, dims=-2) - p  # e_k = q_{k+1} - q_k
        c = torch.linalg.cross(e.roll(1, dims=-2), e, dim=-1)  # corner normals c_k = e_{k-1} x e_k
        c = torch.nn.functional.normalize(c, dim=-1)
        cosines = c @ c.transpose(-1, -2)  # (*B, Q, 4, 4)
        return (cosines <= 1e-12).flatten(-2).any(dim=-1)

    def triangle_normals(self, unit: bool = True) -> torch.Tensor:
        """Outward normals of the triangles of :meth:`triangulated`, shape ``(*B, T + 2Q, 3)``.

        With ``unit=False`` the normals are ``(b - a) x (c - a)``, of length twice the area.
        """
        tri = self.triangulated().triangles
        p = self.vertices[..., tri, :]
        a, b = p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :]
        if not unit:
            return torch.linalg.cross(a, b, dim=-1)
        # scale-free: the edges divided by their largest component before the cross product, so that
        # tiny or huge cages neither underflow nor meet a fixed clamp (|n| = 1 at any size)
        m = torch.maximum(a.abs().amax(dim=-1, keepdim=True), b.abs().amax(dim=-1, keepdim=True))
        m = m.clamp_min(torch.finfo(m.dtype).tiny)
        return _unit(torch.linalg.cross(a / m, b / m, dim=-1))

    def quad_corner_normals(self) -> torch.Tensor:
        """Unnormalised quad corner normals ``N_k = (q_{k+1} - q_k) x (q_{k+3} - q_k)``, ``(*B, Q, 4, 3)``."""
        p = self.vertices[..., self.quads, :]
        return torch.linalg.cross(p.roll(-1, dims=-2) - p, p.roll(1, dims=-2) - p, dim=-1)

    def edge_normals(self) -> torch.Tensor:
        """Outward unit normals of the edges of a 2D cage, ``(*B, E, 2)`` (right of each edge, for a
        counter-clockwise polygon)."""
        if self.dim != 2:
            raise CageError("edge_normals() is for 2D cages; use triangle_normals() in 3D")
        d = self.vertices[..., self.edges[:, 1], :] - self.vertices[..., self.edges[:, 0], :]
        m = d.abs().amax(dim=-1, keepdim=True).clamp_min(torch.finfo(d.dtype).tiny)
        d = d / m  # scale-free, as in triangle_normals
        return _unit(torch.stack([d[..., 1], -d[..., 0]], dim=-1))

    def signed_volume(self) -> torch.Tensor:
        """Signed volume (3D) or signed area (2D), ``(*B,)``; positive for an outward-oriented cage."""
        p = self.vertices.to(torch.float64)
        p = p - p.mean(dim=-2, keepdim=True)
        if self.dim == 2:
            a, b = p[..., self.edges[:, 0], :], p[..., self.edges[:, 1], :]
            return (0.5 * (a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]).sum(dim=-1)).to(self.dtype)
        tri = self.triangulated().triangles
        a, b, c = p[..., tri[:, 0], :], p[..., tri[:, 1], :], p[..., tri[:, 2], :]
        return ((a * torch.linalg.cross(b, c, dim=-1)).sum(dim=(-2, -1)) / 6.0).to(self.dtype)

    def to(self, *args: Any, **kwargs: Any) -> Cage:
        """A copy on another dtype and/or device, with ``Tensor.to`` arguments (``cage.to(torch.float32)``,
        ``cage.to("cuda")``, ``cage.to(device=..., dtype=...)``). Index tensors stay int64."""
        v = self.vertices.to(*args, **kwargs)
        if not v.is_floating_point():
            raise TypeError(f"a cage's vertices must stay floating point, got {v.dtype}")
        dev = v.device
        c = Cage._trusted(v, self.triangles.to(dev), self.quads.to(dev), self.edges.to(dev))
        # a lower precision can round vertices together or overflow: check again then
        c._geometry_checked = getattr(self, "_geometry_checked", False) and v.dtype == self.vertices.dtype
        return c

    @classmethod
    def _from_faces(cls, v: torch.Tensor, faces: torch.Tensor) -> Cage:
        """Build without validation around vertices ``(V, D)`` and the faces of an already
        validated cage: triangles ``(T, 3)`` in 3D, edges ``(E, 2)`` in 2D."""
        empty = [torch.zeros((0, k), dtype=torch.long, device=v.device) for k in (3, 4, 2)]
        if v.shape[-1] == 3:
            return cls._trusted(v, faces, empty[1], empty[2])
        return cls._trusted(v, empty[0], empty[1], faces)

    @classmethod
    def _trusted(cls, v: torch.Tensor, tri: torch.Tensor, quads: torch.Tensor, edges: torch.Tensor) -> Cage:
        """Build without validation from parts already known to be valid."""
        c = cls.__new__(cls)
        c.vertices, c.triangles, c.quads, c.edges = v, tri, quads, edges
        c._geometry_checked = False
        return c

    # ------------------------------------------------------------------ validation
    def _validate(self, geometry: bool = True) -> None:
        """Topology (the faces: indices, closed, manifold, consistently oriented), then, with
        ``geometry``, every batch element's geometry (:meth:`_validate_geometry`)."""
        for name, idx in (("triangles", self.triangles), ("quads", self.quads), ("edges", self.edges)):
            self._check_indices(name, idx)
        if geometry:  # zero-area faces first: they explain most topology errors that follow
            self._check_degenerate()
        if self.dim == 3:
            self._validate_topology_3d()
        else:
            self._validate_topology_2d()
        if geometry:
            self._check_orientation(flip=True)

    def _check_indices(self, name: str, idx: torch.Tensor) -> None:
        if idx.numel() == 0:
            return
        V = self.num_vertices
        bad = (idx < 0) | (idx >= V)
        if bool(bad.any()):
            rows = torch.nonzero(bad.any(dim=1)).flatten()[:10].tolist()
            raise CageError(f"{name} {rows} index vertices outside [0, {V - 1}]; the cage has {V} vertices")
        s = idx.sort(dim=1).values
        rep = (s[:, 1:] == s[:, :-1]).any(dim=1)
        if bool(rep.any()):
            rows = torch.nonzero(rep).flatten()[:10].tolist()
            raise CageError(f"{name} {rows} repeat a vertex index; remove these degenerate {name}")

    def _validate_geometry(self, flip: bool) -> None:
        """Per batch element, vectorised over the batch: no zero-area face (zero-length edge in 2D),
        and one orientation (see :meth:`_check_orientation`)."""
        self._check_degenerate()
        self._check_orientation(flip)

    def _check_intersections(self) -> None:
        """No batch element intersects itself: no edge of a face passes through another face (3D),
        no two polygon edges cross (2D)."""
        from torchcage._intersections import edge_edge_crossings, edge_triangle_crossings

        batch = self.batch_shape
        flat = self.vertices.detach().reshape(-1, self.num_vertices, self.dim)
        tri = self.triangulated().triangles if self.dim == 3 else None
        owner = None
        for b in range(flat.shape[0]):
            if self.dim == 2:
                hit = edge_edge_crossings(flat[b], self.edges)
                if hit.numel():
                    i, j = hit[0].tolist()
                    raise CageTopologyError(
                        f"the polygon intersects itself{_batch_name(b, batch)}: edges {i} {self.edges[i].tolist()} "
                        f"and {j} {self.edges[j].tolist()} cross ({hit.shape[0]} crossing pairs); untangle it "
                        "(a bow-tie is two polygons: give each its own loop)"
                    )
                continue
            edges = self.unique_edges()
            hit = edge_triangle_crossings(flat[b], edges, tri)
            if hit.numel():
                e, t = hit[0].tolist()
                if owner is None:
                    T = self.triangles.shape[0]
                    names = [f"triangle {k}" for k in range(T)]
                    owner = names + [
                        f"quad {k} (split along q0-q2)" for k in range(self.quads.shape[0]) for _ in (0, 1)
                    ]
                raise CageTopologyError(
                    f"the cage intersects itself{_batch_name(b, batch)}: edge {edges[e].tolist()} passes through "
                    f"{owner[t]} ({hit.shape[0]} edge-face crossings); move the vertices so that the surface does not "
                    "pass through itself, or pass check_intersections=False to skip this test"
                )

    def _check_degenerate(self) -> None:
        """No zero-area face (zero-length edge in 2D) in any batch element, and coordinates whose
        squares stay finite."""
        v = self.vertices.detach().to(torch.float64).reshape(-1, self.num_vertices, self.dim)
        extent = float(v.abs().max()) if v.numel() else 0.0
        if extent > _MAX_COORDINATE:
            raise CageError(
                f"cage coordinates reach {extent:.3g}: products of such coordinates overflow float64 (beyond about "
                f"{_MAX_COORDINATE:.0e}); rescale the cage and the points (the coordinates are scale invariant)"
            )
        scales = self._scales().reshape(-1)
        batch = self.batch_shape
        # relative to each element's box (corner at the origin, unit diagonal): tolerances hold at any
        # scale and translation, and products of tiny or huge coordinates neither underflow nor overflow
        lo = v.amin(dim=1, keepdim=True)
        v = (v - lo) / scales.clamp_min(torch.finfo(torch.float64).tiny)[:, None, None]
        scales = torch.ones_like(scales)
        self._check_coincident(v, scales, batch)
        self._check_enclosed(v, batch)
        if self.dim == 3:
            self._check_areas_3d(v, scales, batch)
        else:
            e = self.edges
            length = (v[:, e[:, 1]] - v[:, e[:, 0]]).norm(dim=-1)  # (B, E)
            bad = length <= DEGENERATE_TOLERANCE * scales[:, None]
            if bool(bad.any()):
                b = int(torch.nonzero(bad.any(dim=1))[0])
                raise DegenerateFaceError(
                    f"edges {torch.nonzero(bad[b]).flatten()[:10].tolist()}{_batch_name(b, batch)} have zero "
                    "length (coincident vertices); remove duplicate vertices"
                )

    def _check_coincident(self, v: torch.Tensor, scales: torch.Tensor, batch: torch.Size) -> None:
        """No two vertices at one position in any batch element of ``v`` ``(B, V, D)``: no face edge
        shorter than ``DEGENERATE_TOLERANCE`` of the size (a quad with two corners together keeps a
        positive area), and no two vertices equal anywhere (a pinch). Vectorised over the batch."""
        if self.dim == 3:
            edges = self.unique_edges()
            if edges.numel():
                length = (v[:, edges[:, 1]] - v[:, edges[:, 0]]).norm(dim=-1)  # (B, E)
                bad = length <= DEGENERATE_TOLERANCE * scales[:, None]
                if bool(bad.any()):
                    b = int(torch.nonzero(bad.any(dim=1))[0])
                    pairs = edges[torch.nonzero(bad[b]).flatten()[:10]].tolist()
                    raise DegenerateFaceError(
                        f"vertices {pairs}{_batch_name(b, batch)} coincide (face edges of zero length); "
                        "remove the duplicate vertices (merge them and drop the faces that collapse) or move them apart"
                    )
        # exact duplicates anywhere: a lexicographic order (stable sorts, last key first) puts them side by side
        order = torch.arange(v.shape[1], device=v.device).expand(v.shape[0], -1)
        for k in reversed(range(v.shape[-1])):
            key = torch.gather(v[..., k], 1, order)
            order = torch.gather(order, 1, torch.sort(key, dim=1, stable=True).indices)
        s = torch.gather(v, 1, order[..., None].expand(-1, -1, v.shape[-1]))
        same = (s[:, 1:] == s[:, :-1]).all(dim=-1)  # (B, V - 1)
        if bool(same.any()):
            b = int(torch.nonzero(same.any(dim=1))[0])
            i = int(torch.nonzero(same[b])[0])
            pair = sorted([int(order[b, i]), int(order[b, i + 1])])
            raise DegenerateFaceError(
                f"vertices {pair}{_batch_name(b, batch)} are at the same position "
                f"({int(same[b].sum())} coincident pair(s)); remove the duplicates or move them apart"
            )

    def _check_enclosed(self, v: torch.Tensor, batch: torch.Size) -> None:
        """Every batch element of ``v`` ``(B, V, D)`` (boxes of unit diagonal) encloses a volume (an
        area in 2D) above ``DEGENERATE_TOLERANCE``: a flat cage (faces folded onto one plane, a polygon
        folded onto a line) has no inside, and its coordinates would be meaningless."""
        c = v - v.mean(dim=1, keepdim=True)
        if self.dim == 2:
            a, b = c[:, self.edges[:, 0]], c[:, self.edges[:, 1]]
            size = 0.5 * (a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]).sum(dim=-1)
        else:
            tri = self.triangulated().triangles
            a, b, d = c[:, tri[:, 0]], c[:, tri[:, 1]], c[:, tri[:, 2]]
            size = (a * torch.linalg.cross(b, d, dim=-1)).sum(dim=(-2, -1)) / 6.0
        flat = size.abs() <= DEGENERATE_TOLERANCE
        if bool(flat.any()):
            b = int(torch.nonzero(flat)[0])
            what = "volume" if self.dim == 3 else "area"
            raise DegenerateFaceError(
                f"the cage{_batch_name(b, batch)} encloses no {what} ({what} {float(size[b]):.2g} of its bounding "
                "box): it is flat, or it folds back over itself (a self-intersection, such as a bow-tie, whose "
                f"parts cancel); a cage must enclose the points: give it some thickness, or untangle it"
            )

    def _check_orientation(self, flip: bool) -> None:
        """A batch that is inside out everywhere is flipped (with a warning) when ``flip``; a batch
        whose elements disagree, or any inside-out element when not ``flip``, raises, naming them."""
        batch = self.batch_shape
        vol = self.signed_volume().detach().reshape(-1)
        neg = vol < 0
        if not bool(neg.any()):
            return
        if not bool(neg.all()) or not flip:
            bad = torch.nonzero(neg).flatten()
            what = "signed volume" if self.dim == 3 else "signed area"
            where = "; ".join(_batch_name(int(i), batch).removeprefix(" in ") for i in bad[:10]) or "the cage"
            raise CageOrientationError(
                f"{where} {'is' if bad.numel() == 1 else 'are'} inside out (negative {what}) for these faces, "
                f"while the others are outward ({bad.numel()} of {vol.numel()}); reverse the corner order of "
                "the faces only when every cage is inside out, or fix the vertices of those elements"
            )
        if self.dim == 3:
            warnings.warn(
                "the cage is oriented inward (negative signed volume); its faces were flipped so that "
                "normals point outward",
                stacklevel=4,
            )
            self.triangles = self.triangles[:, [0, 2, 1]]
            self.quads = self.quads[:, [0, 3, 2, 1]]
        else:
            warnings.warn(
                "the 2D cage runs clockwise (negative signed area); its edges were reversed so that it runs "
                "counter-clockwise (vertex order, and so the order of the coordinates, is unchanged)",
                stacklevel=4,
            )
            self.edges = self.edges[:, [1, 0]]

    def _check_areas_3d(self, v: torch.Tensor, scales: torch.Tensor, batch: torch.Size) -> None:
        """Zero-area triangles and quads of vertices ``v`` ``(B, V, 3)``, per batch element."""
        tri, quads = self.triangles, self.quads
        tol = DEGENERATE_TOLERANCE * scales[:, None] ** 2
        checks = []
        if tri.shape[0]:
            p = v[:, tri]  # (B, T, 3, 3)
            area = 0.5 * torch.linalg.cross(p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :], dim=-1).norm(
                dim=-1
            )
            checks.append(("triangles", area <= tol, "have zero area (corners collinear or coincident)"))
        if quads.shape[0]:
            p = v[:, quads]  # (B, Q, 4, 3)

            def tri_area(i: int, j: int, k: int) -> torch.Tensor:
                return torch.linalg.cross(p[..., j, :] - p[..., i, :], p[..., k, :] - p[..., i, :], dim=-1).norm(dim=-1)

            area = torch.minimum(tri_area(0, 1, 2) + tri_area(0, 2, 3), tri_area(1, 2, 3) + tri_area(1, 3, 0)) * 0.5
            checks.append(("quads", area <= tol, "have zero area"))
        for name, bad, why in checks:
            if bool(bad.any()):
                b = int(torch.nonzero(bad.any(dim=1))[0])
                raise DegenerateFaceError(
                    f"{name} {torch.nonzero(bad[b]).flatten()[:10].tolist()}{_batch_name(b, batch)} {why}; "
                    "remove them or move their vertices apart"
                )

    def _validate_topology_3d(self) -> None:
        key = self._topology_key()
        if key is not None and key in _TOPOLOGY_SEEN:
            return  # (these faces passed before: the checks below depend on nothing else)
        self._check_topology_3d()
        if key is not None:
            if len(_TOPOLOGY_SEEN) >= _TOPOLOGY_CACHE_SIZE:
                _TOPOLOGY_SEEN.pop(next(iter(_TOPOLOGY_SEEN)))
            _TOPOLOGY_SEEN[key] = self._unique_edges()

    def _check_topology_3d(self) -> None:
        tri, quads = self.triangles, self.quads
        # Directed half-edges: face k contributes (f[i], f[i+1]).
        polys = [tri, quads]
        src, dst, owner = [], [], []
        offset = 0
        for f in polys:
            if f.shape[0] == 0:
                continue
            src.append(f.reshape(-1))
            dst.append(f.roll(-1, dims=1).reshape(-1))
            owner.append(torch.arange(f.shape[0], device=f.device).repeat_interleave(f.shape[1]) + offset)
            offset += f.shape[0]
        s, d, o = torch.cat(src).cpu(), torch.cat(dst).cpu(), torch.cat(owner).cpu()
        V = self.num_vertices
        lo, hi = torch.minimum(s, d), torch.maximum(s, d)
        key = lo * V + hi
        uniq, counts = torch.unique(key, return_counts=True)
        if bool((counts != 2).any()):
            bad = uniq[counts != 2]
            cnt = counts[counts != 2]
            pairs = [(int(k) // V, int(k) % V, int(c)) for k, c in zip(bad[:10], cnt[:10], strict=True)]
            kind = "open (boundary edges used by one face)" if bool((cnt == 1).any()) else "non-manifold"
            desc = ", ".join(f"({a}, {b}) used by {c} face(s)" for a, b, c in pairs)
            raise CageTopologyError(
                f"the cage is {kind}: every edge must be shared by exactly two faces, but edges {desc}; "
                "close holes and split non-manifold edges"
            )
        # Orientation: the two half-edges of each undirected edge must run in opposite directions.
        dkey = s * V + d
        same = torch.unique(dkey, return_counts=True)[1]
        if bool((same > 1).any()):
            order = torch.argsort(key, stable=True)
            ks, ds, os_ = key[order], dkey[order], o[order]
            clash = torch.nonzero((ks[0::2] == ks[1::2]) & (ds[0::2] == ds[1::2])).flatten()
            fa, fb = int(os_[0::2][clash[0]]), int(os_[1::2][clash[0]])
            e = int(ks[0::2][clash[0]])
            names = self._face_names()
            raise CageOrientationError(
                f"faces are inconsistently oriented: {names[fa]} and {names[fb]} traverse the shared edge "
                f"({e // V}, {e % V}) in the same direction ({len(clash)} such edges); "
                "reverse the corner order of the wrongly oriented faces so that normals point outward"
            )
        self._check_vertex_fans(s, d, o)

    def _check_vertex_fans(self, src: torch.Tensor, dst: torch.Tensor, owner: torch.Tensor) -> None:
        """Around every vertex the faces must form one fan (a single cycle): two surfaces touching at
        a vertex only (a "bowtie") pass the edge checks but are not manifold there.

        Walks around each vertex once through the half-edges (validation only, linear in the
        number of corners)."""
        s, d, o = src.tolist(), dst.tolist(), owner.tolist()
        face_of = {(a, b): f for a, b, f in zip(s, d, o, strict=True)}
        # For the corner of face f at vertex v: its outgoing half-edge (v, b) and incoming (a, v).
        incoming = {(f, b): a for a, b, f in zip(s, d, o, strict=True)}
        corners: dict[int, list[int]] = {}
        for a, f in zip(s, o, strict=True):
            corners.setdefault(a, []).append(f)
        for v, faces in corners.items():
            start = faces[0]
            f, seen = start, 0
            while True:
                seen += 1
                prev = incoming[(f, v)]  # face f enters v from prev; the next face leaves v towards prev
                f = face_of[(v, prev)]
                if f == start or seen > len(faces):
                    break
            if seen != len(faces):
                raise CageTopologyError(
                    f"the cage is non-manifold at vertex {v}: its {len(faces)} faces form more than one fan "
                    f"(surfaces touching at a single vertex); give each fan its own copy of the vertex"
                )

    def _face_names(self) -> list[str]:
        T = self.triangles.shape[0]
        return [f"triangle {k}" for k in range(T)] + [f"quad {k}" for k in range(self.quads.shape[0])]

    def _validate_topology_2d(self) -> None:
        e = self.edges
        V = self.num_vertices
        used = torch.zeros(V, dtype=torch.bool, device=e.device)
        used[e.reshape(-1)] = True
        outdeg = torch.bincount(e[:, 0].cpu(), minlength=V)
        indeg = torch.bincount(e[:, 1].cpu(), minlength=V)
        undirected = torch.bincount(e.reshape(-1).cpu(), minlength=V)
        badv = torch.nonzero((undirected != 2) & used.cpu()).flatten()
        if badv.numel():
            raise CageTopologyError(
                f"the polygon is open or non-manifold at vertices {badv[:10].tolist()}: every vertex "
                "must lie on exactly two edges; close the polygon and remove dangling or branching edges"
            )
        badv = torch.nonzero((outdeg != indeg) | ((outdeg != 1) & used.cpu())).flatten()
        if badv.numel():
            k = int(badv[0])
            ab = torch.nonzero((e[:, 0] == k) | (e[:, 1] == k)).flatten().tolist()
            raise CageOrientationError(
                f"edges {ab} meet at vertex {k} with inconsistent directions (both start or both end "
                "there); give every closed polygon as a consistent loop (one edge in, one edge out)"
            )
