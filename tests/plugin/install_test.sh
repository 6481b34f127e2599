#!/bin/bash
# plugin_install: installs the build into a temporary prefix and uses it as a consumer would:
# find_package(posecal) + posecal::posecal, pkg-config, the installed CLI and Python package.
#
# usage: install_test.sh BUILD_DIR SOURCE_DIR WORK_DIR PYTHON PYTHON_DIR
#   PYTHON_DIR: where the build installs the Python package, relative to the prefix
#   (plugin/CMakeLists.txt: POSECAL_PYTHON_INSTALL_DIR); PYTHON: the interpreter it is for.
set -euo pipefail
build=$1 src=$2 work=$3 python=${4:-python3} pydir=${5:-lib/python3/dist-packages}
prefix=$work/prefix
rm -rf "$work"
mkdir -p "$work"
unset POSECAL_LIBRARY LD_LIBRARY_PATH PYTHONPATH || true

echo "== cmake --install into $prefix"
cmake --install "$build" --prefix "$prefix" > "$work/install.log"
libdir=
for d in lib lib64 lib/x86_64-linux-gnu lib/aarch64-linux-gnu; do
  if [ -e "$prefix/$d/libposecal.so" ]; then libdir=$d; break; fi
done
[ -n "$libdir" ] || { echo "libposecal.so not installed"; cat "$work/install.log"; exit 1; }
for f in "$libdir/libposecal.so" "$libdir/libposecal.so.1" include/posecal.h bin/posecal \
         "$libdir/pkgconfig/posecal.pc" "$libdir/cmake/posecal/posecalConfig.cmake" \
         "$libdir/cmake/posecal/posecalConfigVersion.cmake" \
         "$pydir/posecal/__init__.py" "$pydir/posecal/_install_paths.py" \
         "$pydir/posecal/py.typed"; do
  [ -e "$prefix/$f" ] || { echo "missing in the prefix: $f"; exit 1; }
done
# The wheel for `pip install` from the prefix, where the build made one (plugin/CMakeLists.txt).
if ls "$build"/plugin/python-wheel/posecal-*.whl > /dev/null 2>&1; then
  ls "$prefix"/share/posecal/python/posecal-*-py3-none-any.whl > /dev/null || { echo "no wheel installed"; exit 1; }
fi
[ -L "$prefix/$libdir/libposecal.so" ] && [ -L "$prefix/$libdir/libposecal.so.1" ] ||
  { echo "soname links missing"; exit 1; }
[ "$(readlink "$prefix/$libdir/libposecal.so")" = libposecal.so.1 ] || { echo "bad dev link"; exit 1; }
# Only the C ABI is exported.
others=$(nm -D --defined-only "$prefix/$libdir/libposecal.so" | awk '{print $3}' |
         grep -v -e '^posecal_' -e '^POSECAL_1$' || true)
[ -z "$others" ] || { echo "symbols outside the C ABI are exported:"; echo "$others" | head; exit 1; }
# The only installed header is posecal.h.
[ "$(find "$prefix/include" -type f | wc -l)" = 1 ] || { echo "extra headers installed"; exit 1; }

echo "== find_package(posecal)"
cmake -S "$src/tests/plugin/consumer" -B "$work/consumer-cmake" -DCMAKE_PREFIX_PATH="$prefix" \
      -DCMAKE_BUILD_TYPE=Release > "$work/consumer-configure.log"
cmake --build "$work/consumer-cmake" > "$work/consumer-build.log"
"$work/consumer-cmake/consumer"

echo "== pkg-config"
export PKG_CONFIG_PATH=$prefix/$libdir/pkgconfig
[ "$(pkg-config --modversion posecal)" = "$(grep -m1 -o 'project(posecal VERSION [0-9.]*' "$src/CMakeLists.txt" | cut -d' ' -f3)" ]
cc -std=c99 -Wall -Wextra -Wpedantic -Werror "$src/tests/plugin/consumer/consumer.c" \
   $(pkg-config --cflags --libs posecal) -Wl,-rpath,"$prefix/$libdir" -o "$work/consumer-pc"
"$work/consumer-pc"
# The documented example builds the same way.
cc -std=c99 -Wall -Wextra -Wpedantic -Werror "$src/docs/examples/calibrate.c" \
   $(pkg-config --cflags --libs posecal) -Wl,-rpath,"$prefix/$libdir" -o "$work/calibrate-example"

echo "== installed CLI (RPATH \$ORIGIN/../$libdir)"
"$prefix/bin/posecal" version | grep -q "ABI 1"
used=$(ldd "$prefix/bin/posecal" | awk '/libposecal.so.1/ {print $3}')
[ "$(realpath "$used")" = "$(realpath "$prefix/$libdir/libposecal.so.1")" ] ||
  { echo "the installed CLI uses $used, not the installed library"; exit 1; }

echo "== installed Python package (library found through the install prefix)"
# For the default prefix /usr/local, the directory is one a system interpreter searches (Debian
# 12: /usr/local/lib/python3.11/dist-packages, not lib/python3/dist-packages); an interpreter
# that searches nothing under /usr/local (pyenv's) has no say.
"$python" -c "
import site, sys
local = [d for d in site.getsitepackages() if d.startswith('/usr/local/')]
sys.exit(bool(local) and '/usr/local/$pydir' not in local)" ||
  { echo "$python does not look for packages in /usr/local/$pydir"; exit 1; }
PYTHONPATH=$prefix/$pydir "$python" -c "
import os, sys, posecal
assert os.path.realpath(posecal.__file__).startswith(os.path.realpath('$prefix')), posecal.__file__
lib = os.path.realpath(posecal.library_path)
assert lib.startswith(os.path.realpath('$prefix')), lib
assert posecal.abi_version() == 1
with posecal.Context(backends=['sim']) as ctx, ctx.open('sim://?seed=3') as s:
    assert s.step() and s.status['frames'] == 1
    assert s.last_frame().shape == (720, 1280, 3)
print('python: posecal', posecal.__version__, 'library', posecal.version(), 'from', lib)
"
echo "install test ok"
