#!/usr/bin/env bash
# Runs every libFuzzer target of tests/fuzz/ for SECONDS each (docs/testing.md, "Fuzzing").
#
#   tests/fuzz/run_fuzzers.sh BUILD_DIR SECONDS [TARGET...]
#
# BUILD_DIR is a clang build configured with -DPOSECAL_FUZZ=ON (target posecal_fuzzers built).
# Each target starts from its seed corpus tests/fuzz/corpus/<target>/ and a working corpus in
# BUILD_DIR/fuzz/<target>/corpus (kept between runs, so longer runs build on earlier ones);
# findings go to BUILD_DIR/fuzz/<target>/ as crash-*, leak-*, timeout-*, oom-*. An input that
# runs longer than 1 s is a failure (-timeout=1), as is more than 2 GiB of memory. Prints per
# target the executions, the final coverage (cov: edges, ft: features) and the outcome; exits
# non-zero if any target crashed, leaked, hung or ran out of memory.
# Extra libFuzzer flags: FUZZ_ARGS="-jobs=..." (split on spaces).
set -uo pipefail
if [[ $# -lt 2 ]]; then
  echo "usage: $0 BUILD_DIR SECONDS [TARGET...]" >&2
  exit 2
fi
build=$(cd "$1" && pwd)
seconds=$2
shift 2
here=$(cd "$(dirname "$0")" && pwd)
if [[ $# -gt 0 ]]; then
  targets=("$@")
else
  targets=()
  for src in "$here"/fuzz_*.cpp; do targets+=("$(basename "$src" .cpp)"); done
fi

# ASan's allocator returns freed memory to the kernel (madvise) and recycles its quarantine in
# bursts; on a loaded machine such a burst inside one input has exceeded the 1 s timeout (three
# "timeouts" whose inputs re-ran in 33-225 ms). Not returning memory and a smaller quarantine keep
# the timeout about posecal's code. An ASAN_OPTIONS of the caller replaces this.
export ASAN_OPTIONS=${ASAN_OPTIONS:-allocator_release_to_os_interval_ms=-1:quarantine_size_mb=64}

# OpenCV's parallel_for_ starts a thread pool whose workers spin (sched_yield) between the small
# loops of one 256x256 frame: single-threaded, fuzz_session_feed runs about 1.3x the inputs per
# second (187 -> 250 over the same 1500 inputs). The targets test posecal's code, not OpenCV's
# threading, which the threaded test suites cover.
export OPENCV_FOR_THREADS_NUM=${OPENCV_FOR_THREADS_NUM:-1}

failed=0
failures=()
printf '%-22s %12s %8s %8s %10s  %s\n' target executions cov ft seconds outcome
for t in "${targets[@]}"; do
  bin=$build/bin/$t
  work=$build/fuzz/$t
  mkdir -p "$work/corpus"
  if [[ ! -x $bin ]]; then
    printf '%-22s %s\n' "$t" "not built ($bin)"
    failed=1
    continue
  fi
  seeds=()
  [[ -d $here/corpus/$t ]] && seeds+=("$here/corpus/$t")
  log=$work/last_run.log
  start=$(date +%s)
  # shellcheck disable=SC2086
  "$bin" -max_total_time="$seconds" -timeout=1 -rss_limit_mb=2048 -print_final_stats=1 \
    -artifact_prefix="$work/" ${FUZZ_ARGS:-} "$work/corpus" "${seeds[@]}" >"$log" 2>&1
  rc=$?
  took=$(($(date +%s) - start))
  execs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$log" | tail -1)
  # -fork=N prints no final stats: its last "#N: cov: ..." line counts the executions.
  [[ -z $execs ]] && execs=$(grep -o '^#[0-9]*' "$log" | tail -1 | tr -d '#')
  # The last status line with coverage: "#N  DONE|pulse|NEW ... cov: X ft: Y ..."
  cov=$(grep -o 'cov: [0-9]*' "$log" | tail -1 | cut -d' ' -f2)
  ft=$(grep -o 'ft: [0-9]*' "$log" | tail -1 | cut -d' ' -f2)
  outcome=ok
  if [[ $rc -ne 0 ]]; then
    failed=1
    artifact=$(grep -o "Test unit written to [^ ]*" "$log" | tail -1 | sed 's/Test unit written to //')
    kind=$(grep -m1 -o 'ERROR: libFuzzer: [a-z-]*\|ERROR: AddressSanitizer: [a-z-]*\|ERROR: LeakSanitizer: [a-z-]*\|runtime error: .*\|SUMMARY: UndefinedBehaviorSanitizer: [a-z-]*' "$log")
    outcome="FAILED (exit $rc: ${kind:-see $log}; input: ${artifact:-none})"
  fi
  printf '%-22s %12s %8s %8s %10s  %s\n' "$t" "${execs:-?}" "${cov:-?}" "${ft:-?}" "$took" "$outcome"
  [[ $rc -ne 0 ]] && failures+=("$t|$log|${artifact:-}")
done
# A CI machine's build tree is gone after the run: print what a finding needs to be reproduced
# (the sanitizer's report and the input, base64 up to 8 KiB) where the run's output keeps it.
for f in "${failures[@]}"; do
  IFS='|' read -r t log artifact <<<"$f"
  echo
  echo "=== $t: the end of $log"
  grep -v '^#[0-9]' "$log" | tail -40
  if [[ -n $artifact && -f $artifact ]]; then
    echo "=== $t: the input ($(stat -c %s "$artifact") bytes; base64 -d to reproduce)"
    head -c 8192 "$artifact" | base64
  fi
done
exit $failed
