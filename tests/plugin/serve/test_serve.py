"""posecal serve over HTTP only (issue 18, item 2; docs/serve.md).

A controller's view: the server is a process started with --port 0, and everything is done with
HTTP requests (urllib, no posecal binding): a full calibration, its event stream in order, the
live view, the misuse of every route, the token, and shutdown by SIGTERM.
Needs POSECAL_CLI (the posecal binary); run by ctest (plugin_serve).
"""
import json
import os
import shutil
import signal
import socket
import subprocess
import threading
import time
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest

CLI = os.environ["POSECAL_CLI"]


class Server:
    def __init__(self, *args):
        self.proc = subprocess.Popen([CLI, "serve", "--port", "0", "--json", *args],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline()
        assert line, self.proc.stderr.read()
        self.port = json.loads(line)["port"]
        self.base = f"http://127.0.0.1:{self.port}"

    def request(self, method, path, body=None, headers=None, raw=None, timeout=30):
        data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
        req = urllib.request.Request(self.base + path, data=data, method=method,
                                     headers=headers or {})
        try:
            with urllib.request.urlopen(req, timeout=timeout) as r:
                return r.status, r.read()
        except urllib.error.HTTPError as e:
            return e.code, e.read()

    def json(self, method, path, body=None, headers=None, raw=None):
        status, data = self.request(method, path, body, headers, raw)
        return status, json.loads(data)

    def stop(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                raise


@pytest.fixture
def server():
    s = Server()
    yield s
    s.stop()
    assert s.proc.returncode == 0, s.proc.stderr.read()


def read_events(server, path, out, timeout=300):
    """Reads Server-Sent Events from `path` until "end"; appends (kind, data) to out."""
    with urllib.request.urlopen(server.base + path, timeout=timeout) as r:
        assert r.headers["Content-Type"].startswith("text/event-stream")
        kind, data = None, None
        for raw in r:
            line = raw.decode().rstrip("\n")
            if line.startswith("event: "):
                kind = line[7:]
            elif line.startswith("data: "):
                data = json.loads(line[6:])
            elif line == "" and kind is not None:
                out.append((kind, data))
                if kind == "end":
                    return
                kind, data = None, None


def wait_done(server, sid, timeout=300):
    t0 = time.time()
    while time.time() - t0 < timeout:
        status, st = server.json("GET", f"/api/sessions/{sid}")
        assert status == 200, st
        if st["done"]:
            return st
        time.sleep(0.2)
    raise AssertionError(f"session {sid} not done in {timeout} s")


def test_full_calibration_over_rest_with_every_event_in_order(server, tmp_path):
    status, cams = server.json("GET", "/api/cameras")
    assert status == 200 and isinstance(cams, list)
    status, opened = server.json("POST", "/api/sessions",
                                 {"camera": "sim://?seed=5", "config": {"max_keyframes": 20}})
    assert status == 201, opened
    sid = opened["id"]
    events = []
    reader = threading.Thread(target=read_events,
                              args=(server, f"/api/sessions/{sid}/events", events))
    reader.start()
    st = wait_done(server, sid)
    reader.join(timeout=60)
    assert not reader.is_alive()
    assert st["finished"] and st["converged"] and st["error"] is None, st
    status, result = server.json("GET", f"/api/sessions/{sid}/result")
    assert status == 200
    assert result["converged"] is True
    assert result["keyframes"] >= 3
    assert 0 < result["eps_gt"] < 1.0, result["eps_gt"]
    assert np.isfinite(result["fx"]) and result["fx"] > 0

    # Every event once, in order: the stream's session_seq is 1..N, N the status's count, and
    # it ends with the server's "finished" and "end".
    kinds = [k for k, _ in events]
    assert kinds[-2:] == ["finished", "end"], kinds[-5:]
    body = [d for k, d in events if k != "end"]
    assert [d["session_seq"] for d in body] == list(range(1, len(body) + 1))
    seqs = [d["seq"] for d in body]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    status, st = server.json("GET", f"/api/sessions/{sid}")
    assert st["events"] == len(body)
    assert all(d["session"] == sid and "time" in d for d in body)
    # The states chain: each change starts where the one before ended, and the last is the
    # outcome.
    changes = [d for d in body if d["event"] == "state_changed"]
    for a, b in zip(changes, changes[1:]):
        assert b["from"] == a["to"], (a, b)
    assert changes[-1]["to"] == "converged"
    # one "captured" per keyframe kept or later rejected
    assert kinds.count("captured") - kinds.count("keyframe_rejected") == result["keyframes"]
    assert body[-1]["converged"] is True

    # A late reader gets the same events from the log, and ?after=N skips the first N.
    late = []
    read_events(server, f"/api/sessions/{sid}/events", late, timeout=30)
    assert [d["seq"] for k, d in late if k != "end"] == seqs
    late = []
    read_events(server, f"/api/sessions/{sid}/events?after={seqs[4]}", late, timeout=30)
    assert [d["seq"] for k, d in late if k != "end"] == seqs[5:]

    # Saving on the server and closing.
    status, saved = server.json("POST", f"/api/sessions/{sid}/save",
                                {"path": str(tmp_path / "s.yml")})
    assert status == 200, saved
    assert os.path.getsize(saved["saved"]) > 0
    status, closed = server.json("DELETE", f"/api/sessions/{sid}")
    assert status == 200 and closed["closed"]
    status, err = server.json("GET", f"/api/sessions/{sid}")
    assert status == 404 and sid in err["error"]


def mjpeg_parts(server, path, count, timeout=60):
    """The first `count` JPEG parts of a multipart stream, decoded."""
    pictures = []
    with urllib.request.urlopen(server.base + path, timeout=timeout) as r:
        assert r.headers["Content-Type"].startswith("multipart/x-mixed-replace")
        while len(pictures) < count:
            line = r.readline()
            assert line, "the stream ended"
            if line.lower().startswith(b"content-length:"):
                n = int(line.split(b":")[1])
                r.readline()  # the blank line
                data = r.read(n)
                pictures.append(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR))
    return pictures


def test_live_view_and_abort(server):
    status, opened = server.json("POST", "/api/sessions", {"camera": "sim://?seed=7",
                                                           "config": {"max_keyframes": 9}})
    assert status == 201
    sid = opened["id"]
    # The session list carries the cap the page's keyframe bar fills towards.
    status, sessions = server.json("GET", "/api/sessions")
    assert status == 200 and [s["max_keyframes"] for s in sessions if s["id"] == sid] == [9]
    pictures = mjpeg_parts(server, f"/api/sessions/{sid}/stream.mjpg", 5)
    for p in pictures:
        assert p is not None and p.shape == (720, 1280, 3)
        assert p.std() > 10  # a rendered scene, not a blank picture
    status, data = server.request("GET", f"/api/sessions/{sid}/frame.jpg")
    assert status == 200 and data[:2] == b"\xff\xd8"
    status, r = server.json("POST", f"/api/sessions/{sid}/abort")
    assert status == 200 and r["interrupted"]
    st = wait_done(server, sid, timeout=60)
    assert st["interrupted"] and not st["converged"]
    # Every stream has been released.
    t0 = time.time()
    while server.json("GET", "/api")[1]["streams"] != 0 and time.time() - t0 < 10:
        time.sleep(0.2)
    assert server.json("GET", "/api")[1]["streams"] == 0


def task_count(pid):
    return len(os.listdir(f"/proc/{pid}/task"))


def test_viewers_that_vanish_leak_nothing(server):
    status, opened = server.json("POST", "/api/sessions", {"camera": "sim://?seed=8"})
    sid = opened["id"]
    mjpeg_parts(server, f"/api/sessions/{sid}/stream.mjpg", 1)  # the pool's threads exist now
    time.sleep(1)
    threads = task_count(server.proc.pid)
    for _ in range(3):
        socks = []
        for path in ("stream.mjpg", "events"):
            for _ in range(4):
                s = socket.create_connection(("127.0.0.1", server.port))
                s.sendall(f"GET /api/sessions/{sid}/{path} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
                assert s.recv(100).startswith(b"HTTP/1.1 200")
                socks.append(s)
        assert server.json("GET", "/api")[1]["streams"] == 8
        for s in socks:
            s.close()  # mid-stream
        t0 = time.time()
        while server.json("GET", "/api")[1]["streams"] != 0 and time.time() - t0 < 15:
            time.sleep(0.2)
        assert server.json("GET", "/api")[1]["streams"] == 0
    assert task_count(server.proc.pid) == threads
    server.json("DELETE", f"/api/sessions/{sid}")


def test_records_of_the_station(server, tmp_path):
    # Without --records there is no store to read.
    status, err = server.json("GET", "/api/records")
    assert status == 404 and "--records" in err["error"]
    store = tmp_path / "records.sqlite"
    station = Server("--records", str(store))
    try:
        status, opened = station.json("POST", "/api/sessions", {"camera": "sim://?seed=5"})
        assert status == 201, opened
        sid = opened["id"]
        st = wait_done(station, sid)
        assert st["converged"], st
        status, full = station.json("GET", f"/api/sessions/{sid}")
        assert full["records"] == str(store) and full["run_id"], full
        status, runs = station.json("GET", "/api/records")
        assert status == 200 and [r["run_id"] for r in runs] == [full["run_id"]], runs
        assert runs[0]["state"] == "converged" and runs[0]["keyframes"] == st["keyframes"]
        status, run = station.json("GET", "/api/records/" + full["run_id"])
        assert status == 200 and run["result"]["fx"] > 0 and len(run["keyframes"]) == st["keyframes"]
        status, err = station.json("GET", "/api/records/no-such-run")
        assert status == 404 and err["error"], err
        # A session that names its own store keeps it.
        own = tmp_path / "own.sqlite"
        status, opened = station.json("POST", "/api/sessions",
                                      {"camera": "sim://?seed=6", "config": {"records": str(own)}})
        assert status == 201
        status, st = station.json("GET", f"/api/sessions/{opened['id']}")
        assert st["records"] == str(own), st
    finally:
        station.stop()
    assert station.proc.returncode == 0, station.proc.stderr.read()


def test_bad_requests_get_4xx_with_a_json_error(server):
    cases = [
        ("GET", "/api/nothing", None, None, 404),
        ("GET", "/api/sessions/s999", None, None, 404),
        ("GET", "/api/sessions/s999/result", None, None, 404),
        ("POST", "/api/sessions/s999/abort", None, b"", 404),
        ("DELETE", "/api/sessions/s999", None, None, 404),
        ("GET", "/api/sessions/s999/events", None, None, 404),
        ("POST", "/api/sessions", None, b"{not json", 400),
        ("POST", "/api/sessions", [1, 2], None, 400),
        ("POST", "/api/sessions", {"camera": 5}, None, 400),
        ("POST", "/api/sessions", {"camera": "sim://", "extra": 1}, None, 400),
        ("POST", "/api/sessions", {"camera": "sim://", "config": "x"}, None, 400),
        ("POST", "/api/sessions", {"camera": "external"}, None, 400),
        ("POST", "/api/sessions", {"camera": "sim://", "config": {"no_such_key": 1}}, None, 400),
        ("POST", "/api/sessions", {"camera": "nothing://here"}, None, 400),
        ("POST", "/api/sessions", {"camera": "aravis://no-such-camera"}, None, 404),
        ("POST", "/api/sessions", None, b"x" * (2 << 20), 413),
    ]
    for method, path, body, raw, want in cases:
        status, data = server.request(method, path, body, raw=raw)
        assert status == want, (method, path, status, data[:200])
        j = json.loads(data)
        assert j["status"] == want and j["error"], j
    # A session's calls in the wrong state: 409, naming why.
    status, opened = server.json("POST", "/api/sessions", {"camera": "sim://?seed=9"})
    sid = opened["id"]
    status, err = server.json("POST", f"/api/sessions/{sid}/reached")  # a person session
    assert status == 409 and err["posecal_status"] == "POSECAL_E_STATE", err
    status, err = server.json("POST", f"/api/sessions/{sid}/save", {"path": 3})
    assert status == 400
    server.json("DELETE", f"/api/sessions/{sid}")
    status, err = server.json("DELETE", f"/api/sessions/{sid}")
    assert status == 404
    # The server is still there.
    assert server.json("GET", "/api")[0] == 200


def test_token_is_required_when_set():
    s = Server("--token", "s3cret")
    try:
        status, err = s.json("GET", "/api/sessions")
        assert status == 401 and "token" in err["error"]
        status, _ = s.json("GET", "/api/sessions", headers={"Authorization": "Bearer wrong"})
        assert status == 401
        auth = {"Authorization": "Bearer s3cret"}
        status, opened = s.json("POST", "/api/sessions", {"camera": "sim://?seed=2"},
                                headers=auth)
        assert status == 201
        sid = opened["id"]
        # A second controller without the token cannot close it.
        status, err = s.json("DELETE", f"/api/sessions/{sid}")
        assert status == 401
        status, st = s.json("GET", f"/api/sessions/{sid}?token=s3cret")
        assert status == 200 and st["id"] == sid
        status, _ = s.json("DELETE", f"/api/sessions/{sid}", headers=auth)
        assert status == 200
    finally:
        s.stop()
    assert s.proc.returncode == 0


def test_other_addresses_need_a_token():
    r = subprocess.run([CLI, "serve", "--host", "0.0.0.0", "--port", "0"], capture_output=True,
                       text=True, timeout=30)
    assert r.returncode == 1, r
    assert "--token" in r.stderr


def test_sigterm_closes_running_sessions_and_exits_0():
    s = Server()
    for seed in (11, 12):
        assert s.json("POST", "/api/sessions", {"camera": f"sim://?seed={seed}"})[0] == 201
    time.sleep(1)
    t0 = time.time()
    s.stop()
    assert s.proc.returncode == 0
    assert time.time() - t0 < 15


def test_page_in_chromium_shows_four_live_views(server, tmp_path):
    """The page during a four-camera run, screenshotted by headless Chromium: four tiles, each
    a live picture (a large region of scene pixels) with the overlay's marks.
    The page's snapshot view: a headless screenshot waits until every request has ended, which
    the MJPEG streams only do when their session finishes."""
    chromium = shutil.which("chromium")
    assert chromium, "chromium is not installed (apt-get install --no-install-recommends chromium)"
    ids = []
    for seed in (21, 22, 23, 24):
        status, body = server.json("POST", "/api/sessions",
                                   {"camera": f"sim://?seed={seed}", "config": {"max_keyframes": 30}})
        assert status == 201
        ids.append(body["id"])
    # Every session has a first picture before the browser asks: on a loaded machine a session
    # busy in its first solves draws nothing for seconds, and the page's 4 s of virtual time
    # would then show a broken tile (seen in CI).
    deadline = time.time() + 90
    for sid in ids:
        while server.request("GET", f"/api/sessions/{sid}/frame.jpg")[0] != 200:
            assert time.time() < deadline, f"session {sid} drew no picture in 90 s"
            time.sleep(0.2)

    def screenshot(attempt):
        shot = tmp_path / f"page{attempt}.png"
        try:
            r = subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu",
                                "--disable-dev-shm-usage", "--hide-scrollbars",
                                "--window-size=1400,1000", "--virtual-time-budget=4000",
                                f"--user-data-dir={tmp_path / f'profile{attempt}'}",
                                f"--screenshot={shot}", server.base + "/?view=snapshots"],
                               capture_output=True, text=True, timeout=120)
        except subprocess.TimeoutExpired as e:
            return None, f"chromium timed out after 120 s: {(e.stderr or b'')[-2000:]!r}"
        return (shot if shot.exists() else None), r.stderr[-2000:]

    # One retry: headless Chromium on a loaded two-core machine has hung once in CI (no output
    # for 120 s); a second browser process, with its own profile, is a fair second chance.
    shot, why = screenshot(1)
    if shot is None:
        shot, why = screenshot(2)
    assert shot is not None, why
    out = os.environ.get("POSECAL_SERVE_SCREENSHOT")
    if out:
        shutil.copy(shot, out)
    img = cv2.imread(str(shot), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[1] == 1400
    # The page is dark (#1d2126, tiles #2a3038); a live view is a large region of scene pixels.
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    n, labels, stats, _ = cv2.connectedComponentsWithStats((gray > 60).astype(np.uint8))
    views = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] > 30000]
    assert len(views) >= 4, sorted(stats[1:, cv2.CC_STAT_AREA])[-6:]
    b, g, r_ = [img[:, :, i].astype(int) for i in range(3)]
    # The overlay's colours: the guidance's yellow, the green of a capture or of converged
    # parameters (core/select/overlay.cpp).
    marks = ((r_ > 180) & (g > 180) & (b < 100)) | ((g > 150) & (r_ < 120) & (b < 120))
    for i in views[:4]:
        x, y, w, h = stats[i, :4]
        box = marks[y:y + h, x:x + w]
        assert box.sum() > 20, f"no overlay in the view at {x},{y} ({w}x{h})"
