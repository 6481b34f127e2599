#!/bin/bash
# plugin_deb: builds the Debian packages of this build with CPack (cmake/packaging.cmake), checks
# their names, SONAME, contents and dependencies, then installs them with apt-get into this
# machine (root only), uses them as a user would (the CLI, a C consumer by pkg-config and by
# find_package, the Python package with the newcomer example) and purges them again.
#
# usage: deb_test.sh BUILD_DIR SOURCE_DIR WORK_DIR VERSION
# Exits 77 (ctest's skip) after the package checks when not root or without apt-get: the
# installation needs both. Refuses to run where another posecal is installed in /usr/local or
# the packages are already installed (it would test that one, or remove it).
set -euo pipefail
# (grep without -q in pipelines: -q stops reading early, and pipefail would report the writer's
# SIGPIPE.)
build=$1 src=$2 work=$3 version=$4
release=1
packages=(libposecal1 libposecal-dev posecal python3-posecal)
rm -rf "$work"
mkdir -p "$work"
unset POSECAL_LIBRARY LD_LIBRARY_PATH PYTHONPATH PKG_CONFIG_PATH || true

fail() { echo "FAIL: $*"; exit 1; }
deb_of() { echo "$work/debs/${1}_${version}-${release}_$(dpkg --print-architecture).deb"; }

echo "== cpack -G DEB"
cpack --config "$build/CPackConfig.cmake" -G DEB -B "$work/debs" > "$work/cpack.log" 2>&1 ||
  { cat "$work/cpack.log"; fail "cpack"; }
for p in "${packages[@]}"; do
  [ -f "$(deb_of "$p")" ] || { ls "$work/debs"; fail "no $(basename "$(deb_of "$p")")"; }
  [ "$(dpkg-deb -f "$(deb_of "$p")" Package)" = "$p" ] || fail "$p: wrong Package field"
  [ "$(dpkg-deb -f "$(deb_of "$p")" Version)" = "$version-$release" ] || fail "$p: wrong Version"
  dpkg-deb -c "$(deb_of "$p")" | grep > /dev/null " ./usr/share/doc/$p/copyright$" || fail "$p: no copyright"
done
[ "$(ls "$work/debs"/*.deb | wc -l)" = 4 ] || fail "packages other than the four: $(ls "$work/debs")"

contents() { dpkg-deb -c "$(deb_of "$1")" | awk '{print $6}' | sed 's|^\./|/|' | grep -v '/$'; }
depends() { dpkg-deb -f "$(deb_of "$1")" Depends; }
# libposecal1: the library under its SONAME and Debian's file name, nothing for development.
lib=$(contents libposecal1 | grep '/libposecal\.so\.1\.[0-9]*\.[0-9]*$') || fail "no libposecal.so.1.M.P"
contents libposecal1 | grep > /dev/null '/libposecal\.so\.1$' || fail "no libposecal.so.1 link"
! contents libposecal1 | grep > /dev/null -e '/libposecal\.so$' -e '\.h$' -e '\.pc$' || fail "dev files in libposecal1"
mkdir -p "$work/x"
dpkg-deb -x "$(deb_of libposecal1)" "$work/x"
[ "$(objdump -p "$work/x$lib" | awk '/SONAME/ {print $2}')" = libposecal.so.1 ] || fail "SONAME"
dpkg-deb --ctrl-tarfile "$(deb_of libposecal1)" | tar -xO ./shlibs | grep > /dev/null '^libposecal 1 libposecal1 ' ||
  fail "libposecal1 has no shlibs file"
# Its dependencies are the Debian packages the library links (dpkg-shlibdeps).
for d in libopencv-core406 libopencv-contrib406 libaravis-0.8-0 libcairo2 libpng16-16 libusb-1.0-0; do
  depends libposecal1 | grep > /dev/null "$d" || fail "libposecal1 does not depend on $d: $(depends libposecal1)"
done
for p in libposecal-dev posecal python3-posecal; do
  depends $p | grep > /dev/null "libposecal1 (= $version-$release)" || fail "$p: not on libposecal1 = $version"
done
contents libposecal-dev | grep > /dev/null '/usr/include/posecal.h$' || fail "no header in libposecal-dev"
contents libposecal-dev | grep > /dev/null '/libposecal\.so$' || fail "no libposecal.so in libposecal-dev"
contents posecal | grep > /dev/null '^/usr/bin/posecal$' || fail "no /usr/bin/posecal"
contents posecal | grep > /dev/null '^/usr/share/doc/posecal/examples/station.py$' || fail "examples not in posecal"
contents python3-posecal | grep > /dev/null '/dist-packages/posecal/py.typed$' || fail "no py.typed"
contents python3-posecal | grep > /dev/null "^/usr/share/posecal/python/posecal-$version-py3-none-any.whl$" ||
  fail "no wheel in python3-posecal"
depends python3-posecal | grep > /dev/null python3-numpy || fail "python3-posecal does not need numpy"

if [ "$(id -u)" != 0 ] || ! command -v apt-get > /dev/null; then
  echo "package checks passed; installing them needs root and apt-get: skipped"
  exit 77
fi
for p in "${packages[@]}"; do
  if dpkg-query -W -f='${Status}' "$p" 2> /dev/null | grep > /dev/null "ok installed"; then
    fail "$p is already installed on this machine; remove it first (apt-get purge $p)"
  fi
