"""The editor's server refuses what another web page, a DNS-rebinding page or a misbehaving
client could send: forged headers over raw HTTP on 127.0.0.1,
deep JSON, stalled and dropping clients, a full worker pool, unportable save prefixes, a taken
port and a missing browser. (Chromium from a second local origin: test_viewer_browser.py.)"""

from __future__ import annotations

import http.client
import json
import socket
import struct
import threading
import time
import webbrowser

import pytest
import torch

import torchcage
from torchcage.viewer import EditorError, EditorServer, EditorSession, fetch_token
from torchcage.viewer import server as server_module
from torchcage.viewer.server import MAX_DEPTH, TOKEN_HEADER, json_depth
from torchcage.viewer.session import check_prefix

D = torchcage.data


@pytest.fixture(scope="module")
def cube():
    cage = torchcage.load_cage(D.path("cube.obj"))
    points = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.25, 0.5], [-0.5, 0.5, 0.0]], dtype=torch.float64)
    return cage, points


def start(cube, out, **options) -> EditorServer:
    cage, points = cube
    session = EditorSession(points, torch.zeros(0, 3, dtype=torch.long), cage, out_dir=out, background=False)
    return EditorServer(session, **options).start()


@pytest.fixture
def server(cube, tmp_path):
    s = start(cube, tmp_path / "out")
    yield s
    s.close()


def raw(server, method: str, path: str, body: bytes | None = None, headers=None, host: str | None = "default"):
    """(status, parsed JSON or bytes) of one request whose headers are exactly these (Host too)."""
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
    try:
        conn.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
        if host == "default":
            host = f"127.0.0.1:{server.port}"
        if host is not None:
            conn.putheader("Host", host)
        for k, v in (headers or {}).items():
            conn.putheader(k, v)
        if body is not None:
            conn.putheader("Content-Length", str(len(body)))
        conn.endheaders(body)
        answer = conn.getresponse()
        data = answer.read()
    finally:
        conn.close()
    if answer.getheader("Content-Type", "").startswith("application/json"):
        return answer.status, json.loads(data)
    return answer.status, data


def good(server) -> dict[str, str]:
    return {TOKEN_HEADER: server.token, "Content-Type": "application/json"}


def state(server, out) -> tuple:
    s = server.session
    return s.pose.tolist(), s.version, s.status().method, sorted(p.name for p in out.glob("*")) if out.exists() else []


def writes(server) -> list[tuple[str, bytes]]:
    """A request to each route that changes something, with a body that would be accepted."""
    pose = json.dumps({"vertices": (server.session.cage.vertices * 2).tolist()}).encode()
    return [
        ("/api/pose", pose),
        ("/api/method", b'{"method": "gc"}'),
        ("/api/save", b'{"prefix": "pwned"}'),
        ("/api/load", json.dumps({"obj": "".join(f"v {x} {y} {z}\n" for x, y, z in [[0, 0, 0]] * 8)}).encode()),
    ]


# ---------------------------------------------------------------------------------------- item 1
def forged(port: int, token: str) -> list[tuple[str, dict, str | None, int]]:
    """(case, headers, Host, expected status): each differs from an accepted request in one way."""
    ok = {TOKEN_HEADER: token, "Content-Type": "application/json"}
    here = f"127.0.0.1:{port}"
    wrong = token[:-1] + ("A" if token[-1] != "A" else "B")
    return [
        ("rebinding host", ok, f"attacker.example:{port}", 403),
        ("host, other port", ok, f"127.0.0.1:{port + 1}", 403),
        ("localhost suffix", ok, f"localhost.attacker.example:{port}", 403),
        ("no host", ok, None, 403),
        ("foreign origin", {**ok, "Origin": "http://attacker.example"}, here, 403),
        ("other local origin", {**ok, "Origin": f"http://127.0.0.1:{port + 1}"}, here, 403),
        ("null origin", {**ok, "Origin": "null"}, here, 403),
        ("https origin", {**ok, "Origin": f"https://{here}"}, here, 403),
        ("no token", {"Content-Type": "application/json"}, here, 403),
        ("wrong token", {**ok, TOKEN_HEADER: wrong}, here, 403),
        ("token prefix", {**ok, TOKEN_HEADER: token[:8]}, here, 403),
        ("non-ascii token", {**ok, TOKEN_HEADER: "é" * 10}, here, 403),
        ("text/plain", {**ok, "Content-Type": "text/plain"}, here, 415),
        ("form", {**ok, "Content-Type": "application/x-www-form-urlencoded"}, here, 415),
        ("no content type", {TOKEN_HEADER: token}, here, 415),
    ]


