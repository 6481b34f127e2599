#!/usr/bin/python3
"""posecal's .cameramodel read by mrcal itself (Debian's python3-mrcal): mrcal.cameramodel loads
it and mrcal.project agrees with posecal's own projection to 1e-6 px over a grid that covers the
whole image (issue 17, "Proof").

  test_mrcal_roundtrip.py FORMAT_PROJECTION_GRID POSECAL_CLI WORK_DIR

Run with /usr/bin/python3: Debian's modules are not on a pyenv interpreter's path. Exits 77
(ctest's skip) when mrcal cannot be imported.
"""
import io
import os
import subprocess
import sys

try:
    import mrcal
    import numpy as np
except ImportError as e:
    print("SKIP: mrcal cannot be imported (%s); apt-get install python3-mrcal" % e)
    sys.exit(77)

TOLERANCE_PX = 1e-6


def posecal_grid(grid_tool, mode, path, *extra):
    out = subprocess.run([grid_tool, mode, path, *extra], check=True, capture_output=True, text=True).stdout
    w, h = (int(v) for v in out.splitlines()[0].split()[1:3])
    return (w, h), np.loadtxt(io.StringIO(out), comments="#")


def compare(label, path, size, grid, expected="LENSMODEL_OPENCV5"):
    model = mrcal.cameramodel(path)
    lensmodel, intrinsics = model.intrinsics()
    assert lensmodel == expected, lensmodel
    assert tuple(model.imagersize()) == size, (model.imagersize(), size)
    assert np.all(model.extrinsics_rt_fromref() == 0), model.extrinsics_rt_fromref()
    q = mrcal.project(grid[:, 0:3], lensmodel, intrinsics)
    err = np.linalg.norm(q - grid[:, 3:5], axis=1)
    # The grid reaches every edge and corner of the image.
    assert np.min(grid[:, 3]) < 1e-6 and np.max(grid[:, 3]) > size[0] - 1 - 1e-6
    assert np.min(grid[:, 4]) < 1e-6 and np.max(grid[:, 4]) > size[1] - 1 - 1e-6
    print("%s: max |mrcal.project - posecal| = %.3g px over %d points (%dx%d image)"
          % (label, err.max(), len(err), size[0], size[1]))
    assert err.max() < TOLERANCE_PX, err.max()


def main():
    grid_tool, cli, work = sys.argv[1:4]
    os.makedirs(work, exist_ok=True)

    # A strongly distorted model (tens of pixels at the corners), written by posecal's writer.
    sample = os.path.join(work, "sample.cameramodel")
    size, grid = posecal_grid(grid_tool, "--write", sample)
    compare("sample model", sample, size, grid)
    # OpenCV's rational and thin-prism models are mrcal's LENSMODEL_OPENCV8 and OPENCV12.
    for lens, name in (("opencv8", "LENSMODEL_OPENCV8"), ("opencv12", "LENSMODEL_OPENCV12")):
        path = os.path.join(work, lens + ".cameramodel")
        size, grid = posecal_grid(grid_tool, "--write", path, lens)
        compare(lens + " sample model", path, size, grid, name)

    # A calibration written by the command line, read by both.
    sim = os.path.join(work, "simulate.cameramodel")
    if os.path.exists(sim):
        os.remove(sim)
    run = subprocess.run([cli, "simulate", "--seed", "3", "--max-keyframes", "4", "--out", sim],
                         capture_output=True, text=True)
    assert run.returncode in (0, 3), run.stdout + run.stderr  # 3: not converged, still written
    size, grid = posecal_grid(grid_tool, "--read", sim)
    compare("posecal simulate --out .cameramodel", sim, size, grid)


if __name__ == "__main__":
    main()
