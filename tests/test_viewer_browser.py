"""The cage editor in a real browser: headless Chromium loads the page, renders the mesh, and a
drag through the page's own pointer handling changes the pose that the server reports; a page from
another local origin, and a DNS-rebinding name, can change and read nothing.

Skips, with the reason, where no Chromium can be had (``apt-get install chromium``; CI installs
it). ``TORCHCAGE_EDITOR_SCREENSHOT=path.png`` keeps the screenshot (the docs' picture).
"""

from __future__ import annotations

import http.server
import io
import json
import os
import threading
import time
import urllib.request

import numpy as np
import pytest
import torch
from browser import Browser, BrowserError, find_chromium
from PIL import Image

import torchcage

pytest.importorskip("websocket", reason="websocket-client is needed to drive the browser (pip install -e '.[test]')")
CHROMIUM = find_chromium()
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no Chromium on PATH (apt-get install chromium)")
D = torchcage.data
READY = "window.torchcage && window.torchcage.ready"
REBIND = "rebind.test"  # the browser resolves it to 127.0.0.1, as a DNS-rebinding attacker's name would


@pytest.fixture(scope="module")
def bar():
    return torchcage.load_cage(D.path("bar_cage.obj")), torchcage.load_mesh(D.path("bar.obj"))


@pytest.fixture(scope="module")
def browser():
    try:
        b = Browser(CHROMIUM, extra_args=(f"--host-resolver-rules=MAP {REBIND} 127.0.0.1",))
    except BrowserError as err:  # pragma: no cover - a broken install
        pytest.skip(f"chromium does not start here: {err}")
    with b:
        yield b


@pytest.fixture
def editor(bar, browser, tmp_path):
    cage, mesh = bar
    with torchcage.view(mesh, cage, out=tmp_path) as viewer:
        viewer.wait(60)
        browser.open(viewer.url, READY)
        browser.evaluate("window.torchcage.idle()")
        yield viewer


def scene(viewer) -> dict:
    with urllib.request.urlopen(viewer.url + "api/scene", timeout=30) as r:
        return json.load(r)


def wait_for(predicate, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.1)
    return False


def test_the_page_renders_the_mesh_and_the_cage(editor, browser):
    # the bundled bent pose, set by a script, with the top four vertices selected (the docs' picture)
    pose = torchcage.load_cage(D.path("bar_cage_deformed.obj"), check_intersections=False).vertices
    editor.set_pose(pose)
    assert wait_for(lambda: browser.evaluate("window.torchcage.version") == editor.session.version)
    top = torch.topk(pose[:, 2], 4).indices.tolist()
    browser.evaluate(f"window.torchcage.select({top})")
    time.sleep(0.5)  # let the frames land
    png = browser.screenshot()
    if os.environ.get("TORCHCAGE_EDITOR_SCREENSHOT"):
        with open(os.environ["TORCHCAGE_EDITOR_SCREENSHOT"], "wb") as f:
            f.write(png)
    image = torch.from_numpy(np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64)).reshape(-1, 3)
    r, g, b = image.unbind(-1)
    mesh_blue = (b > r + 25) & (b > 90) & (b < 245)  # the shaded mesh: blue-grey, lit and in shadow
    cage_orange = (r > 150) & (r > b + 80) & (g > 60)  # cage edges and vertices
    assert mesh_blue.double().mean() > 0.02, "no mesh on the canvas"
    assert cage_orange.sum() > 200, "no cage on the canvas"
    assert len({tuple(p) for p in image[mesh_blue].round().tolist()}) > 20, "the mesh is flat, not shaded"


def test_a_drag_through_the_page_moves_the_vertex_and_the_mesh(editor, browser, bar):
    cage, (v, _) = bar
    i = 12
    pose = torch.tensor(browser.evaluate(f"window.torchcage.dragVertex({i}, 70, -50)"), dtype=torch.float64).view(-1, 3)
    assert browser.evaluate("window.torchcage.selection()") == [i]
    moved = (pose - cage.vertices).norm(dim=1)
    assert moved[i] > 0.05 * cage.scale and moved[torch.arange(16) != i].max() == 0
    reported = scene(editor)
    assert torch.allclose(torch.tensor(reported["cage"]["vertices"], dtype=torch.float64), pose, atol=1e-12)
    assert torch.allclose(editor.pose, pose, atol=1e-12)
    expected = torchcage.MeanValueCoordinates(cage.triangulated(), v)(pose)
    assert torch.allclose(torch.tensor(reported["mesh"]["vertices"], dtype=torch.float64), expected, atol=1e-12)
    shown = torch.tensor(browser.evaluate("window.torchcage.meshPositions()"), dtype=torch.float64).view(-1, 3)
    assert (shown - expected).abs().max() < 1e-5 * cage.scale  # the page shows that mesh (float32)