def test_forged_writes_are_refused_and_change_nothing(server, tmp_path):
    out = tmp_path / "out"
    before = state(server, out)
    refused = 0
    for case, headers, host, expected in forged(server.port, server.token):
        for path, body in writes(server):
            status, answer = raw(server, "POST", path, body, headers, host=host)
            assert status == expected, (case, path, status, answer)
            assert "refused" in answer["error"] or "Content-Type" in answer["error"]
            refused += 1
    assert state(server, out) == before  # no pose, no method, no file
    assert refused == 15 * 4
    assert raw(server, "GET", "/api/status")[0] == 200  # and the server goes on


def test_reads_with_a_foreign_host_are_refused(server):
    for path in ("/", "/api/scene", "/api/pose", "/api/deformed", "/static/editor.js"):
        status, answer = raw(server, "GET", path, host=f"rebind.example:{server.port}")
        assert status == 403 and "does not name this server" in answer["error"]
        assert server.token not in json.dumps(answer)
        assert raw(server, "GET", path)[0] == 200
    status, page = raw(server, "GET", "/", host=f"localhost:{server.port}")
    assert status == 200 and server.token.encode() in page


def test_right_headers_are_accepted(server, tmp_path):
    cage = server.session.cage
    for host, origin in [
        (f"127.0.0.1:{server.port}", None),  # a script: no Origin
        (f"127.0.0.1:{server.port}", f"http://127.0.0.1:{server.port}"),  # the page
        (f"localhost:{server.port}", f"http://localhost:{server.port}"),
    ]:
        headers = good(server) | ({"Origin": origin} if origin else {})
        pose = cage.vertices * (1 + server.session.version)
        body = json.dumps({"vertices": pose.tolist()}).encode()
        status, answer = raw(server, "POST", "/api/pose", body, headers, host=host)
        assert status == 200, answer
        assert torch.equal(server.session.pose, pose)
    headers = good(server) | {"Content-Type": "application/json; charset=utf-8"}
    status, _ = raw(server, "POST", "/api/save", b'{"prefix": "pose_01"}', headers)
    assert status == 200
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["pose_01_cage.obj", "pose_01_mesh.obj"]


def test_the_token_is_per_session_in_the_page_and_fetch_token_reads_it(cube, server, tmp_path):
    assert fetch_token(server.url) == server.token and len(server.token) >= 32
    other = start(cube, tmp_path / "other")
    try:
        assert other.token != server.token
        body = json.dumps({"vertices": (other.session.cage.vertices * 3).tolist()}).encode()
        assert raw(other, "POST", "/api/pose", body, good(server))[0] == 403  # another session's token
        assert raw(other, "POST", "/api/pose", body, good(other))[0] == 200
    finally:
        other.close()
    with pytest.raises(ValueError, match="not serve the torchcage editor"):
        fetch_token(server.url + "static/editor.css")


