"""The interactive cage editor in the browser: ``torchcage view`` and :func:`torchcage.view`.

A local HTTP server (standard library) serves one page (three.js, vendored) that shows a mesh and
its cage, lets the user drag, rotate and scale cage vertices, and shows the mesh deform live; the
coordinates are computed once, server side, and each pose is one product. The same server answers
a scripting API (:mod:`torchcage.viewer.server`), and :class:`Viewer` drives it from Python.
Requests that change anything carry the session's secret (:attr:`Viewer.headers`): other web pages
open in the same browser cannot drive the editor.

Examples:
    >>> import torch, torchcage
    >>> cage = torchcage.load_cage(torchcage.data.path("bar_cage.obj"))
    >>> mesh = torchcage.load_mesh(torchcage.data.path("bar.obj"))
    >>> with torchcage.view(mesh, cage) as viewer:  # serves http://127.0.0.1:<port>/
    ...     _ = viewer.wait()
    ...     deformed = viewer.set_pose(viewer.pose * 2)     # what the page shows, too
    ...     torch.allclose(deformed, mesh[0] * 2)
    True
"""

from __future__ import annotations

import errno
import sys
import warnings
import webbrowser
from pathlib import Path
from typing import Any

import torch

from torchcage.cage import Cage
from torchcage.viewer.server import EditorServer, fetch_token
from torchcage.viewer.session import CoordinatesError, EditorError, EditorSession, PoseError, Status

__all__ = [
    "DEFAULT_PORT",
    "CoordinatesError",
    "EditorError",
    "EditorServer",
    "EditorSession",
    "PoseError",
    "Status",
    "Viewer",
    "fetch_token",
    "view",
]

#: The editor's usual port (``torchcage view``); when it is taken, :func:`view` serves on a free
#: one and says so.
DEFAULT_PORT = 8765
_LOOPBACK = ("127.0.0.1", "localhost", "::1")


class Viewer:
    """A running editor: its address, and the pose the user (or a script) made.

    Returned by :func:`torchcage.view`; a context manager that stops the server on exit.

    Attributes:
        url: the page's address.
        session: the :class:`EditorSession` behind the page.
        server: the :class:`EditorServer` (``server.token``: the secret each ``POST`` needs).
    """

    def __init__(self, session: EditorSession, server: EditorServer) -> None:
        self.session = session
        self.server = server
        self.url = server.url

    @property
    def pose(self) -> torch.Tensor:
        """The current deformed cage vertices ``(V, 3)`` float64 (what the page shows)."""
        return self.session.pose

    @property
    def deformed(self) -> torch.Tensor | None:
        """The mesh deformed by the current pose ``(N, 3)``, waiting for the coordinates."""
        return self.session.deform()

    @property
    def token(self) -> str:
        """The session's secret, required in the ``X-Torchcage-Token`` header of every ``POST``."""
        return self.server.token

    @property
    def headers(self) -> dict[str, str]:
        """The headers a script's ``POST`` to :attr:`url` needs (the token, JSON content type)."""
        return self.server.headers

    @property
    def method(self) -> str:
        return self.session.status().method

    def set_pose(self, vertices: torch.Tensor) -> torch.Tensor | None:
        """Set the pose ``(V, 3)`` (the page follows within a second); return the deformed mesh."""
        return self.session.set_pose(vertices)

    def set_method(self, method: str, *, wait: bool = False) -> Status:
        """Recompute the coordinates with another method (see :data:`torchcage.methods.METHODS`)."""
        return self.session.set_method(method, wait=wait)

    def wait(self, timeout: float | None = None) -> Status:
        """Block until the coordinates are computed; return the status."""
        return self.session.wait(timeout)

    def save(self, prefix: str = "deformed") -> dict[str, str]:
        """Write the deformed cage and mesh as OBJ into the output folder; return their paths."""
        return self.session.save(prefix)

    def open(self) -> bool:
        """Open the page in the default web browser; where none opens (``False``), print the
        address to open by hand on stderr."""
        why = ""
        try:
            opened = bool(webbrowser.open(self.url))
        except Exception as err:  # webbrowser.Error, or a browser command that fails to start
            opened, why = False, f" ({type(err).__name__}: {err})"
        if not opened:
            print(f"torchcage view: no web browser could be opened{why}; open {self.url} by hand", file=sys.stderr)
        return opened

    def close(self) -> None:
        """Stop the server."""
        self.server.close()

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _repr_html_(self) -> str:  # a notebook shows the editor inline
        return f'<iframe src="{self.url}" width="100%" height="600" style="border:0"></iframe>'

    def __repr__(self) -> str:
        s = self.session.status()
        return f"Viewer(url={self.url!r}, method={s.method!r}, state={s.state!r}, version={s.version})"


