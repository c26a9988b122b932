"""The editor's HTTP server: the page, its static files and the scripting API, on the standard
library's threading HTTP server (one thread per request, no dependency).

Routes (JSON unless said otherwise; errors answer ``{"error": message}`` with 400, 404, 409 (the
coordinates failed or are still computing) or 413, and the server keeps serving):

- ``GET /``: the editor page; ``GET /static/<file>``: its script and the vendored three.js.
- ``GET /api/scene``: ``{"cage": {"vertices", "faces", "edges", "rest"}, "mesh": {"vertices",
  "faces"}, "method", "status", "version", ...}`` (the current pose and deformed mesh).
- ``GET /api/status``: the computation's state and progress, the pose ``version``.
- ``GET /api/pose``: ``{"vertices": cage pose, "version"}``; ``GET /api/deformed``: the deformed
  mesh, ``{"vertices"}``, or raw little-endian float32 with ``?format=f32``.
- ``POST /api/pose`` ``{"vertices": [[x, y, z], ...]}``: sets the pose, answers the deformed mesh
  ``{"vertices", "version"}`` (``?format=f32``: raw float32, the version in ``X-Pose-Version``;
  ``?wait=0``: answer 202 at once while the coordinates compute).
- ``POST /api/method`` ``{"method": "qmvc"}``: recompute (202; follow ``/api/status``).
- ``POST /api/save`` ``{"prefix": "deformed"}`` (optional): writes the OBJ files, answers their paths.
- ``POST /api/load``: the text of a deformed cage OBJ file; sets the pose like ``/api/pose``.

Examples:
    >>> import json, urllib.request, torch, torchcage
    >>> from torchcage.viewer import EditorServer, EditorSession
    >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj"))
    >>> session = EditorSession(torch.zeros(1, 3), torch.zeros(0, 3, dtype=torch.long), cage, background=False)
    >>> server = EditorServer(session).start()
    >>> body = json.dumps({"vertices": (cage.vertices + 1).tolist()}).encode()
    >>> with urllib.request.urlopen(urllib.request.Request(server.url + "api/pose", data=body)) as r:
    ...     json.load(r)["vertices"]
    [[1.0, 1.0, 1.0]]
    >>> server.close()
"""

from __future__ import annotations

import json
import sys
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any
from urllib.parse import parse_qs, urlsplit

import numpy as np

from .session import CoordinatesError, EditorError, EditorSession

__all__ = ["MAX_BODY", "EditorServer"]

#: The largest request body accepted (a pose of a million cage vertices fits).
MAX_BODY = 64 * 1024 * 1024
_STATIC = {
    "index.html": "text/html; charset=utf-8",
    "editor.js": "text/javascript; charset=utf-8",
    "editor.css": "text/css; charset=utf-8",
    "vendor/three.module.min.js": "text/javascript; charset=utf-8",
}


class _RequestError(Exception):
    def __init__(self, status: HTTPStatus, message: str) -> None:
        super().__init__(message)
        self.status = status