def test_host_names_of_a_server_on_every_address(cube, tmp_path):
    s = start(cube, tmp_path, host="0.0.0.0", allowed_hosts=["editor.internal:9000"])
    try:
        httpd = s._httpd
        port = s.port
        for ok in (f"127.0.0.1:{port}", f"192.168.1.20:{port}", f"[::1]:{port}", f"localhost:{port}"):
            assert httpd.host_allowed(ok), ok
        assert httpd.host_allowed("EDITOR.internal:9000")
        for bad in (f"attacker.example:{port}", f"192.168.1.20:{port + 1}", "editor.internal:9001", ""):
            assert not httpd.host_allowed(bad), bad
    finally:
        s.close()


# ---------------------------------------------------------------------------------------- item 2
def nested(depth: int, rng: torch.Generator) -> object:
    """A random JSON value exactly ``depth`` deep (strings with brackets in them)."""
    if depth == 0:
        return ["[", "{]", '"\\[', 1.5, None][int(torch.randint(5, (), generator=rng))]
    inner = [nested(depth - 1, rng)] + [nested(int(torch.randint(depth, (), generator=rng)), rng) for _ in range(2)]
    return inner if int(torch.randint(2, (), generator=rng)) else {f"k{i}]": v for i, v in enumerate(inner)}


def depth_of(value: object) -> int:
    if isinstance(value, list):
        return 1 + max((depth_of(v) for v in value), default=0)
    if isinstance(value, dict):
        return 1 + max((depth_of(v) for v in value.values()), default=0)
    return 0


def test_json_depth_agrees_with_the_parsed_value():
    rng = torch.Generator().manual_seed(0)
    for depth in [0, 1, 2, 3, 5, 8]:
        for _ in range(4):
            value = nested(depth, rng)
            text = json.dumps(value).encode()
            assert json_depth(text) == depth_of(value) == depth, text


def test_deep_json_is_refused_without_recursion(server):
    before = state(server, server.session.out_dir)
    for depth in (MAX_DEPTH + 1, 100_000):
        body = b'{"vertices": ' + b"[" * depth + b"]" * depth + b"}"
        status, answer = raw(server, "POST", "/api/pose", body, good(server))
        assert status == 400 and f"deeper than {MAX_DEPTH}" in answer["error"]
    body = b'{"vertices": ' + b"[" * (MAX_DEPTH - 1) + b"]" * (MAX_DEPTH - 1) + b"}"  # deep enough, not too deep
    status, answer = raw(server, "POST", "/api/pose", body, good(server))
    assert status == 400 and "shape" in answer["error"]
    assert state(server, server.session.out_dir) == before


def test_body_limits(cube, tmp_path):
    s = start(cube, tmp_path, max_body=1000)
    try:
        body = json.dumps({"vertices": (s.session.cage.vertices * 2).tolist()}).encode()
        assert len(body) < 1000
        status, answer = raw(s, "POST", "/api/method", b'{"method": "mvc", "x": "' + b"a" * 1000 + b'"}', good(s))
        assert status == 413 and "over 1000 bytes" in answer["error"]
        assert raw(s, "POST", "/api/pose", body, good(s) | {"Transfer-Encoding": "chunked"})[0] == 411
        assert raw(s, "POST", "/api/pose", body, good(s))[0] == 200
    finally:
        s.close()


def test_a_stalled_client_is_dropped_within_the_timeout(cube, tmp_path):
    s = start(cube, tmp_path, timeout=0.5)
    try:
        for partial in (
            b"",
            b"POST /api/pose HTTP/1.1\r\n",
            b"POST /api/pose HTTP/1.1\r\nContent-Length: 100\r\n\r\n{",
        ):
            with socket.create_connection(("127.0.0.1", s.port), timeout=10) as c:
                c.sendall(partial)
                t = time.monotonic()
                try:
                    rest = c.recv(1 << 16)  # the server closes the connection: b"" (or a reset)
                except ConnectionResetError:
                    rest = b""
                waited = time.monotonic() - t
            assert 0.3 < waited < 5.0 and rest in (b"", b"HTTP/1.1 408 Request Timeout\r\n"), (partial, waited, rest)
        assert raw(s, "GET", "/api/status")[0] == 200
    finally:
        s.close()


