#!/bin/sh
# lsan_tracer_retry_test.sh RETRY_SCRIPT: checks lsan_tracer_retry.sh against fake programs that
# print what a sanitized test prints, counting how often each is run: a pass runs once, a lone
# tracer crash once more (and fails if it repeats), anything else besides the crash never again.
set -u
retry=$1
dir=$(mktemp -d)
trap 'rm -rf "$dir"' EXIT
failures=0

# fake RUNS_BEFORE_PASS EXIT_CODE EXTRA_LINE: a program that crashes like LeakSanitizer's tracer
# (printing EXTRA_LINE too, if not empty) until it has run RUNS_BEFORE_PASS times, then passes.
cat >"$dir/fake" <<'FAKE'
#!/bin/sh
count_file=$1 runs_before_pass=$2 code=$3 extra=$4
n=$(( $(cat "$count_file" 2>/dev/null || echo 0) + 1 ))
echo "$n" >"$count_file"
if [ "$n" -gt "$runs_before_pass" ]; then echo "[  PASSED  ] 1 test."; exit 0; fi
[ -n "$extra" ] && echo "$extra"
echo "Tracer caught signal 11: addr=0x0 pc=0x0 sp=0x0"
echo "==1==LeakSanitizer has encountered a fatal error."
exit "$code"
FAKE
chmod +x "$dir/fake"

# check NAME WANT_EXIT WANT_RUNS RUNS_BEFORE_PASS EXIT_CODE EXTRA_LINE
check() {
  name=$1 want_exit=$2 want_runs=$3
  rm -f "$dir/count"
  "$retry" "$dir/fake" "$dir/count" "$4" "$5" "$6" >"$dir/out" 2>&1
  got_exit=$?
  got_runs=$(cat "$dir/count")
  if [ "$got_exit" -ne "$want_exit" ] || [ "$got_runs" -ne "$want_runs" ]; then
    echo "FAIL $name: exit $got_exit (want $want_exit), runs $got_runs (want $want_runs)"
    sed 's/^/  | /' "$dir/out"
    failures=$((failures + 1))
  else
    echo "ok   $name"
  fi
}

check "a pass runs once" 0 1 0 23 ""
check "a lone tracer crash runs once more" 0 2 1 23 ""
check "a tracer crash twice fails with its exit code" 23 2 5 23 ""
check "a leak report is not retried" 23 1 5 23 "ERROR: LeakSanitizer: detected memory leaks"
check "an ASan error is not retried" 23 1 5 23 "==1==ERROR: AddressSanitizer: heap-use-after-free"
check "a UBSan error is not retried" 23 1 5 23 "x.cpp:1:2: runtime error: signed integer overflow"
check "a failed check is not retried" 23 1 5 23 "[  FAILED  ] Abi.Misuse"
grep -q "running once more" "$dir/out" && { echo "FAIL: the last run said it retried"; failures=$((failures + 1)); }
[ "$failures" -eq 0 ]
