"""The editor's state, apart from any server or page: a mesh, its cage, the current pose and the
coordinates of one method, computed once in a background thread with progress.

Every method is thread-safe: the HTTP server answers each request on its own thread, and a
script may hold the same session through :class:`torchcage.viewer.Viewer`.

Examples:
    >>> import torch, torchcage
    >>> from torchcage.viewer import EditorSession
    >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj"))
    >>> points = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.5, 0.5]], dtype=torch.float64)
    >>> session = EditorSession(points, torch.zeros(0, 3, dtype=torch.long), cage, background=False)
    >>> deformed = session.set_pose(cage.vertices * 2 + 1)   # scale by 2, shift by 1
    >>> torch.allclose(deformed, points * 2 + 1)
    True
"""

from __future__ import annotations

import re
import tempfile
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import torch

from torchcage.cage import Cage
from torchcage.errors import CageError
from torchcage.families import family
from torchcage.methods import METHOD_NAMES, METHODS, build_module

__all__ = ["PREFIX_RULE", "CoordinatesError", "EditorError", "EditorSession", "PoseError", "Status", "check_prefix"]

#: A save prefix: a portable file name (letters, digits, ``.``, ``_``, ``-``; a letter or digit first).
_PREFIX = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
#: Device names that Windows refuses as a file name's stem, with or without an extension.
_RESERVED = frozenset(
    ["con", "prn", "aux", "nul", *(f"com{i}" for i in range(1, 10)), *(f"lpt{i}" for i in range(1, 10))]
)
#: What :func:`check_prefix` allows, in words (its error says it).
PREFIX_RULE = (
    "1 to 64 characters: letters, digits, '.', '_' and '-', starting with a letter or digit, not ending "
    "with '.', without '..', and not a Windows device name (CON, PRN, AUX, NUL, COM1-9, LPT1-9)"
)


class EditorError(ValueError):
    """The editor cannot do what was asked: the coordinates failed or are not ready, or a file
    cannot be written; the message names the cause and the fix."""


class CoordinatesError(EditorError):
    """The coordinates cannot serve a pose: their computation failed (choose another method) or
    has not finished in time (retry)."""


class PoseError(EditorError):
    """A deformed cage that does not fit the rest cage: wrong vertex count, non-finite values,
    other faces."""


def check_prefix(prefix: object) -> str:
    """``prefix`` if it is a portable file-name prefix (see :data:`PREFIX_RULE`).

    Raises:
        EditorError: any other prefix (``-rf``, ``CON``, ``con.obj``, ``x..``, ``a/b``, ``''``), naming the rule.

    Examples:
        >>> check_prefix("pose_01")
        'pose_01'
    """
    ok = (
        isinstance(prefix, str)
        and _PREFIX.match(prefix) is not None
        and not prefix.endswith(".")
        and ".." not in prefix
        and prefix.split(".")[0].lower() not in _RESERVED
    )
    if not ok:
        raise EditorError(f"a save prefix must be a plain file name, {PREFIX_RULE}; got {prefix!r}")
    return str(prefix)


@dataclass
class Status:
    """Where the coordinates stand (what ``GET /api/status`` answers).

    Attributes:
        method: the method whose coordinates are (being) computed.
        state: ``"computing"``, ``"ready"`` or ``"failed"``.
        done, total: progress (points, or solver iterations with ``total`` ``None``).
        message: a line for people: progress, or the error with its fix.
        seconds: time spent on the current computation.
        version: pose counter, raised by every new pose.
        coordinates: counter raised each time a computation finishes.
        warnings: the warnings the computation raised (points outside a Green cage, ...).
    """

    method: str
    state: str
    done: int = 0
    total: int | None = None
    message: str = ""
    seconds: float = 0.0
    version: int = 0
    coordinates: int = 0
    warnings: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__, method_name=METHOD_NAMES[self.method])


class _SupersededError(Exception):
    """Raised inside a computation's progress report when another method was chosen meanwhile."""


