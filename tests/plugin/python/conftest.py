"""pytest set-up of the Python binding's tests (tests/plugin/CMakeLists.txt runs them).

Environment: POSECAL_LIBRARY (the library under test), POSECAL_SOURCE_DIR (the source tree),
and PYTHONPATH=plugin/python for the source tree's package, or, for the installed-package run
(venv_test.sh), POSECAL_EXPECT_PACKAGE_UNDER=<virtualenv>: then every test module first checks
that `import posecal` found the package installed there, not the source tree's.
"""
import os

import pytest

import posecal

SOURCE_DIR = os.environ.get(
    "POSECAL_SOURCE_DIR", os.path.join(os.path.dirname(__file__), "..", "..", ".."))


def pytest_report_header(config):
    return "posecal %s from %s, library %s" % (posecal.__version__, posecal.__file__,
                                               posecal.library_path)


def pytest_collection_modifyitems(session, config, items):
    expected = os.environ.get("POSECAL_EXPECT_PACKAGE_UNDER")
    if expected:
        package = os.path.realpath(posecal.__file__)
        if not package.startswith(os.path.realpath(expected) + os.sep):
            raise pytest.UsageError("posecal was imported from %s, not from the package "
                                    "installed under %s" % (package, expected))


@pytest.fixture
def ctx():
    with posecal.Context() as c:
        yield c


@pytest.fixture(scope="module")
def sim_result():
    """One simulated calibration to convergence (sim://?seed=5, ~5 s), shared by a module's
    tests: (Result, path of the saved .yml, last frame as BGR array)."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp, posecal.Context() as c, \
            c.open("sim://?seed=5") as s:
        r = s.run()
        path = os.path.join(tmp, "cam.yml")
        s.save(path)
        yield r, path, s.last_frame()