def test_gizmo_transform_of_a_selection_then_undo_redo_reset(editor, browser, bar):
    cage, (v, _) = bar
    browser.evaluate("window.torchcage.select([...Array(16).keys()])")
    angle = 0.4
    c, s = torch.cos(torch.tensor(angle)).item(), torch.sin(torch.tensor(angle)).item()
    # rotation about z and scaling by 1.5 about the selection's centre, as the gizmo's pivot applies it
    centre = cage.vertices.mean(dim=0)
    R = 1.5 * torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    M = torch.eye(4, dtype=torch.float64)
    M[:3, :3], M[:3, 3] = R, centre - R @ centre
    pose = browser.evaluate(f"window.torchcage.transformSelection({M.T.reshape(-1).tolist()})")
    expected_pose = (cage.vertices - centre) @ R.T + centre
    assert torch.allclose(torch.tensor(pose, dtype=torch.float64).view(-1, 3), expected_pose, atol=1e-9)
    reported = scene(editor)
    mesh = torch.tensor(reported["mesh"]["vertices"], dtype=torch.float64)
    assert (mesh - ((v - centre) @ R.T + centre)).abs().max() < 1e-9  # MVC reproduces the similarity
    # (the page sends each pose to the server asynchronously: wait for it, as a loaded machine may lag)
    browser.evaluate("window.torchcage.undo()")
    assert wait_for(lambda: torch.allclose(editor.pose, cage.vertices, atol=1e-12)), "undo did not reach the server"
    browser.evaluate("window.torchcage.redo()")
    assert wait_for(lambda: torch.allclose(editor.pose, expected_pose, atol=1e-9)), "redo did not reach the server"
    browser.evaluate("window.torchcage.reset()")
    assert wait_for(lambda: torch.allclose(editor.pose, cage.vertices, atol=1e-12)), "reset did not reach the server"


def test_the_page_follows_a_pose_set_by_a_script(editor, browser, bar):
    cage, _ = bar
    pose = cage.vertices + torch.tensor([0.2, -0.1, 0.3], dtype=torch.float64)
    editor.set_pose(pose)

    def shown() -> bool:
        return torch.allclose(torch.tensor(browser.evaluate("window.torchcage.pose()")).view(-1, 3).double(), pose)

    assert wait_for(shown), "the page did not pick up the script's pose"


def test_switching_the_method_on_the_page(editor, browser):
    browser.evaluate(
        "(() => { const s = document.getElementById('method'); s.value = 'qmvc';"
        " s.dispatchEvent(new Event('change')); })()"
    )
    assert wait_for(lambda: editor.session.status().method == "qmvc")
    assert editor.wait(60).state == "ready"
    assert wait_for(lambda: "quad mean value" in browser.evaluate("document.getElementById('status').textContent"))


HOSTILE = """<!doctype html><html><body><iframe name="sink" id="sink"></iframe><script>
window.results = [];
window.done = false;
const target = %(target)s;
const attempts = %(attempts)s;
async function attack() {
  for (const [path, body] of attempts) {
    try {  // a "simple" request: the browser sends it without asking, and hides the answer
      await fetch(target + path, { method: 'POST', mode: 'no-cors', headers: { 'Content-Type': 'text/plain' }, body });
      results.push(`no-cors sent ${path}`);
    } catch (err) { results.push(`no-cors failed ${path}: ${err}`); }
    try {  // JSON and a guessed token: the browser must ask first (a preflight), which the server refuses
      const r = await fetch(target + path, {
        method: 'POST', headers: { 'Content-Type': 'application/json', 'X-Torchcage-Token': 'guess' }, body });
      results.push(`cors answered ${path} ${r.status}`);
    } catch (err) { results.push(`cors blocked ${path}`); }
  }
  try {  // read the page, and with it the token
    const r = await fetch(target);
    results.push(`read ${(await r.text()).length}`);
  } catch (err) { results.push('read blocked'); }
  await new Promise((resolve) => {  // a form whose text/plain body is shaped like JSON
    const form = document.createElement('form');
    Object.assign(form, { method: 'POST', action: target + 'api/save', enctype: 'text/plain', target: 'sink' });
    const input = Object.assign(document.createElement('input'), { name: '{"prefix": "form", "x": "', value: '"}' });
    form.appendChild(input);
    document.body.appendChild(form);
    document.getElementById('sink').onload = resolve;
    setTimeout(resolve, 5000);
    form.submit();
  });
  results.push('form sent');
  window.done = true;
}
attack();
</script></body></html>"""