done
if ls /usr/local/lib/libposecal.so* /usr/local/lib/*/libposecal.so* /usr/local/bin/posecal \
      /usr/local/lib/python3*/dist-packages/posecal > /dev/null 2>&1; then
  fail "a posecal installed under /usr/local would shadow the packages; remove it first"
fi

purge() { apt-get purge -y "${packages[@]}" > "$work/purge.log" 2>&1 || cat "$work/purge.log"; }
trap purge EXIT
echo "== apt-get install the four packages"
apt-get install -y --no-install-recommends "$(deb_of libposecal1)" "$(deb_of libposecal-dev)" \
  "$(deb_of posecal)" "$(deb_of python3-posecal)" > "$work/apt.log" 2>&1 ||
  { cat "$work/apt.log"; fail "apt-get install"; }

echo "== the CLI"
[ "$(command -v posecal)" = /usr/bin/posecal ] || fail "posecal on PATH is $(command -v posecal)"
posecal --version | grep > /dev/null "$version" || fail "posecal --version: $(posecal --version)"
# (its RUNPATH, $ORIGIN/../lib, is the packaged library's directory)
used=$(ldd /usr/bin/posecal | awk '/libposecal.so.1/ {print $3}')
[ "$(realpath "$used")" = "$(realpath /usr/lib/libposecal.so.1)" ] ||
  fail "the CLI does not use the packaged library but $used"
(cd "$work" && timeout 600 posecal simulate --seed 2 --out "$work/sim.yml" > "$work/simulate.log") ||
  { cat "$work/simulate.log"; fail "posecal simulate"; }
grep -q camera_matrix "$work/sim.yml" || fail "posecal simulate wrote no calibration"

echo "== a C consumer: pkg-config and find_package, from /usr only"
export PKG_CONFIG_LIBDIR=/usr/lib/$(dpkg-architecture -qDEB_HOST_MULTIARCH 2> /dev/null || echo x86_64-linux-gnu)/pkgconfig:/usr/lib/pkgconfig:/usr/share/pkgconfig
[ "$(pkg-config --modversion posecal)" = "$version" ] || fail "pkg-config --modversion"
cc -std=c99 -Wall -Wextra -Wpedantic -Werror "$src/tests/plugin/consumer/consumer.c" \
   $(pkg-config --cflags --libs posecal) -o "$work/consumer-pc"
"$work/consumer-pc"
cmake -S "$src/tests/plugin/consumer" -B "$work/consumer-cmake" -DCMAKE_BUILD_TYPE=Release \
      -DCMAKE_FIND_USE_CMAKE_SYSTEM_PATH=ON -Dposecal_DIR=/usr/lib/cmake/posecal \
      > "$work/consumer-configure.log" || { cat "$work/consumer-configure.log"; fail "find_package"; }
cmake --build "$work/consumer-cmake" > "$work/consumer-build.log"
"$work/consumer-cmake/consumer"

echo "== the Python package with Debian's python3, and the newcomer example from the docs"
env -i PATH=/usr/bin:/bin HOME="$work" /usr/bin/python3 -c "
import posecal, numpy
assert posecal.__file__.startswith('/usr/lib/'), posecal.__file__
assert posecal.__version__ == '$version', posecal.__version__
print('posecal', posecal.__version__, 'from', posecal.__file__)
"
(cd "$work" && env -i PATH=/usr/bin:/bin HOME="$work" timeout 600 /usr/bin/python3 \
   /usr/share/doc/posecal/examples/station.py "$work/station.yml" > "$work/station.log" 2>&1) ||
  { cat "$work/station.log"; fail "examples/station.py"; }
grep -q "^saved " "$work/station.log" || fail "station.py saved nothing"

echo "== pip install of the packaged wheel into a virtualenv (offline), which loads libposecal1's library"
wheel=$(ls /usr/share/posecal/python/posecal-"$version"-py3-none-any.whl) || fail "no wheel in python3-posecal"
env -i PATH=/usr/bin:/bin HOME="$work" /usr/bin/python3 -m venv --system-site-packages "$work/venv"
env -i PATH=/usr/bin:/bin HOME="$work" "$work/venv/bin/python" -m pip install --no-index --no-deps \
  --disable-pip-version-check --quiet "$wheel" || fail "pip install $wheel"
env -i PATH=/usr/bin:/bin HOME="$work" "$work/venv/bin/python" -c "
import os, posecal, posecal._native as n
assert posecal.__file__.startswith('$work/venv/'), posecal.__file__
mapped = {l.split()[-1] for l in open('/proc/self/maps') if 'libposecal' in l}
assert mapped == {os.path.realpath('/usr/lib/libposecal.so.1')}, mapped
print('in the virtualenv: posecal', posecal.__version__, 'from', posecal.__file__, 'library', mapped.pop())
"

echo "== apt-get purge"
trap - EXIT
purge
for p in "${packages[@]}"; do
  ! dpkg-query -W -f='${Status}' "$p" 2> /dev/null | grep > /dev/null "ok installed" || fail "$p still installed"
done
[ ! -e /usr/bin/posecal ] && ! ls /usr/lib/libposecal.so* > /dev/null 2>&1 || fail "files left after purge"
echo "OK: four packages built, installed, used and removed"