def _load_mesh(mesh: Any) -> tuple[torch.Tensor, torch.Tensor]:
    from torchcage.io import load_mesh

    if isinstance(mesh, (str, Path)):
        return load_mesh(mesh)
    if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        return torch.as_tensor(mesh[0]), torch.as_tensor(mesh[1])
    if isinstance(mesh, torch.Tensor):  # a point cloud
        return mesh, torch.zeros(0, 3, dtype=torch.long)
    raise TypeError(f"mesh must be a path, a (vertices, faces) pair or a (N, 3) tensor, got {type(mesh).__name__}")


def view(
    mesh: Any,
    cage: Cage | str | Path,
    *,
    method: str = "mvc",
    pose: torch.Tensor | str | Path | None = None,
    host: str = "127.0.0.1",
    port: int = 0,
    out: str | Path = ".",
    up: str = "z",
    open_browser: bool = False,
    verbose: bool = False,
    fallback: bool | None = None,
    timeout: float | None = None,
    allowed_hosts: tuple[str, ...] | list[str] = (),
) -> Viewer:
    """Start the cage editor on ``mesh`` and ``cage``; return a :class:`Viewer` (the server runs
    in a background thread until :meth:`Viewer.close`).

    Args:
        mesh: a mesh file, a ``(vertices (N, 3), faces (F, 3))`` pair, or ``(N, 3)`` points.
        cage: a :class:`~torchcage.Cage` or a cage OBJ file (quads kept).
        method: the coordinates (see :data:`torchcage.methods.METHODS`); computed in the
            background, with progress on the page.
        pose: an initial deformed cage: ``(V, 3)`` vertices or an OBJ file with the cage's faces.
        host: the address to listen on; anything but loopback warns (anyone who can reach the
            server can open the page, and with it the session's token, and write files into ``out``).
        port: the port (``0``: a free one).
        out: the folder that Save writes into.
        up: the mesh's up axis (``"x"``, ``"y"``, ``"z"``).
        open_browser: open the page in the default browser (where none opens, the address to
            open by hand is printed on stderr).
        verbose: log each request, and each client that drops, on stderr.
        fallback: when ``port`` is taken, serve on a free port instead and say so on stderr
            (default: only for :data:`DEFAULT_PORT`; another taken port raises ``OSError``).
        timeout: seconds a connection may stay silent before it is dropped (default
            :data:`torchcage.viewer.server.DEFAULT_TIMEOUT`).
        allowed_hosts: more ``host:port`` names the server answers to (e.g. ``"localhost:9000"``
            behind a port forward to another local port); the page refuses any other.

    Returns:
        The running :class:`Viewer`; ``viewer.url`` is the page.

    Raises:
        ValueError: an unusable mesh, cage, pose or method (with the fix).
        OSError: the port cannot be bound (or is taken, without ``fallback``).
    """
    from torchcage.io import load_cage

    if not isinstance(cage, Cage):
        cage = load_cage(cage)
    vertices, faces = _load_mesh(mesh)
    session = EditorSession(vertices, faces, cage, method=method, out_dir=out, up=up)
    if isinstance(pose, (str, Path)):
        session.load_pose_obj(Path(pose).read_text(), wait=False)
    elif pose is not None:
        session.set_pose(pose, wait=False)
    if host not in _LOOPBACK:
        warnings.warn(
            f"the editor listens on {host}: anyone who can reach it can open the page (and with it the session's "
            f"token), read the mesh and write files into {Path(out).resolve()}; it has no other authentication "
            "(use the default 127.0.0.1 and a port forward)",
            UserWarning,
            stacklevel=2,
        )
    options: dict[str, Any] = {"verbose": verbose, "allowed_hosts": allowed_hosts}
    if timeout is not None:
        options["timeout"] = timeout
    try:
        server = EditorServer(session, host, port, **options)
    except OSError as err:
        if not (fallback if fallback is not None else port == DEFAULT_PORT) or port == 0:
            raise
        server = EditorServer(session, host, 0, **options)
        taken = "is in use" if err.errno == errno.EADDRINUSE else f"cannot be used ({err})"
        print(f"torchcage view: port {port} {taken}; serving on {server.url}", file=sys.stderr, flush=True)
    viewer = Viewer(session, server.start())
    if open_browser:
        viewer.open()
    return viewer
