"""The package around the binding: __version__, the py.typed marker, the exceptions' builtin
bases, and (when run against a pip-installed package) its metadata.

Run by ctest (plugin_python_package, and plugin_python_venv against a pip install).
"""
import builtins
import importlib.metadata
import os
import pickle
import re

import pytest

import posecal
from posecal import errors
from conftest import SOURCE_DIR


def cmake_project_version():
    with open(os.path.join(SOURCE_DIR, "CMakeLists.txt")) as f:
        return re.search(r"project\(posecal\s+VERSION\s+([0-9.]+)", f.read()).group(1)


def test_version():
    assert re.fullmatch(r"\d+\.\d+\.\d+", posecal.__version__)
    # The package follows the library's version (CMakeLists.txt), and the library under test
    # was built from this tree.
    assert posecal.__version__ == cmake_project_version()
    assert posecal.version() == posecal.__version__
    assert posecal.abi_version() == posecal._native.ABI_VERSION == 1


def test_py_typed_marker():
    package_dir = os.path.dirname(posecal.__file__)
    assert os.path.isfile(os.path.join(package_dir, "py.typed"))


def test_public_api_is_annotated():
    # Every public callable of the package says what it takes and returns (mypy checks the
    # annotations themselves: plugin_python_types).
    import inspect

    missing = []
    for name in posecal.__all__:
        obj = getattr(posecal, name)
        members = [(name, obj)]
        if inspect.isclass(obj) and not issubclass(obj, BaseException):
            members = [("%s.%s" % (name, m), v) for m, v in vars(obj).items()
                       if not m.startswith("_") or m in ("__init__", "__enter__", "__iter__")]
        for qual, member in members:
            fn = member.fget if isinstance(member, property) else member
            if not inspect.isfunction(fn):
                continue
            sig = inspect.signature(fn)
            if sig.return_annotation is inspect.Signature.empty:
                missing.append(qual + " -> ?")
            for p in sig.parameters.values():
                if p.name != "self" and p.annotation is inspect.Parameter.empty:
                    missing.append("%s(%s)" % (qual, p.name))
    assert not missing, missing


@pytest.mark.skipif(not os.environ.get("POSECAL_EXPECT_PACKAGE_UNDER"),
                    reason="the source tree's package has no distribution metadata")
def test_installed_distribution():
    assert importlib.metadata.version("posecal") == posecal.__version__
    files = {str(f) for f in importlib.metadata.files("posecal")}
    assert "posecal/py.typed" in files and "posecal/__init__.py" in files
    assert "posecal/_install_paths.py" not in files  # only `cmake --install` writes one
    requires = importlib.metadata.requires("posecal")  # "numpy>=1.21" or "numpy (>=1.21)"
    assert len(requires) == 1 and re.fullmatch(r"numpy *\(?>=1\.21\)?", requires[0]), requires


# ---- exceptions --------------------------------------------------------------------------------
# The builtins each status's exception also is: independent of errors.py, on purpose.
EXPECTED_BASES = {
    errors.E_INVALID_ARGUMENT: (posecal.InvalidArgumentError, ValueError),
    errors.E_NOT_FOUND: (posecal.NotFoundError, LookupError),
    errors.E_BUFFER_TOO_SMALL: (posecal.BufferTooSmallError, ValueError),
    errors.E_TIMEOUT: (posecal.TimeoutError, builtins.TimeoutError, OSError),
    errors.E_DEVICE: (posecal.DeviceError, OSError),
    errors.E_STATE: (posecal.StateError, RuntimeError),
    errors.E_IO: (posecal.FileError, OSError),
    errors.E_INTERNAL: (posecal.InternalError, RuntimeError),
    errors.E_DEGENERATE: (posecal.DegenerateError, ValueError),
    errors.E_UNSUPPORTED: (posecal.UnsupportedError, NotImplementedError),
}


def test_every_status_has_its_builtin_base():
    assert set(EXPECTED_BASES) == set(errors.STATUS_NAMES) - {errors.OK}
    for status, bases in EXPECTED_BASES.items():
        e = errors.error_for(status, "what happened")
        assert type(e) is bases[0]
        assert isinstance(e, posecal.PosecalError)
        for b in bases:
            assert isinstance(e, b), (type(e), b)
        assert str(e) == "what happened [%s]" % errors.STATUS_NAMES[status]
        assert (e.status, e.message) == (status, "what happened")
        if isinstance(e, OSError):
            assert e.errno is None  # the ABI reports a status, not an errno
        # Pickled intact (multiprocessing, concurrent.futures).
        back = pickle.loads(pickle.dumps(e))
        assert (type(back), back.status, back.message) == (type(e), status, e.message)
    assert posecal.TimeoutError is not builtins.TimeoutError
    assert issubclass(posecal.InvalidTypeError, posecal.InvalidArgumentError)
    assert issubclass(posecal.InvalidTypeError, TypeError)


def test_library_errors_caught_as_builtins(ctx, tmp_path):
    # Code that knows nothing of posecal catches the library's errors by their builtin kind.
    with pytest.raises(builtins.TimeoutError):
        ctx.grab("external", 1, str(tmp_path), timeout_ms=20)
    with pytest.raises(OSError) as exc:
        ctx.evaluate(str(tmp_path / "missing.yml"), "sim://")
    assert type(exc.value) is posecal.FileError
    with pytest.raises(OSError):
        posecal.write_target(str(tmp_path / "no" / "such" / "dir" / "board.png"))
    with pytest.raises(LookupError):
        ctx.calibrate_images(str(tmp_path / "no-such-folder"))
    with pytest.raises(ValueError):
        ctx.open("sim://", bogus_key=1)
    with pytest.raises(TypeError):
        ctx.open(42)
    with posecal.Context(backends=["sim"]) as only_sim, pytest.raises(NotImplementedError):
        only_sim.open("external")
    with ctx.open("sim://?seed=2") as s, pytest.raises(RuntimeError):
        s.save(str(tmp_path / "x.yml"))  # no calibration before two keyframes
