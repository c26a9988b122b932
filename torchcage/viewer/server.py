"""The editor's HTTP server: the page, its static files and the scripting API, on the standard
library's HTTP server (a bounded pool of handler threads, no dependency).

Routes (JSON unless said otherwise; errors answer ``{"error": message}`` with 400, 403, 404, 409
(the coordinates failed or are still computing), 411, 413, 415 or 503, and the server keeps serving):

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
- ``POST /api/load`` ``{"obj": "<the text of a deformed cage OBJ file>"}``: sets the pose like
  ``/api/pose``.

Security (any web page open in the user's browser can send requests to a local server):

- every request must carry a ``Host`` header naming this server (``127.0.0.1:PORT`` or
  ``localhost:PORT`` for a loopback server), so a DNS-rebinding page cannot read the mesh (403);
- every ``POST`` must carry the session's secret in ``X-Torchcage-Token`` (the page has it in a
  ``<meta name="torchcage-token">`` tag; scripts use :attr:`EditorServer.token` or
  :func:`fetch_token`), compared in constant time (403), an ``Origin``, when sent, of this server
  (403), and ``Content-Type: application/json`` (415): a foreign page can neither read the secret
  nor send a JSON body without the browser asking the server first (which it refuses).
- bodies over ``max_body`` bytes answer 413, JSON nested deeper than :data:`MAX_DEPTH` 400, a
  connection silent for ``timeout`` seconds is dropped, and at most ``workers`` connections are
  served at once (503 beyond).

Examples:
    >>> import json, urllib.request, torch, torchcage
    >>> from torchcage.viewer import EditorServer, EditorSession
    >>> cage = torchcage.load_cage(torchcage.data.path("cube.obj"))
    >>> session = EditorSession(torch.zeros(1, 3), torch.zeros(0, 3, dtype=torch.long), cage, background=False)
    >>> server = EditorServer(session).start()
    >>> body = json.dumps({"vertices": (cage.vertices + 1).tolist()}).encode()
    >>> request = urllib.request.Request(server.url + "api/pose", data=body, headers=server.headers)
    >>> with urllib.request.urlopen(request) as r:
    ...     json.load(r)["vertices"]
    [[1.0, 1.0, 1.0]]
    >>> server.close()
"""

from __future__ import annotations

import hmac
import ipaddress
import json
import re
import secrets
import socket
import sys
import threading
import urllib.parse
import urllib.request
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any
from urllib.parse import parse_qs, urlsplit

import numpy as np

from torchcage.viewer.session import CoordinatesError, EditorError, EditorSession

__all__ = [
    "DEFAULT_TIMEOUT",
    "DEFAULT_WORKERS",
    "MAX_BODY",
    "MAX_DEPTH",
    "TOKEN_HEADER",
    "EditorServer",
    "fetch_token",
    "json_depth",
]

#: The largest request body accepted (a pose of a million cage vertices fits).
MAX_BODY = 64 * 1024 * 1024
#: The deepest JSON nesting accepted (a pose is 2 levels inside its object).
MAX_DEPTH = 64
#: Seconds a connection may stay silent (mid-request, or idle between requests) before it is dropped.
DEFAULT_TIMEOUT = 20.0
#: Connections served at once; more are answered 503 (a browser holds about 6 per page).
DEFAULT_WORKERS = 64
#: The request header that carries the session's secret.
TOKEN_HEADER = "X-Torchcage-Token"
#: Who may frame the editor's pages: the page itself and pages served from this machine (a notebook).
FRAME_ANCESTORS = "frame-ancestors 'self' http://localhost:* http://127.0.0.1:* http://[::1]:* https://localhost:*"
_TOKEN_META = re.compile(r'<meta name="torchcage-token" content="([A-Za-z0-9_-]+)">')
_STATIC = {
    "index.html": "text/html; charset=utf-8",
    "editor.js": "text/javascript; charset=utf-8",
    "editor.css": "text/css; charset=utf-8",
    "vendor/three.module.min.js": "text/javascript; charset=utf-8",
}
_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"')  # a JSON string literal (escapes included)
_DROPPED = (ConnectionError, TimeoutError)  # the client went away or went silent
_DISCARD = 1 << 20  # a refused request's body up to this size is read and dropped