def _as_mesh(vertices: Any, faces: Any) -> tuple[torch.Tensor, torch.Tensor]:
    v = torch.as_tensor(vertices).detach().to("cpu", torch.float64)
    f = torch.as_tensor(faces).detach().to("cpu")
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise ValueError(f"the editor's mesh vertices must have shape (N, 3) with N >= 1, got {tuple(v.shape)}")
    if not bool(torch.isfinite(v).all()):
        raise ValueError("the mesh vertices contain NaN or inf; clean the mesh first")
    if f.is_floating_point() or f.ndim != 2 or f.shape[1] not in (3, 4):
        raise ValueError(f"the editor's mesh faces must be integer (F, 3) or (F, 4), got {tuple(f.shape)} {f.dtype}")
    f = f.long()
    if f.numel() and (int(f.min()) < 0 or int(f.max()) >= v.shape[0]):
        raise ValueError(f"mesh face indices must lie in [0, {v.shape[0]}), got {int(f.min())}..{int(f.max())}")
    if f.shape[1] == 4:  # shown and written as triangles
        f = torch.cat([f[:, [0, 1, 2]], f[:, [0, 2, 3]]])
    return v, f


class EditorSession:
    """A mesh embedded in a cage, a current pose of the cage and the deformed mesh it gives.

    The coordinates of the mesh vertices are computed once per method, in a background thread
    (``background=True``) whose progress :meth:`status` reports; each pose is then one product
    (:meth:`deform`).

    Args:
        mesh_vertices: ``(N, 3)`` mesh vertices.
        mesh_faces: ``(F, 3)`` (or ``(F, 4)``, split for display) integer faces; ``(0, 3)`` for a
            point cloud.
        cage: the rest cage (3D, one cage: a batched or 2D cage raises ``ValueError``).
        method: one of :data:`torchcage.methods.METHODS`.
        pose: ``(V, 3)`` initial deformed vertices (default: the rest cage).
        out_dir: the folder :meth:`save` writes into.
        up: the mesh's up axis, ``"x"``, ``"y"`` or ``"z"`` (for the page's camera).
        background: compute the coordinates in a thread (``False``: in the constructor).

    Raises:
        ValueError: an unusable mesh, cage, method or pose (with the fix).
    """

    def __init__(
        self,
        mesh_vertices: torch.Tensor,
        mesh_faces: torch.Tensor,
        cage: Cage,
        *,
        method: str = "mvc",
        pose: torch.Tensor | None = None,
        out_dir: str | Path = ".",
        up: str = "z",
        background: bool = True,
    ) -> None:
        if not isinstance(cage, Cage):
            raise TypeError(f"cage must be a torchcage.Cage, got {type(cage).__name__}")
        if cage.dim != 3 or cage.is_batched:
            raise ValueError(
                f"the editor shows one 3D cage, got {cage!r}; for 2D cages see torchcage.image, for a batch "
                "edit one element (cage.unbind())"
            )
        if up not in ("x", "y", "z"):
            raise ValueError(f"up must be 'x', 'y' or 'z', got {up!r}")
        self.mesh_vertices, self.mesh_faces = _as_mesh(mesh_vertices, mesh_faces)
        self.cage = cage.with_vertices(cage.vertices.detach().to("cpu", torch.float64))
        self.out_dir = Path(out_dir)
        self.up = up
        self._lock = threading.Condition(threading.RLock())
        self._pose = self.cage.vertices.clone()
        self._version = 0
        self._module: torch.nn.Module | None = None
        self._status = Status(method=method, state="computing")
        self._token = 0
        self._outside: int | None = None
        self._started = time.perf_counter()
        if pose is not None:
            self._pose = self._check_pose(pose)
        self.set_method(method, wait=not background)

    # ------------------------------------------------------------------ coordinates
    def set_method(self, method: str, *, wait: bool = False) -> Status:
        """Compute the coordinates of ``method`` (in a background thread unless ``wait``).

        A computation still running for another method is abandoned at its next progress report.

        Raises:
            ValueError: an unknown method.
            CoordinatesError: with ``wait``, the computation failed.
        """
        method = family(method).short
        with self._lock:
            self._token += 1
            token = self._token
            self._module = None
            self._started = time.perf_counter()
            self._status = Status(
                method=method,
                state="computing",
                message="starting",
                version=self._version,
                coordinates=self._status.coordinates,
            )
        if wait:
            self._compute(method, token)
            status = self.status()
            if status.state == "failed":
                raise CoordinatesError(status.message)
            return status
        threading.Thread(target=self._compute, args=(method, token), name=f"torchcage-{method}", daemon=True).start()
        return self.status()

    def _compute(self, method: str, token: int) -> None:
        def progress(done: int, total: int | None, message: str) -> None:
            with self._lock:
                if token != self._token:
                    raise _SupersededError
                self._status.done, self._status.total, self._status.message = done, total, message

        try:
            # (no warnings.catch_warnings here: it swaps process-wide state under other threads' feet;
            # the modules' own warnings reach stderr, and the outside count below reaches the page)
            module = build_module(method, self.cage, self.mesh_vertices, progress=progress)
            notes = self._outside_note()
        except _SupersededError:
            return
        except Exception as err:  # reported to the page and the scripts, never raised in the thread
            with self._lock:
                if token == self._token:
                    self._status.state = "failed"
                    self._status.message = f"{METHOD_NAMES[method]} failed: {err}"
                    self._status.seconds = time.perf_counter() - self._started
                    self._lock.notify_all()
            return
        with self._lock:
            if token != self._token:
                return
            self._module = module
            n = self.mesh_vertices.shape[0]
            self._status.state = "ready"
            self._status.done, self._status.total = n, n
            self._status.seconds = time.perf_counter() - self._started
            self._status.message = f"{METHOD_NAMES[method]} of {n:,} points in {self._status.seconds:.1f} s"
            self._status.warnings = notes
            self._status.coordinates += 1
            self._lock.notify_all()

    def _outside_note(self) -> list[str]:
        """A line for the page when mesh vertices lie outside the rest cage (winding numbers)."""
        from torchcage.geometry import inside_cage

        if self._outside is None:  # (once; outside the lock: requests go on meanwhile)
            self._outside = int((~inside_cage(self.mesh_vertices, self.cage)).sum())
        if not self._outside:
            return []
        return [
            f"{self._outside:,} of {self.mesh_vertices.shape[0]:,} mesh vertices lie outside the cage: Green "
            "coordinates extrapolate them, MEC refuses them; enlarge the cage (torchcage.make_cage) to enclose them"
        ]

    def status(self) -> Status:
        """A snapshot of the computation's state and the pose version."""
        with self._lock:
            s = replace(self._status, warnings=list(self._status.warnings))  # a copy that later progress leaves alone
            s.version = self._version
            if s.state == "computing":
                s.seconds = time.perf_counter() - self._started
            return s

    def wait(self, timeout: float | None = None) -> Status:
        """Block until the coordinates are computed (or failed); return the status.

        Raises:
            TimeoutError: still computing after ``timeout`` seconds.
        """
        with self._lock:
            if not self._lock.wait_for(lambda: self._status.state != "computing", timeout):
                raise TimeoutError(f"the coordinates are still computing after {timeout} s ({self._status.message})")
        return self.status()

    # ------------------------------------------------------------------ poses
    @property
    def pose(self) -> torch.Tensor:
        """The current deformed cage vertices ``(V, 3)`` (a copy)."""
        with self._lock:
            return self._pose.clone()

    @property
    def version(self) -> int:
        """The pose counter: raised by every :meth:`set_pose`."""
        with self._lock:
            return self._version

    def _check_pose(self, vertices: Any) -> torch.Tensor:
        V = self.cage.num_vertices
        try:
            pose = torch.as_tensor(vertices, dtype=torch.float64).detach().to("cpu").clone()
        except (TypeError, ValueError, RuntimeError) as err:
            raise PoseError(f"a pose must be {V} vertices [[x, y, z], ...] of numbers: {err}") from None
        if pose.shape != (V, 3):
            raise PoseError(f"a pose must have shape ({V}, 3) for this cage, got {tuple(pose.shape)}")
        if not bool(torch.isfinite(pose).all()):
            bad = torch.nonzero(~torch.isfinite(pose).all(dim=1)).flatten()[:10].tolist()
            raise PoseError(f"the pose has NaN or inf coordinates at vertices {bad}; send finite numbers")
        return pose

    def snapshot(self) -> tuple[torch.Tensor, int]:
        """The current pose ``(V, 3)`` (a copy) and its version, read together."""
        with self._lock:
            return self._pose.clone(), self._version

    def set_pose(self, vertices: Any, *, wait: bool | float = True) -> torch.Tensor | None:
        """Make ``vertices`` ``(V, 3)`` the current pose; return the deformed mesh ``(N, 3)``.

        Args:
            vertices: the deformed cage vertices (tensor, array or nested lists).
            wait: while the coordinates compute, wait for them (``True``, or at most this many
                seconds) or return ``None`` at once (``False``); the pose is kept either way.

        Raises:
            PoseError: a pose of the wrong shape, or with NaN or inf.
            CoordinatesError: the coordinates failed (choose another method).
        """
        return self.post_pose(vertices, wait=wait)[1]

    def post_pose(self, vertices: Any, *, wait: bool | float = True) -> tuple[int, torch.Tensor | None]:
        """:meth:`set_pose`, also returning the version this pose got (for the page, which must
        tell its own poses from a script's)."""
        pose = self._check_pose(vertices)
        with self._lock:
            self._pose = pose
            self._version += 1
            version = self._version
        return version, self.deform(pose, wait=wait)

    def deform(self, pose: torch.Tensor | None = None, *, wait: bool | float = True) -> torch.Tensor | None:
        """The mesh deformed by ``pose`` (default: the current pose), ``(N, 3)`` float64; ``None``
        when the coordinates are not ready and ``wait`` is ``False``.

        Raises:
            CoordinatesError: the coordinates failed, or did not finish within ``wait`` seconds.
        """
        pose = self.pose if pose is None else self._check_pose(pose)
        with self._lock:
            if wait is not False and self._status.state == "computing":
                timeout = None if wait is True else float(wait)
                if not self._lock.wait_for(lambda: self._status.state != "computing", timeout):
                    raise CoordinatesError(f"the coordinates are still computing ({self._status.message}); retry later")
            if self._status.state == "failed":
                raise CoordinatesError(f"{self._status.message}; choose another method")
            module = self._module
        if module is None:
            return None
        with torch.no_grad():
            return module(pose)

    def load_pose_obj(self, text: str, *, wait: bool | float = True) -> torch.Tensor | None:
        """Take the pose from the text of a deformed cage OBJ file (the rest cage's faces).

        Raises:
            PoseError: the file does not read as a cage with the rest cage's faces.
        """
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "pose.obj"
            path.write_text(text)
            from torchcage.io import load_cage

            try:
                other = load_cage(path, dim=3, check_intersections=False)  # a pose may fold through itself
            except CageError as err:
                raise PoseError(f"the file is not a cage: {str(err).replace(str(path), 'the file')}") from None
        if other.num_vertices != self.cage.num_vertices or not (
            torch.equal(other.triangles, self.cage.triangles) and torch.equal(other.quads, self.cage.quads)
        ):
            raise PoseError(
                f"the loaded cage must have the rest cage's faces and {self.cage.num_vertices} vertices, got "
                f"{other.num_vertices} vertices, {other.triangles.shape[0]} triangles and {other.quads.shape[0]} quads"
            )
        return self.set_pose(other.vertices, wait=wait)

    def save(self, prefix: str = "deformed") -> dict[str, str]:
        """Write ``<prefix>_cage.obj`` (quads kept) and ``<prefix>_mesh.obj`` into ``out_dir``.

        Returns:
            ``{"cage": path, "mesh": path}``.

        Raises:
            EditorError: a prefix that is not a portable file name (see :func:`check_prefix`), or
                coordinates not ready.
        """
        from torchcage.io import save_cage, save_mesh

        check_prefix(prefix)
        pose = self.pose
        deformed = self.deform(pose, wait=60.0)
        if deformed is None:  # pragma: no cover - deform waits or raises
            raise CoordinatesError("the coordinates are not ready; retry when they are")
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            paths = {"cage": self.out_dir / f"{prefix}_cage.obj", "mesh": self.out_dir / f"{prefix}_mesh.obj"}
            save_cage(paths["cage"], self.cage, pose)
            save_mesh(paths["mesh"], deformed, self.mesh_faces)
        except OSError as err:
            raise EditorError(f"cannot write into {self.out_dir}: {err}; choose another --out folder") from None
        return {k: str(p.resolve()) for k, p in paths.items()}

    # ------------------------------------------------------------------ what the page shows
    def scene(self) -> dict[str, Any]:
        """The scene as JSON-ready lists: the current pose and its deformed mesh (the rest mesh
        while the coordinates compute), faces, edges, the rest cage, method and status."""
        pose = self.pose
        try:
            deformed = self.deform(pose, wait=False)
        except CoordinatesError:  # the coordinates failed: the page shows the rest mesh and the message
            deformed = None
        status = self.status()
        mesh = self.mesh_vertices if deformed is None else deformed
        faces = self.cage.faces
        return {
            "cage": {
                "vertices": pose.tolist(),
                "faces": faces if isinstance(faces, list) else faces.tolist(),
                "edges": self.cage.unique_edges().tolist(),
                "rest": self.cage.vertices.tolist(),
            },
            "mesh": {"vertices": mesh.tolist(), "faces": self.mesh_faces.tolist(), "deformed": deformed is not None},
            "method": status.method,
            "methods": {m: METHOD_NAMES[m] for m in METHODS},
            "status": status.as_dict(),
            "version": status.version,
            "up": self.up,
        }