def wait_until(predicate, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()


def test_the_worker_pool_is_bounded(cube, tmp_path):
    s = start(cube, tmp_path, workers=2, timeout=5.0)
    try:
        idle = [socket.create_connection(("127.0.0.1", s.port), timeout=10) for _ in range(2)]  # hold both workers
        assert wait_until(lambda: s._httpd._slots._value == 0)
        threads = threading.active_count()
        status, answer = raw(s, "GET", "/api/status")
        assert status == 503 and "busy" in answer["error"]
        assert threading.active_count() == threads  # no thread for the refused client
        for c in idle:
            c.close()
        assert wait_until(lambda: s._httpd._slots._value == 2)
        assert raw(s, "GET", "/api/status")[0] == 200
    finally:
        s.close()


def drop(port: int, data: bytes) -> None:
    """Send ``data``, then reset the connection (SO_LINGER 0) without reading the answer."""
    c = socket.create_connection(("127.0.0.1", port), timeout=10)
    c.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    c.sendall(data)
    c.close()


@pytest.mark.parametrize("verbose", [False, True])
def test_dropping_clients_give_one_line_each_and_no_traceback(cube, tmp_path, capfd, verbose):
    s = start(cube, tmp_path, verbose=verbose)
    try:
        capfd.readouterr()
        pose = json.dumps({"vertices": (s.session.cage.vertices * 2).tolist()}).encode()
        head = f"POST /api/pose HTTP/1.1\r\nHost: 127.0.0.1:{s.port}\r\nContent-Type: application/json\r\n"
        head += f"{TOKEN_HEADER}: {s.token}\r\nContent-Length: {len(pose)}\r\n\r\n"
        messages = [b"GET /api/sce", head.encode() + pose[:20], head.encode()[:30], b"GET /api/scene HTTP/1.1\r\n"]
        messages.append(b"GET /\x1b[31mred HTTP/1.1\r\n\r\n")  # (a terminal escape: printed escaped)
        clients = 60
        for k in range(clients):
            drop(s.port, messages[k % len(messages)])
        assert wait_until(lambda: s._httpd._slots._value == server_module.DEFAULT_WORKERS)
        assert raw(s, "GET", "/api/status")[0] == 200  # still serving
        err = capfd.readouterr().err
    finally:
        s.close()
    assert "Traceback" not in err and "Exception" not in err and "\x1b" not in err
    assert len([line for line in err.splitlines() if "dropped" in line]) <= clients
    if not verbose:
        assert err == ""
    assert all(line.startswith("torchcage view: ") for line in err.splitlines())


# ---------------------------------------------------------------------------------------- item 3
REFUSED = [
    "-rf",
    "CON",
    "con.obj",
    "Lpt9",
    "com1.txt",
    "x..",
    "a..b",
    "x.",
    "a/b",
    "a\\b",
    "",
    " a",
    "a b",
    ".hidden",
    "é",
]


def test_unportable_prefixes_are_refused(server, tmp_path):
    for prefix in [*REFUSED, 7, None, "a" * 65]:
        with pytest.raises(EditorError, match=r"letters, digits.*Windows device name"):
            check_prefix(prefix)
        status, answer = raw(server, "POST", "/api/save", json.dumps({"prefix": prefix}).encode(), good(server))
        assert status == 400 and "plain file name" in answer["error"] and repr(prefix) in answer["error"]
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_portable_prefixes_are_written(server, tmp_path):
    accepted = ["pose_01", "a", "CONSOLE", "com10", "v1.2-final", "A" * 64]
    for prefix in accepted:
        assert check_prefix(prefix) == prefix
        assert raw(server, "POST", "/api/save", json.dumps({"prefix": prefix}).encode(), good(server))[0] == 200
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == sorted(f"{prefix}_{kind}.obj" for prefix in accepted for kind in ("cage", "mesh"))


# ---------------------------------------------------------------------------------------- item 5
@pytest.fixture
def taken():
    holder = socket.socket()
    holder.bind(("127.0.0.1", 0))
    holder.listen(1)
    yield holder.getsockname()[1]
    holder.close()


def test_a_taken_port_is_said_and_another_served(cube, taken, tmp_path, capsys, monkeypatch):
    import torchcage.viewer as viewer_module

    cage, points = cube
    mesh = (points, torch.zeros(0, 3, dtype=torch.long))
    with pytest.raises(OSError, match=f"cannot listen on 127.0.0.1:{taken}"):
        torchcage.view(mesh, cage, port=taken, out=tmp_path)  # an explicit port is not moved silently
    with torchcage.view(mesh, cage, port=taken, out=tmp_path, fallback=True) as v:
        assert v.server.port != taken
        assert f"port {taken} is in use; serving on {v.url}" in capsys.readouterr().err
    monkeypatch.setattr(viewer_module, "DEFAULT_PORT", taken)  # the default port moves by default
    with torchcage.view(mesh, cage, port=taken, out=tmp_path) as v:
        assert f"port {taken} is in use; serving on {v.url}" in capsys.readouterr().err


def test_cli_view_says_the_port_and_when_no_browser_opens(taken, tmp_path, capsys, monkeypatch):
    import torchcage.cli as cli
    import torchcage.viewer as viewer_module

    opened = []

    def no_browser(url, *args, **kwargs):
        opened.append(url)
        return False

    def stop(seconds):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "DEFAULT_PORT", taken)
    monkeypatch.setattr(viewer_module, "DEFAULT_PORT", taken)
    monkeypatch.setattr(webbrowser, "open", no_browser)
    monkeypatch.setattr(cli.time, "sleep", stop)
    assert cli.main(["view", "--out", str(tmp_path)]) == 0
    captured = capsys.readouterr()
    assert len(opened) == 1 and not opened[0].endswith(f":{taken}/")
    assert f"port {taken} is in use; serving on {opened[0]}" in captured.err
    assert f"no web browser could be opened; open {opened[0]} by hand" in captured.err


