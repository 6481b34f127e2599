"""posecal serve with a camera that vanishes (issue 18, "Bad input"; docs/serve.md).

A GigE Vision camera (Aravis' simulator, arv-fake-gv-camera-0.8, on loopback) and a simulated one
are calibrated side by side; the GigE camera's process is killed. Its session must say the camera
is gone (camera_connected false in the session list, which the page's tile shows), the other
session must go
on to its result, and the server must still answer every request and exit 0 on SIGTERM.
Skipped by pytest where the simulator is not installed (it is in .ci/test-packages). Run by ctest
(plugin_serve_camera_vanishes, which holds the GVCP loopback lock).
"""
import shutil
import subprocess
import time

import pytest

from test_serve import Server, wait_done


def poll(what, check, timeout):
    t0 = time.time()
    while time.time() - t0 < timeout:
        value = check()
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"{what}: not within {timeout} s")


def test_a_camera_that_vanishes_leaves_the_others_running():
    simulator = shutil.which("arv-fake-gv-camera-0.8")
    if not simulator:
        pytest.skip("arv-fake-gv-camera-0.8 not installed")
    fake = subprocess.Popen([simulator, "-i", "127.0.0.1"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    server = Server()
    try:
        # The GigE camera: no board in its test pattern, so no board timeout either.
        def open_gige():
            status, body = server.json("POST", "/api/sessions",
                                       {"camera": "aravis://127.0.0.1",
                                        "config": {"board_timeout_s": 0}})
            return body["id"] if status == 201 else None
        gone = poll("the simulator answers", open_gige, 30)
        status, body = server.json("POST", "/api/sessions", {"camera": "sim://?seed=3"})
        assert status == 201, body
        stays = body["id"]
        poll("frames from the GigE camera",
             lambda: server.json("GET", f"/api/sessions/{gone}")[1].get("frames", 0) >= 3, 60)

        fake.kill()
        fake.wait()

        def tile(sid):
            status, sessions = server.json("GET", "/api/sessions")
            assert status == 200
            return next(s for s in sessions if s["id"] == sid)
        poll("the session says its camera is gone",
             lambda: tile(gone)["camera_connected"] is False, 60)

        # The other camera is not held up: it goes on to its result.
        st = wait_done(server, stays)
        assert st["converged"], st
        assert tile(stays)["camera_connected"] is True
        # The vanished camera's session still answers, and closes.
        status, st = server.json("GET", f"/api/sessions/{gone}")
        assert status == 200 and st["camera_connected"] is False, st
        status, _ = server.request("DELETE", f"/api/sessions/{gone}")
        assert status in (200, 204)
        status, _ = server.json("GET", f"/api/sessions/{gone}")
        assert status == 404
    finally:
        server.stop()
        if fake.poll() is None:
            fake.kill()
            fake.wait()
    assert server.proc.returncode == 0, server.proc.stderr.read()