@pytest.fixture
def hostile_origin():
    """A second local origin (another port on 127.0.0.1) serving the page that ``page`` holds."""
    page = {}

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            body = page["html"].encode()
            self.send_response(200)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args) -> None:
            pass

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}/", page
    httpd.shutdown()
    httpd.server_close()


def test_a_page_from_another_local_origin_changes_and_reads_nothing(bar, browser, hostile_origin, tmp_path, capfd):
    cage, mesh = bar
    out = tmp_path / "out"
    url, page = hostile_origin
    with torchcage.view(mesh, cage, out=out, verbose=True) as viewer:
        viewer.wait(60)
        pose = json.dumps({"vertices": (cage.vertices * 2).tolist()})
        obj = "".join(f"v {x} {y} {z}\n" for x, y, z in (cage.vertices * 2).tolist())
        attempts = [
            ["api/pose", pose],
            ["api/method", json.dumps({"method": "gc"})],
            ["api/save", json.dumps({"prefix": "pwned"})],
            ["api/load", json.dumps({"obj": obj})],
        ]
        page["html"] = HOSTILE % {"target": json.dumps(viewer.url), "attempts": json.dumps(attempts)}
        before = viewer.pose, viewer.session.version, viewer.method
        capfd.readouterr()
        browser.open(url, "window.done === true", timeout=60)
        results = browser.evaluate("window.results")
        time.sleep(0.3)  # (the server's log lines of the last requests)
        log = capfd.readouterr().err
        assert torch.equal(viewer.pose, before[0]) and viewer.session.version == before[1]
        assert viewer.method == before[2] == "mvc"
    assert not out.exists() or not any(out.iterdir()), "a file was written"
    assert [r for r in results if r.startswith("no-cors")] == [f"no-cors sent {a[0]}" for a in attempts]
    assert [r for r in results if r.startswith("cors")] == [f"cors blocked {a[0]}" for a in attempts]
    assert "read blocked" in results and "form sent" in results
    # the requests did reach the server, and were refused there (not merely unanswered)
    refused = [line for line in log.splitlines() if '"POST /api/' in line and '" 403 ' in line]
    assert len(refused) >= len(attempts) + 1, log  # the no-cors fetches and the form
    assert not [line for line in log.splitlines() if '"POST /api/' in line and '" 20' in line], log


def test_a_dns_rebinding_name_reads_nothing(bar, browser, tmp_path):
    cage, mesh = bar
    with torchcage.view(mesh, cage, out=tmp_path) as viewer:
        rebound = f"http://{REBIND}:{viewer.server.port}/"
        browser.open(
            rebound, f"location.host === '{REBIND}:{viewer.server.port}' && document.readyState === 'complete'"
        )
        shown = browser.evaluate("document.body.innerText")
        assert "does not name this server" in shown and viewer.token not in shown
        answers = browser.evaluate(
            "Promise.all(['api/scene', 'api/pose', 'static/editor.js'].map(p => fetch('/' + p).then(r => r.status)))"
        )
        assert answers == [403, 403, 403]
        status = browser.evaluate(
            "fetch('/api/pose', {method: 'POST', headers: {'Content-Type': 'application/json'},"
            " body: JSON.stringify({vertices: []})}).then(r => r.status)"
        )
        assert status == 403
        # the same browser, at the server's own address, gets the page
        browser.open(viewer.url, READY)
        assert browser.evaluate("document.querySelector('meta[name=\"torchcage-token\"]').content") == viewer.token


def test_save_and_load_on_the_page_pass_the_checks(editor, browser, bar, tmp_path):
    """The page's own Save and Load (a file chosen in its input) send the token and JSON."""
    cage, _ = bar
    pose = cage.vertices * 1.25
    editor.set_pose(pose)
    assert wait_for(lambda: browser.evaluate("window.torchcage.version") == editor.session.version)
    browser.evaluate("document.getElementById('save').click()")
    saved = tmp_path / "deformed_cage.obj"
    assert wait_for(lambda: (tmp_path / "deformed_mesh.obj").exists()), browser.evaluate("document.body.innerText")
    assert torch.allclose(torchcage.load_cage(saved, check_intersections=False).vertices, pose, atol=1e-12)
    editor.set_pose(cage.vertices)
    assert wait_for(lambda: browser.evaluate("window.torchcage.version") == editor.session.version)
    root = browser.send("DOM.getDocument")["root"]["nodeId"]
    node = browser.send("DOM.querySelector", nodeId=root, selector="#load")["nodeId"]
    browser.send("DOM.setFileInputFiles", files=[str(saved)], nodeId=node)
    assert wait_for(lambda: torch.allclose(editor.pose, pose, atol=1e-12)), browser.evaluate("document.body.innerText")
    assert wait_for(
        lambda: "loaded deformed_cage.obj" in browser.evaluate("document.getElementById('message').textContent")
    )