class _RequestError(Exception):
    def __init__(self, status: HTTPStatus, message: str) -> None:
        super().__init__(message)
        self.status = status


def _static(name: str) -> bytes:
    return resources.files("torchcage.viewer").joinpath("static", *name.split("/")).read_bytes()


def json_depth(raw: bytes, limit: int = MAX_DEPTH) -> int:
    """The nesting depth of the JSON text ``raw`` (brackets inside strings not counted), without
    parsing it (so without recursion): what :data:`MAX_DEPTH` is checked against.

    Args:
        raw: the body, UTF-8 JSON text (need not be valid: the parser judges that next).
        limit: counting stops once past it (in chunks of 1 MiB), the answer then being over it.

    Returns:
        The deepest nesting of ``[]`` and ``{}``: 0 for a number, 1 for ``[1]``.

    Examples:
        >>> json_depth(b'{"a": [[1, 2], "[[["]}')
        3
    """
    codes = np.frombuffer(_STRING.sub(b'""', raw), dtype=np.uint8)
    depth = deepest = 0
    for start in range(0, codes.size, 1 << 20):
        c = codes[start : start + (1 << 20)]
        step = (c == ord("[")).astype(np.int32) + (c == ord("{")) - (c == ord("]")) - (c == ord("}"))
        running = np.cumsum(step) + depth
        deepest, depth = max(deepest, int(running.max())), int(running[-1])
        if deepest > limit:
            break
    return deepest