def test_no_browser_prints_the_address(cube, tmp_path, capsys, monkeypatch):
    cage, points = cube
    mesh = (points, torch.zeros(0, 3, dtype=torch.long))

    def broken(url, *args, **kwargs):
        raise webbrowser.Error("could not locate runnable browser")

    monkeypatch.setattr(webbrowser, "open", broken)
    with torchcage.view(mesh, cage, out=tmp_path, open_browser=True) as v:
        err = capsys.readouterr().err
        assert f"no web browser could be opened (Error: could not locate runnable browser); open {v.url} by hand" in err
        monkeypatch.setattr(webbrowser, "open", lambda url, *a, **k: True)
        assert v.open() is True and capsys.readouterr().err == ""


def test_other_sites_cannot_frame_the_editor(server):
    """Clickjacking: every answer says which ancestors may frame it (this machine's pages only)."""
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
    try:
        conn.request("GET", "/", headers={"Host": f"127.0.0.1:{server.port}"})
        answer = conn.getresponse()
        answer.read()
    finally:
        conn.close()
    policy = answer.getheader("Content-Security-Policy", "")
    assert answer.status == 200 and policy.startswith("frame-ancestors 'self'")
    assert "*" not in policy.replace(":*", "")  # no wildcard host: remote sites are not ancestors


def test_fetch_token_reads_http_only(tmp_path):
    from torchcage.viewer import fetch_token

    secret = tmp_path / "secret.html"
    secret.write_text('<meta name="torchcage-token" content="x">')
    for url in (secret.as_uri(), "ftp://127.0.0.1/", "page.html"):
        with pytest.raises(ValueError, match="served over http"):
            fetch_token(url)
