"""The documented Python examples, run as a user runs them (docs/examples/).

Run by ctest (plugin_python_examples) with pytest.
"""
import json
import os
import re
import subprocess
import sys

import cv2
import numpy as np

from conftest import SOURCE_DIR

EXAMPLES = os.path.join(SOURCE_DIR, "docs", "examples")


def run_example(name, *args, cwd=None):
    # -W error: an example that uses a deprecated form fails.
    return subprocess.run([sys.executable, "-W", "error", os.path.join(EXAMPLES, name), *args],
                          capture_output=True, text=True, timeout=600, cwd=cwd)


def printed_numbers(text):
    return [float(v) for v in re.findall(r"-?\d+\.\d*(?:e[-+]?\d+)?", text)]


def test_newcomer_station(tmp_path):
    # docs/examples/station.py: numpy frames from the simulated camera fed to an "external"
    # session, K and D printed as arrays, the calibration saved.
    r = run_example("station.py", "camera.yml", cwd=str(tmp_path))
    assert r.returncode == 0, r.stderr
    assert r.stderr == ""
    out = r.stdout
    assert "guidance: calibration converged" in out
    assert re.search(r"^converged: True with \d+ keyframes$", out, re.M), out
    k_text = out.split("K =\n", 1)[1].split("D =", 1)[0]
    d_text = out.split("D =", 1)[1].split("(", 1)[0]
    assert "(k1 k2 p1 p2 k3)" in out
    fs = cv2.FileStorage(str(tmp_path / "camera.yml"), cv2.FILE_STORAGE_READ)
    K = fs.getNode("camera_matrix").mat()
    D = fs.getNode("distortion_coefficients").mat().ravel()
    fs.release()
    # What it printed is what it saved (to the 5 printed decimals).
    np.testing.assert_allclose(printed_numbers(k_text), K.ravel(), rtol=0, atol=1e-5)
    np.testing.assert_allclose(printed_numbers(d_text), D, rtol=0, atol=1e-5)
    assert 900 < K[0, 0] < 1200 and D.shape == (5,)  # the simulated camera's lens


def test_multi_camera_station_four_cameras(tmp_path):
    # docs/examples/multi_camera_station.py: four simulated cameras calibrated concurrently
    # from Python threads (one Session each, one shared Context), a file per camera and a
    # summary.
    tmp = str(tmp_path)
    r = run_example("multi_camera_station.py", "--cameras",
                    "sim://?seed=41, sim://?seed=42,sim://?seed=43,sim://?seed=44&operator=robot",
                    "--out-dir", tmp, "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["total"] == 4
    assert summary["converged"] == 4
    files = sorted(os.path.basename(c["file"]) for c in summary["cameras"])
    assert files == ["sim-41.yml", "sim-42.yml", "sim-43.yml", "sim-44.yml"]
    for c in summary["cameras"]:
        assert c["error"] is None
        assert os.path.getsize(c["file"]) > 100
        assert c["eps_test"] < 0.3
    # The calibrations overlapped in time: they ran on concurrent threads.
    spans = [(c["started_s"], c["finished_s"]) for c in summary["cameras"]]
    latest_start = max(a for a, _ in spans)
    earliest_end = min(b for _, b in spans)
    assert latest_start < earliest_end, spans
    with open(os.path.join(tmp, "summary.json")) as f:
        assert json.load(f)["converged"] == 4