def _host_names(host: str) -> tuple[set[str], bool]:
    """The host names a request to a server bound to ``host`` may carry (lower case, IPv6 in
    brackets), and whether any IP literal is also fine (a server bound to every address)."""
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:  # a name, e.g. "localhost"
        return {host.lower(), "localhost", "127.0.0.1", "[::1]"} if host == "localhost" else {host.lower()}, False
    if ip.is_unspecified:  # 0.0.0.0 or ::, reached by any of the machine's addresses or names
        names = {"localhost", socket.gethostname().lower(), socket.getfqdn().lower()}
        return names, True
    names = {f"[{ip.compressed}]" if ip.version == 6 else ip.compressed}
    if ip.is_loopback:
        names |= {"localhost", "127.0.0.1", "[::1]"}
    return names, False


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    protocol_version = "HTTP/1.1"

    # ------------------------------------------------------------------ plumbing
    def setup(self) -> None:
        super().setup()
        self.connection.settimeout(self.server.request_timeout)  # every read and write: a silent client is dropped

    def log_message(self, format: str, *args: Any) -> None:
        if self.server.verbose:  # (control characters of a request line escaped: no terminal escapes)
            line = "".join(c if c.isprintable() else repr(c)[1:-1] for c in format % args)
            sys.stderr.write(f"torchcage view: {self.address_string()} {line}\n")

    def _send(self, status: HTTPStatus, body: bytes, content_type: str, headers: dict[str, str] | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        # no framing by other sites (clickjacking: the framed page holds the token); a notebook on
        # this machine may still show it (Viewer._repr_html_'s iframe)
        self.send_header("Content-Security-Policy", FRAME_ANCESTORS)
        if self.close_connection:
            self.send_header("Connection", "close")
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

    def _check_host(self) -> None:
        """Refuse a ``Host`` that is not this server (a DNS-rebinding page names its own host)."""
        host = self.headers.get("Host")
        if host is None or not self.server.host_allowed(host):
            raise _RequestError(
                HTTPStatus.FORBIDDEN,
                f"refused: the Host header {host!r} does not name this server; open {self.server.url}",
            )

    def _check_write(self) -> None:
        """Refuse a state-changing request without the session's secret, from another origin, or
        not JSON: what another web page in the user's browser could send."""
        origin = self.headers.get("Origin")
        if origin is not None:
            try:
                parts = urlsplit(origin)
                ours = parts.scheme == "http" and not parts.path and self.server.host_allowed(parts.netloc)
            except ValueError:  # not a URL ("null" parses, as another origin)
                ours = False
            if not ours:
                raise _RequestError(HTTPStatus.FORBIDDEN, f"refused: a request from another origin ({origin})")
        sent = self.headers.get(TOKEN_HEADER, "")
        if not hmac.compare_digest(sent.encode("utf-8", "replace"), self.server.token.encode()):
            raise _RequestError(
                HTTPStatus.FORBIDDEN,
                f"refused: the {TOKEN_HEADER} header is {'wrong' if sent else 'missing'}; send the editor's "
                "token (Viewer.headers in Python, or torchcage.viewer.fetch_token(url))",
            )
        kind = self.headers.get_content_type()  # (text/plain when absent)
        if kind != "application/json":
            raise _RequestError(
                HTTPStatus.UNSUPPORTED_MEDIA_TYPE,
                f"send the body as JSON with Content-Type: application/json, not {kind}",
            )

    def _discard_body(self) -> None:
        """Read and drop a small body (so the answer reaches the client before the connection
        closes), or close the connection after answering."""
        try:
            length = int(self.headers.get("Content-Length", "0"))
        except ValueError:
            length = -1
        if "Transfer-Encoding" in self.headers or not 0 <= length <= _DISCARD:
            self.close_connection = True
        elif length:
            self.rfile.read(length)

    def _body(self) -> bytes:
        if "Transfer-Encoding" in self.headers:
            self.close_connection = True  # the body is left unread
            raise _RequestError(HTTPStatus.LENGTH_REQUIRED, "send the body with a Content-Length, not chunked")
        try:
            length = int(self.headers.get("Content-Length", "0"))
        except ValueError:
            self.close_connection = True
            raise _RequestError(HTTPStatus.BAD_REQUEST, "Content-Length is not a number") from None
        if length < 0:
            self.close_connection = True
            raise _RequestError(HTTPStatus.BAD_REQUEST, "Content-Length is negative")
        if length > self.server.max_body:
            self.close_connection = True  # the body is left unread
            raise _RequestError(
                HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"the body is over {self.server.max_body} bytes ({length})"
            )
        raw = self.rfile.read(length)
        if len(raw) < length:  # the client closed before the end
            raise ConnectionResetError(f"the body ended after {len(raw)} of {length} bytes")
        return raw

    def _json_body(self) -> dict[str, Any]:
        raw = self._body()
        if not raw.strip():
            return {}
        if json_depth(raw) > MAX_DEPTH:
            raise _RequestError(HTTPStatus.BAD_REQUEST, f"the JSON is nested deeper than {MAX_DEPTH} levels")
        try:
            data = json.loads(raw)  # NaN and Infinity read as floats, then refused as a pose
        except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as err:
            raise _RequestError(HTTPStatus.BAD_REQUEST, f"the body is not JSON: {err}") from None
        if not isinstance(data, dict):
            raise _RequestError(HTTPStatus.BAD_REQUEST, f"the body must be a JSON object, got {type(data).__name__}")
        return data

    def _dispatch(self, routes: dict[str, Any], write: bool = False) -> None:
        url = urlsplit(self.path)
        query = {k: v[-1] for k, v in parse_qs(url.query).items()}
        route = routes.get(url.path)
        try:
            try:
                self._check_host()
                if write:
                    self._check_write()
            except _RequestError:
                self._discard_body()  # a refused request's body is never looked at
                raise
            if route is None:
                if url.path.startswith("/static/") and self.command in ("GET", "HEAD"):
                    return self._serve_static(url.path[len("/static/") :])
                raise _RequestError(HTTPStatus.NOT_FOUND, f"no route {self.command} {url.path}")
            route(query)
        except _DROPPED:  # the client went away (see _Server.handle_error)
            raise
        except _RequestError as err:
            self._error(err.status, str(err))
        except CoordinatesError as err:  # the request was fine; the coordinates cannot serve it
            self._error(HTTPStatus.CONFLICT, str(err))
        except (EditorError, ValueError, TypeError) as err:
            self._error(HTTPStatus.BAD_REQUEST, str(err))
        except Exception as err:  # never let one request take the server down
            self._error(HTTPStatus.INTERNAL_SERVER_ERROR, f"{type(err).__name__}: {err}")

    def do_GET(self) -> None:
        self._dispatch(
            {
                "/": lambda q: self._serve_page(),
                "/index.html": lambda q: self._serve_page(),
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
            },
            write=True,
        )

    # ------------------------------------------------------------------ routes
    def _serve_page(self) -> None:
        page = _static("index.html").replace(b"{{TORCHCAGE_TOKEN}}", self.server.token.encode())
        self._send(HTTPStatus.OK, page, _STATIC["index.html"])

    def _serve_static(self, name: str) -> None:
        if name not in _STATIC or name == "index.html":
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
        text = self._json_body().get("obj")
        if not isinstance(text, str):
            raise _RequestError(HTTPStatus.BAD_REQUEST, 'the body must be {"obj": "<the text of an OBJ file>"}')
        session = self.server.session
        deformed = session.load_pose_obj(text, wait=query.get("wait") != "0")
        pose, version = session.snapshot()
        mesh = None if deformed is None else deformed.tolist()
        self._json({"cage": pose.tolist(), "vertices": mesh, "version": version})


class _Server(ThreadingHTTPServer):
    """A threading HTTP server with at most ``workers`` handler threads (503 beyond), a socket
    timeout per connection, and one line (verbose only) per client that drops."""

    daemon_threads = True
    allow_reuse_address = True
    request_queue_size = 128  # the listen backlog (the standard library's 5 drops bursts' SYNs: 1 s retries)

    def __init__(
        self,
        address: tuple[str, int],
        session: EditorSession,
        *,
        verbose: bool,
        timeout: float,
        workers: int,
        max_body: int,
        allowed_hosts: tuple[str, ...],
    ) -> None:
        super().__init__(address, _Handler)
        self.session = session
        self.verbose = verbose
        self.request_timeout = timeout
        self.max_body = max_body
        self.token = secrets.token_urlsafe(32)
        self._slots = threading.BoundedSemaphore(workers)
        host, port = str(self.server_address[0]), int(self.server_address[1])
        names, self._any_ip = _host_names(host)
        if address[0]:
            names.add(address[0].lower())  # the name it was given ("localhost", the machine's name)
        self._port = port
        self._hosts = {f"{name}:{port}" for name in names} | {h.lower() for h in allowed_hosts}
        shown = "127.0.0.1" if self._any_ip else (f"[{host}]" if ":" in host else host)
        self.url = f"http://{shown}:{port}/"

    def host_allowed(self, value: str) -> bool:
        """Whether a ``Host`` header (or an ``Origin``'s ``host:port``) names this server."""
        value = value.strip().lower()
        if value in self._hosts:
            return True
        if not self._any_ip:
            return False
        name, _, port = value.rpartition(":")
        try:
            ipaddress.ip_address(name.strip("[]"))  # an IP literal: no DNS name to rebind
        except ValueError:
            return False
        return port == str(self._port)

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self._slots.acquire(blocking=False):
            self._refuse(request, client_address)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()

    def _refuse(self, request: Any, client_address: Any) -> None:
        body = json.dumps({"error": "the editor is busy (too many connections); retry"}).encode()
        head = (
            "HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\nConnection: close\r\n"
            f"Retry-After: 1\r\nContent-Length: {len(body)}\r\n\r\n"
        )
        try:
            request.settimeout(0.2)  # never let one client stall the accepting thread
            request.sendall(head.encode() + body)
        except OSError:
            pass
        if self.verbose:
            sys.stderr.write(f"torchcage view: {client_address[0]}: busy, answered 503\n")
        self.shutdown_request(request)

    def handle_error(self, request: Any, client_address: Any) -> None:
        err = sys.exc_info()[1]
        if isinstance(err, _DROPPED):  # a client that went away or went silent: not the server's fault
            if self.verbose:
                sys.stderr.write(f"torchcage view: {client_address[0]}: connection dropped ({type(err).__name__})\n")
            return
        sys.stderr.write(f"torchcage view: {client_address[0]}: {type(err).__name__}: {err}\n")


class EditorServer:
    """Serve an :class:`EditorSession` at ``http://host:port/``.

    Args:
        session: the editor's state.
        host: the address to listen on (loopback by default: the page, and with it the session's
            token, is open to anyone who can reach the server).
        port: the port; ``0`` picks a free one (see :attr:`url`).
        verbose: log each request, and each client that drops, on stderr.
        timeout: seconds a connection may stay silent before it is dropped.
        workers: connections served at once (503 beyond).
        max_body: the largest request body in bytes (413 beyond).
        allowed_hosts: more ``host:port`` values to accept in ``Host`` and ``Origin`` headers
            (e.g. ``"localhost:9000"`` behind a port forward to another local port).

    Attributes:
        token: the session's secret, required in the ``X-Torchcage-Token`` header of each ``POST``.

    Raises:
        OSError: the address is in use or cannot be bound (the message names it).
    """

    def __init__(
        self,
        session: EditorSession,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        verbose: bool = False,
        timeout: float = DEFAULT_TIMEOUT,
        workers: int = DEFAULT_WORKERS,
        max_body: int = MAX_BODY,
        allowed_hosts: tuple[str, ...] | list[str] = (),
    ):
        if not timeout > 0 or workers < 1 or max_body < 0:
            raise ValueError(f"need timeout > 0, workers >= 1, max_body >= 0; got {timeout}, {workers}, {max_body}")
        try:
            self._httpd = _Server(
                (host, port),
                session,
                verbose=verbose,
                timeout=timeout,
                workers=workers,
                max_body=max_body,
                allowed_hosts=tuple(allowed_hosts),
            )
        except OSError as err:
            refused = OSError(f"cannot listen on {host}:{port}: {err.strerror or err}; choose another --port")
            refused.errno = err.errno  # (EADDRINUSE: the port is taken)
            raise refused from None
        self.session = session
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        """The page's address, ``http://host:port/``."""
        return self._httpd.url

    @property
    def port(self) -> int:
        """The port served."""
        return int(self._httpd.server_address[1])

    @property
    def token(self) -> str:
        """The session's secret: send it in the ``X-Torchcage-Token`` header of each ``POST``."""
        return self._httpd.token

    @property
    def headers(self) -> dict[str, str]:
        """The headers a script's ``POST`` needs: the token and the JSON content type."""
        return {TOKEN_HEADER: self.token, "Content-Type": "application/json"}

    def start(self) -> EditorServer:
        """Serve in a daemon thread; return ``self``."""
        self._thread = threading.Thread(
            target=self._httpd.serve_forever,
            kwargs={"poll_interval": 0.1},  # (close() returns within 0.1 s)
            name="torchcage-view",
            daemon=True,
        )
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


def fetch_token(url: str, timeout: float = 10.0) -> str:
    """The token of the editor served at ``url`` (read from its page), for a script in another
    process than the one that started the editor (e.g. ``torchcage view``).

    Raises:
        ValueError: ``url`` is not an http(s) address, or the page there is not the editor's.
    """
    scheme = urllib.parse.urlsplit(url).scheme
    if scheme not in ("http", "https"):
        raise ValueError(f"the editor is served over http; got a {scheme or 'relative'} address {url!r}")
    with urllib.request.urlopen(url, timeout=timeout) as answer:
        found = _TOKEN_META.search(answer.read().decode("utf-8", "replace"))
    if found is None:
        raise ValueError(f"{url} does not serve the torchcage editor's page (no token in it)")
    return found.group(1)
