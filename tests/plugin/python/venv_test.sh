#!/bin/bash
# plugin_python_venv: `pip install` of the source tree's package into a fresh virtualenv, offline
# (--no-index --no-build-isolation: setuptools and wheel from the system), then the Python tests
# against the installed package, with the library found through POSECAL_LIBRARY, and mypy on
# the newcomer example against the installed package (which needs its py.typed marker).
#
# usage: venv_test.sh PYTHON SOURCE_DIR WORK_DIR LIBRARY
set -euo pipefail
python=$1 src=$2 work=$3 lib=$4
rm -rf "$work"
mkdir -p "$work/src"
unset PYTHONPATH POSECAL_LIBRARY
export PYTHONDONTWRITEBYTECODE=1

# pip builds in the directory it installs from (build/, posecal.egg-info/): install from a copy
# of plugin/python, so the test leaves the source tree as it was.
cp -r "$src/plugin/python/." "$work/src/"
rm -rf "$work/src/build" "$work/src"/*.egg-info
find "$work/src" -name __pycache__ -prune -exec rm -rf {} +

echo "== $python -m venv --system-site-packages"
"$python" -m venv --system-site-packages "$work/venv"
venv_python=$work/venv/bin/python

echo "== pip install --no-build-isolation --no-deps (offline)"
"$venv_python" -m pip install --no-index --no-build-isolation --no-deps \
  --disable-pip-version-check "$work/src"
"$venv_python" -m pip show --files posecal

echo "== the Python tests against the installed package"
cd "$src/tests/plugin/python"
POSECAL_LIBRARY=$lib POSECAL_EXPECT_PACKAGE_UNDER=$work/venv POSECAL_SOURCE_DIR=$src \
  "$venv_python" -m pytest -p no:cacheprovider -v \
  test_binding_package.py test_binding_errors.py test_binding_numpy.py \
  test_examples.py::test_newcomer_station

echo "== mypy on docs/examples/station.py, posecal's types from the installed package"
"$venv_python" -m mypy --strict --no-warn-return-any --cache-dir "$work/mypy-cache" \
  "$src/docs/examples/station.py"
echo "venv test ok"
