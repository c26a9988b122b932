"""The cage editor's session, HTTP API and CLI (no browser: see test_viewer_browser.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.parse
import urllib.request

import numpy as np
import pytest
import torch

import torchcage
from torchcage.viewer import EditorSession, PoseError, fetch_token
from torchcage.viewer import session as session_module
from torchcage.viewer.server import TOKEN_HEADER

D = torchcage.data


@pytest.fixture(scope="module")
def bar():
    return torchcage.load_cage(D.path("bar_cage.obj")), torchcage.load_mesh(D.path("bar.obj"))


@pytest.fixture
def viewer(bar, tmp_path):
    cage, mesh = bar
    with torchcage.view(mesh, cage, out=tmp_path) as v:
        v.wait(60)
        yield v


def call(url: str, body: bytes | dict | None = None, method: str | None = None, headers=None):
    """(status, headers, parsed JSON or raw bytes) of one request; errors included. A body is sent
    as a script in another process would: the token read from the page, JSON content type."""
    data = json.dumps(body).encode() if isinstance(body, dict) else body
    if data is not None:
        parts = urllib.parse.urlsplit(url)
        token = fetch_token(f"{parts.scheme}://{parts.netloc}/")
        headers = {TOKEN_HEADER: token, "Content-Type": "application/json", **(headers or {})}
    req = urllib.request.Request(url, data=data, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=60) as r:
            status, head, raw = r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as err:
        status, head, raw = err.code, dict(err.headers), err.read()
    if head.get("Content-Type", "").startswith("application/json"):
        return status, head, json.loads(raw)
    return status, head, raw


def affine_pose(cage: torchcage.Cage) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    A = torch.eye(3, dtype=torch.float64) + 0.3 * torch.randn(3, 3, generator=g, dtype=torch.float64)
    b = torch.randn(3, generator=g, dtype=torch.float64)
    return cage.vertices @ A.T + b, A, b


def test_scene_reports_cage_with_quads_mesh_and_method(viewer, bar):
    cage, (v, f) = bar
    status, _, scene = call(viewer.url + "api/scene")
    assert status == 200
    assert scene["method"] == "mvc"
    assert torch.equal(torch.tensor(scene["cage"]["vertices"], dtype=torch.float64), cage.vertices)
    assert sorted(map(tuple, scene["cage"]["faces"])) == sorted(map(tuple, cage.quads.tolist()))
    assert len(scene["cage"]["edges"]) == cage.unique_edges().shape[0]
    assert torch.allclose(torch.tensor(scene["mesh"]["vertices"], dtype=torch.float64), v, atol=1e-12)
    assert torch.equal(torch.tensor(scene["mesh"]["faces"]), f)
    assert scene["status"]["state"] == "ready"


def test_pose_deforms_like_the_module_and_reproduces_affine_maps(viewer, bar):
    cage, (v, _) = bar
    pose, A, b = affine_pose(cage)
    status, _, answer = call(viewer.url + "api/pose", {"vertices": pose.tolist()})
    assert status == 200
    got = torch.tensor(answer["vertices"], dtype=torch.float64)
    reference = torchcage.MeanValueCoordinates(cage.triangulated(), v)(pose)
    assert torch.allclose(got, reference, atol=1e-12)
    assert (got - (v @ A.T + b)).abs().max() < 1e-10 * cage.scale  # linear precision of MVC
    assert answer["version"] == viewer.session.version
    assert torch.equal(viewer.pose, pose)
    _, _, scene = call(viewer.url + "api/scene")
    assert torch.allclose(torch.tensor(scene["mesh"]["vertices"], dtype=torch.float64), got, atol=1e-12)


def test_binary_pose_answer_is_the_float32_mesh(viewer, bar):
    cage, _ = bar
    pose = cage.vertices * 1.3
    status, head, raw = call(viewer.url + "api/pose?format=f32", {"vertices": pose.tolist()})
    assert status == 200 and head["Content-Type"] == "application/octet-stream"
    got = torch.from_numpy(np.frombuffer(raw, dtype="<f4").copy()).view(-1, 3).double()
    _, _, js = call(viewer.url + "api/deformed")
    exact = torch.tensor(js["vertices"], dtype=torch.float64)
    assert int(head["X-Pose-Version"]) == viewer.session.version
    assert (got - exact).abs().max() <= 1e-6 * exact.abs().max()


@pytest.mark.parametrize(
    ("body", "fragment"),
    [
        (b"not json", "not JSON"),
        (b"[1, 2]", "JSON object"),
        (b'{"pose": []}', '"vertices"'),
        (b'{"vertices": [[1, 2, 3]]}', "shape (16, 3)"),
        (b'{"vertices": "abc"}', "of numbers"),
        (b'{"vertices": [[1, 2], [3, 4]]}', "shape (16, 3)"),
        (json.dumps({"vertices": [[float("nan"), 0, 0]] + [[0, 0, 0]] * 15}).encode(), "NaN or inf"),
        (json.dumps({"vertices": [[0, 0, 0]] * 15 + [[float("inf"), 0, 0]]}).encode(), "vertices [15]"),
        (b"\xff\xfe", "not JSON"),
    ],
)
def test_bad_poses_answer_400_and_the_server_goes_on(viewer, bar, body, fragment):
    before = viewer.pose
    status, _, answer = call(viewer.url + "api/pose", body)
    assert status == 400 and fragment in answer["error"]
    assert torch.equal(viewer.pose, before)  # a refused pose changes nothing
    assert call(viewer.url + "api/status")[0] == 200


def test_other_bad_requests(viewer):
    assert call(viewer.url + "api/nothing")[0] == 404
    assert call(viewer.url + "static/../session.py")[0] == 404
    status, _, answer = call(viewer.url + "api/method", {"method": "nope"})
    assert status == 400 and "unknown method" in answer["error"]
    status, _, answer = call(viewer.url + "api/save", {"prefix": "../escape"})
    assert status == 400 and "plain file name" in answer["error"]
    status, _, answer = call(viewer.url + "api/pose", b"{}", headers={"Content-Length": str(10**9)})
    assert status == 413
    assert call(viewer.url + "api/status")[0] == 200


def test_static_files_are_served(viewer):
    status, head, page = call(viewer.url)
    assert status == 200 and b"editor.js" in page and head["Content-Type"].startswith("text/html")
    for name in ("editor.js", "editor.css", "vendor/three.module.min.js"):
        assert call(viewer.url + "static/" + name)[0] == 200


def test_save_writes_cage_with_quads_and_mesh_then_load_reads_the_pose_back(viewer, bar, tmp_path):
    cage, (_, f) = bar
    pose, _, _ = affine_pose(cage)
    viewer.set_pose(pose)
    status, _, paths = call(viewer.url + "api/save", {"prefix": "pose1"})
    assert status == 200
    saved = torchcage.load_cage(paths["cage"], check_intersections=False)
    assert saved.quads.shape == cage.quads.shape and saved.triangles.shape[0] == 0
    assert torch.allclose(saved.vertices, pose, atol=1e-12)
    mv, mf = torchcage.load_mesh(paths["mesh"])
    assert torch.equal(mf, f) and torch.allclose(mv, viewer.deformed, atol=1e-9)

    viewer.set_pose(cage.vertices)
    status, _, answer = call(viewer.url + "api/load", {"obj": open(paths["cage"]).read()})
    assert status == 200
    assert torch.allclose(viewer.pose, pose, atol=1e-12)
    assert torch.allclose(torch.tensor(answer["cage"], dtype=torch.float64), pose, atol=1e-12)
    assert torch.allclose(torch.tensor(answer["vertices"], dtype=torch.float64), viewer.deformed, atol=1e-12)


def test_load_refuses_files_that_are_not_this_cage(viewer, tmp_path):
    cube = tmp_path / "cube.obj"
    torchcage.save_cage(cube, torchcage.load_cage(D.path("cube.obj")))
    status, _, answer = call(viewer.url + "api/load", {"obj": cube.read_text()})
    assert status == 400 and "rest cage's faces" in answer["error"]
    status, _, answer = call(viewer.url + "api/load", {"obj": "f 1 2 3 4 5\n"})
    assert status == 400
    status, _, answer = call(viewer.url + "api/load", {"text": "v 0 0 0\n"})
    assert status == 400 and '{"obj"' in answer["error"]


def test_method_switch_recomputes_with_quads_kept(viewer, bar):
    cage, (v, _) = bar
    status, _, answer = call(viewer.url + "api/method", {"method": "qmvc"})
    assert status == 202 and answer["method"] == "qmvc"
    assert viewer.wait(120).state == "ready"
    pose = cage.vertices.clone()
    pose[:4] += torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    _, _, answer = call(viewer.url + "api/pose", {"vertices": pose.tolist()})
    reference = torchcage.QuadMeanValueCoordinates(cage, v)(pose)
    assert torch.allclose(torch.tensor(answer["vertices"], dtype=torch.float64), reference, atol=1e-12)
    assert call(viewer.url + "api/status")[2]["method"] == "qmvc"


def test_a_failed_method_answers_409_with_the_cause(bar, tmp_path):
    cage, _ = bar
    outside = torch.tensor([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0]], dtype=torch.float64)  # MEC refuses outside points
    with torchcage.view((outside, torch.zeros(0, 3, dtype=torch.long)), cage, method="mec", out=tmp_path) as v:
        status = v.wait(60)
        assert status.state == "failed" and "maximum entropy" in status.message
        code, _, answer = call(v.url + "api/pose", {"vertices": cage.vertices.tolist()})
        assert code == 409 and "choose another method" in answer["error"]
        code, _, scene = call(v.url + "api/scene")  # the page still loads, with the rest mesh and the cause
        assert code == 200 and scene["status"]["state"] == "failed" and not scene["mesh"]["deformed"]
        code, _, _ = call(v.url + "api/method", {"method": "mvc"})  # and it recovers
        status = v.wait(60)
        assert code == 202 and status.state == "ready"
        assert any("1 of 2 mesh vertices lie outside" in w for w in status.warnings)  # shown on the page
        assert call(v.url + "api/pose", {"vertices": cage.vertices.tolist()})[0] == 200


def test_progress_is_reported_and_a_superseded_computation_is_dropped(bar, monkeypatch):
    cage, (v, f) = bar
    release = threading.Event()
    reported = threading.Event()
    real = session_module.build_module

    def slow(method, cage, points, progress):
        if method == "gc":
            progress(10, 40, "10 of 40 points")
            reported.set()
            release.wait(30)
            progress(20, 40, "20 of 40 points")  # superseded by then: raises and ends the thread
        return real(method, cage, points, progress)

    monkeypatch.setattr(session_module, "build_module", slow)
    session = EditorSession(v, f, cage, method="gc")
    assert reported.wait(30)
    status = session.status()
    assert (status.state, status.method, status.done, status.total) == ("computing", "gc", 10, 40)
    assert session.deform(wait=False) is None
    session.set_method("mvc")
    release.set()
    assert session.wait(60).state == "ready"
    time.sleep(0.2)  # the superseded thread has ended; its method must not come back
    assert session.status().method == "mvc"
    assert torch.allclose(session.deform(cage.vertices * 2), v * 2, atol=1e-12)


def test_session_errors(bar):
    cage, (v, f) = bar
    with pytest.raises(ValueError, match="one 3D cage"):
        EditorSession(v[:, :2], f, torchcage.Cage(torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])))
    with pytest.raises(ValueError, match="NaN or inf"):
        EditorSession(v * float("nan"), f, cage)
    with pytest.raises(ValueError, match=r"\[0, 2562\)"):
        EditorSession(v, f + 10_000, cage)
    with pytest.raises(ValueError, match="unknown method"):
        EditorSession(v, f, cage, method="xyz")
    session = EditorSession(v, f, cage, background=False)
    with pytest.raises(PoseError, match="shape"):
        session.set_pose(torch.zeros(3, 3))


def test_view_from_python_with_an_initial_pose_file_and_a_warning_off_loopback(bar, tmp_path):
    cage, _ = bar
    pose_file = tmp_path / "pose.obj"
    pose = cage.vertices * 0.5
    torchcage.save_cage(pose_file, cage, pose)
    with pytest.warns(UserWarning, match="session's token"):
        v = torchcage.view(D.path("bar.obj"), D.path("bar_cage.obj"), pose=pose_file, host="0.0.0.0", out=tmp_path)
    with v:
        assert torch.allclose(v.pose, pose)
        assert v.url.startswith("http://127.0.0.1:")
        _, _, scene = call(v.url + "api/scene")
        assert torch.allclose(torch.tensor(scene["cage"]["vertices"], dtype=torch.float64), pose)
        assert "iframe" in v._repr_html_()


def test_cli_view_serves_the_bundled_scene(tmp_path):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "torchcage.cli", "view", "--no-browser", "--port", "0", "--out", str(tmp_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    try:
        url = None
        deadline = time.monotonic() + 60
        while url is None and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            if "http://" in line:
                url = line[line.index("http://") :].split()[0]
        assert url, "torchcage view printed no URL"
        status, _, scene = call(url + "api/scene")
        assert status == 200 and len(scene["cage"]["vertices"]) == 16 and scene["method"] == "mvc"
        status, _, paths = call(url + "api/save", {})
        assert status == 200 and os.path.dirname(paths["cage"]) == str(tmp_path.resolve())
    finally:
        proc.terminate()
        proc.wait(10)


def test_cli_view_errors(tmp_path, capsys):
    from torchcage.cli import main

    cage = str(D.path("bar_cage.obj"))
    assert main(["view", "--mesh", str(tmp_path / "missing.obj"), "--cage", cage, "--no-browser"]) == 2
    assert "missing.obj" in capsys.readouterr().err
    assert main(["view", "--mesh", str(D.path("bar.obj")), "--no-browser"]) == 2
    assert "both --mesh and --cage" in capsys.readouterr().err


def test_cli_view_with_an_automatic_cage(tmp_path, monkeypatch, capsys):
    pytest.importorskip("skimage")
    pytest.importorskip("fast_simplification")
    import torchcage.cli as cli
    import torchcage.viewer as viewer_module

    seen = {}
    real_view = viewer_module.view

    def spy(*args, **kwargs):
        seen["viewer"] = real_view(*args, **kwargs)
        return seen["viewer"]

    def serve_once(seconds):  # instead of serving until Ctrl+C: look at the page's scene, then stop
        seen["scene"] = call(seen["viewer"].url + "api/scene")[2]
        raise KeyboardInterrupt

    monkeypatch.setattr(viewer_module, "view", spy)
    monkeypatch.setattr(cli.time, "sleep", serve_once)
    mesh = str(D.path("bar.obj"))
    args = ["view", "--mesh", mesh, "--cage", "auto", "--cage-vertices", "20", "--no-browser", "--port", "0"]
    assert cli.main([*args, "--out", str(tmp_path)]) == 0
    made = torchcage.load_cage(tmp_path / "made_cage.obj")
    assert abs(made.num_vertices - 20) <= 5
    assert torch.allclose(torch.tensor(seen["scene"]["cage"]["vertices"], dtype=torch.float64), made.vertices)
    assert "made a cage of" in capsys.readouterr().out
