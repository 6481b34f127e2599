#!/usr/bin/env bash
# The unit, fake-hw and plugin tests under AddressSanitizer + UndefinedBehaviorSanitizer
# (docs/testing.md, "Sanitizers"): configures BUILD_DIR (default build-asan) with
# -DPOSECAL_SANITIZE=ON, which compiles the whole tree with -fsanitize=address,undefined (core,
# the Aravis and V4L2 backends, libposecal.so, the CLI and the tests), builds it and runs every
# test but the slow ones and the real-hardware ones.
#
#   tests/run_sanitized.sh [BUILD_DIR] [JOBS]
#
# Python tests: python3 is not instrumented, and an ASan library it dlopens needs the ASan
# runtime loaded first; they run in a second ctest call with LD_PRELOAD of GCC's libasan and
# leak detection off (CPython's own allocations at exit are not ours). Any sanitizer report
# fails the test that produced it (halt_on_error, abort_on_error).
set -euo pipefail
src=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$src/build-asan}
jobs=${2:-2}
start=$(date +%s)

# Benchmarks are not tests; RelWithDebInfo keeps the sanitizers' stack traces readable.
# CMAKE_ARGS: extra configure arguments (e.g. the ccache launchers).
# shellcheck disable=SC2086
cmake -S "$src" -B "$build" -DCMAKE_BUILD_TYPE=RelWithDebInfo -DPOSECAL_SANITIZE=ON \
  -DPOSECAL_BUILD_BENCHMARKS=OFF ${CMAKE_ARGS:-}
cmake --build "$build" -j"$jobs"
built=$(date +%s)

# verify_asan_link_order=0: the install test's consumers are plain executables linked against
# the (sanitized) libposecal.so, which brings the ASan runtime itself.
export ASAN_OPTIONS=detect_leaks=1:abort_on_error=1:strict_string_checks=1:verify_asan_link_order=0
export UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1
# Leaks of libraries outside posecal that live until the process ends, each with its reason.
export LSAN_OPTIONS=suppressions=$src/tests/lsan.supp:print_suppressions=0
status=0
ctest --test-dir "$build" -LE '^hw$|slow' -E '^plugin_python_' -j"$jobs" --output-on-failure \
  --timeout 900 || status=1

# libstdc++ is preloaded too: ASan resolves the real __cxa_throw when it starts, and a python3
# that does not link libstdc++ itself would leave it unresolved ("CHECK failed ... real___cxa_throw"
# at the first C++ exception inside the library).
libasan=$(gcc -print-file-name=libasan.so)
libstdcxx=$(gcc -print-file-name=libstdc++.so)
LD_PRELOAD="$libasan $libstdcxx" ASAN_OPTIONS=detect_leaks=0:abort_on_error=1:verify_asan_link_order=0 \
  ctest --test-dir "$build" -R '^plugin_python_' --output-on-failure --timeout 900 || status=1

echo "run_sanitized: build $((built - start)) s, tests $(($(date +%s) - built)) s, status $status"
exit $status