def _static(name: str) -> bytes:
    return resources.files("torchcage.viewer").joinpath("static", *name.split("/")).read_bytes()


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    protocol_version = "HTTP/1.1"

    # ------------------------------------------------------------------ plumbing
    def log_message(self, format: str, *args: Any) -> None:
        if self.server.verbose:
            sys.stderr.write(f"torchcage view: {self.address_string()} {format % args}\n")

    def _send(self, status: HTTPStatus, body: bytes, content_type: str, headers: dict[str, str] | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, payload: Any, status: HTTPStatus = HTTPStatus.OK) -> None:
        body = json.dumps(payload, allow_nan=False, separators=(",", ":")).encode()
        self._send(status, body, "application/json")

    def _error(self, status: HTTPStatus, message: str) -> None:
        self._json({"error": message}, status)

    def _body(self) -> bytes:
        try:
            length = int(self.headers.get("Content-Length", "0"))
        except ValueError:
            raise _RequestError(HTTPStatus.BAD_REQUEST, "Content-Length is not a number") from None
        if length < 0:
            raise _RequestError(HTTPStatus.BAD_REQUEST, "Content-Length is negative")
        if length > MAX_BODY:
            self.close_connection = True  # the body is left unread
            raise _RequestError(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"the body is over {MAX_BODY} bytes")
        return self.rfile.read(length)

    def _json_body(self) -> dict[str, Any]:
        raw = self._body()
        if not raw.strip():
            return {}
        try:
            data = json.loads(raw)  # NaN and Infinity read as floats, then refused as a pose
        except (UnicodeDecodeError, json.JSONDecodeError) as err:
            raise _RequestError(HTTPStatus.BAD_REQUEST, f"the body is not JSON: {err}") from None
        if not isinstance(data, dict):
            raise _RequestError(HTTPStatus.BAD_REQUEST, f"the body must be a JSON object, got {type(data).__name__}")
        return data

    def _dispatch(self, routes: dict[str, Any]) -> None:
        url = urlsplit(self.path)
        query = {k: v[-1] for k, v in parse_qs(url.query).items()}
        route = routes.get(url.path)
        try:
            if route is None:
                if url.path.startswith("/static/") and self.command in ("GET", "HEAD"):
                    return self._serve_static(url.path[len("/static/") :])
                raise _RequestError(HTTPStatus.NOT_FOUND, f"no route {self.command} {url.path}")
            route(query)
        except _RequestError as err:
            self._error(err.status, str(err))
        except CoordinatesError as err:  # the request was fine; the coordinates cannot serve it
            self._error(HTTPStatus.CONFLICT, str(err))
        except (EditorError, ValueError, TypeError) as err:
            self._error(HTTPStatus.BAD_REQUEST, str(err))
        except (BrokenPipeError, ConnectionResetError):  # the client went away
            self.close_connection = True
        except Exception as err:  # never let one request take the server down
            self._error(HTTPStatus.INTERNAL_SERVER_ERROR, f"{type(err).__name__}: {err}")

    def do_GET(self) -> None:
        self._dispatch(
            {
                "/": lambda q: self._serve_static("index.html"),
                "/index.html": lambda q: self._serve_static("index.html"),
                "/api/scene": lambda q: self._json(self.server.session.scene()),
                "/api/status": lambda q: self._json(self.server.session.status().as_dict()),
                "/api/pose": self._get_pose,
                "/api/deformed": self._get_deformed,
            }
        )

    def do_HEAD(self) -> None:
        self.do_GET()

    def do_POST(self) -> None:
        self._dispatch(
            {
                "/api/pose": self._post_pose,
                "/api/method": self._post_method,
                "/api/save": self._post_save,
                "/api/load": self._post_load,
            }
        )

    # ------------------------------------------------------------------ routes
    def _serve_static(self, name: str) -> None:
        if name not in _STATIC:
            raise _RequestError(HTTPStatus.NOT_FOUND, f"no file {name!r}")
        self._send(HTTPStatus.OK, _static(name), _STATIC[name])

    def _get_pose(self, query: dict[str, str]) -> None:
        pose, version = self.server.session.snapshot()
        self._json({"vertices": pose.tolist(), "version": version})

    def _answer_mesh(self, deformed: Any, version: int, query: dict[str, str]) -> None:
        if deformed is None:
            status = self.server.session.status()
            self._json({"vertices": None, "version": version, "status": status.as_dict()}, HTTPStatus.ACCEPTED)
        elif query.get("format") == "f32":
            body = np.ascontiguousarray(deformed.numpy(), dtype="<f4").tobytes()
            self._send(HTTPStatus.OK, body, "application/octet-stream", {"X-Pose-Version": str(version)})
        else:
            self._json({"vertices": deformed.tolist(), "version": version})

    def _get_deformed(self, query: dict[str, str]) -> None:
        session = self.server.session
        pose, version = session.snapshot()
        self._answer_mesh(session.deform(pose, wait=query.get("wait") != "0"), version, query)

    def _post_pose(self, query: dict[str, str]) -> None:
        data = self._json_body()
        if "vertices" not in data:
            raise _RequestError(HTTPStatus.BAD_REQUEST, 'the body must be {"vertices": [[x, y, z], ...]}')
        version, deformed = self.server.session.post_pose(data["vertices"], wait=query.get("wait") != "0")
        self._answer_mesh(deformed, version, query)

    def _post_method(self, query: dict[str, str]) -> None:
        method = self._json_body().get("method")
        if not isinstance(method, str):
            raise _RequestError(HTTPStatus.BAD_REQUEST, 'the body must be {"method": "mvc" | "qmvc" | ...}')
        self._json(self.server.session.set_method(method).as_dict(), HTTPStatus.ACCEPTED)

    def _post_save(self, query: dict[str, str]) -> None:
        prefix = self._json_body().get("prefix", "deformed")
        self._json(self.server.session.save(prefix))

    def _post_load(self, query: dict[str, str]) -> None:
        raw = self._body()
        try:
            text = raw.decode()
        except UnicodeDecodeError:
            raise _RequestError(HTTPStatus.BAD_REQUEST, "the body must be the text of an OBJ file (UTF-8)") from None
        if text.lstrip().startswith("{"):
            try:
                text = json.loads(text)["obj"]
            except (json.JSONDecodeError, KeyError, TypeError):
                raise _RequestError(HTTPStatus.BAD_REQUEST, 'a JSON body must be {"obj": "<OBJ text>"}') from None
        session = self.server.session
        deformed = session.load_pose_obj(text, wait=query.get("wait") != "0")
        pose, version = session.snapshot()
        mesh = None if deformed is None else deformed.tolist()
        self._json({"cage": pose.tolist(), "vertices": mesh, "version": version})


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, address: tuple[str, int], session: EditorSession, verbose: bool) -> None:
        super().__init__(address, _Handler)
        self.session = session
        self.verbose = verbose


class EditorServer:
    """Serve an :class:`EditorSession` at ``http://host:port/``.

    Args:
        session: the editor's state.
        host: the address to listen on (loopback by default: the editor has no authentication).
        port: the port; ``0`` picks a free one (see :attr:`url`).
        verbose: log each request on stderr.

    Raises:
        OSError: the address is in use or cannot be bound (the message names it).
    """

    def __init__(self, session: EditorSession, host: str = "127.0.0.1", port: int = 0, *, verbose: bool = False):
        try:
            self._httpd = _Server((host, port), session, verbose)
        except OSError as err:
            raise OSError(f"cannot listen on {host}:{port}: {err.strerror or err}; choose another --port") from None
        self.session = session
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        """The page's address, ``http://host:port/``."""
        host, port = self._httpd.server_address[:2]
        shown = "127.0.0.1" if host in ("0.0.0.0", "") else ("[::1]" if host == "::" else host)
        return f"http://{shown}:{port}/"

    def start(self) -> EditorServer:
        """Serve in a daemon thread; return ``self``."""
        self._thread = threading.Thread(target=self._httpd.serve_forever, name="torchcage-view", daemon=True)
        self._thread.start()
        return self

    def serve_forever(self) -> None:
        """Serve in this thread until :meth:`close` (or Ctrl+C)."""
        self._httpd.serve_forever()

    def close(self) -> None:
        """Stop serving and free the port."""
        self._httpd.shutdown()
        self._httpd.server_close()
        if self._thread is not None:
            self._thread.join(timeout=5)
