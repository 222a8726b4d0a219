#!/usr/bin/env bash
# The README's test command and CI's (.ci/run): installs what is missing, then
#   1. release build + the default ctest labels (everything but bench and fuzz)
#   1b. the .deb: cpack from the release tree, apt-get install, checks, dpkg -r
#   2. the ASan + UBSan suite (clang): build target kestrel_asan_suite, `ctest
#      --preset debug` (label asan, sanitizer-sized flights: KESTREL_TEST_SCALE=small)
#   3. bounded libFuzzer runs of every parser, linked in that same debug tree
#      (its objects carry the fuzzer's coverage already): `ctest --preset
#      debug-fuzz`, KESTREL_FUZZ_SECONDS per target (default here 20)
#   4. the two-thread stress tests under ThreadSanitizer
# and prints what each part cost. docs/testing.md: the suites, what each
# covers, local runs, the CPU-hour fuzz command, measured costs.
# Skips (local use only): KESTREL_SKIP_ASAN=1, KESTREL_SKIP_FUZZ=1, KESTREL_SKIP_TSAN=1,
# KESTREL_SKIP_DEB=1 (the .deb part installs a package: root or sudo).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
jobs=$(nproc 2>/dev/null || echo 2)
script_name=test.sh
# shellcheck source=tools/timed_parts.sh
source "$root/tools/timed_parts.sh"

part "install-deps" bash tools/install-deps.sh
part "release build" bash tools/build.sh release
part "release suite" ctest --preset release -j "$jobs"
# The companion computer's .deb from the release tree just built (no rebuild): build, install,
# `kestrel version`, unit and udev checks, remove (tools/package/check_deb.sh, docs/package.md).
if [ "${KESTREL_SKIP_DEB:-0}" != "1" ]; then
  part "deb package (build, install, remove)" bash tools/package/check_deb.sh build/release
fi
if [ "${KESTREL_SKIP_ASAN:-0}" != "1" ]; then
  part "asan+ubsan build (asan suite)" bash tools/build.sh debug --target kestrel_asan_suite
  part "asan+ubsan suite" ctest --preset debug -j "$jobs"
fi
if [ "${KESTREL_SKIP_FUZZ:-0}" != "1" ]; then
  part "fuzz build (the debug tree's fuzzers)" bash tools/build.sh debug --target kestrel_fuzz_all
  export KESTREL_FUZZ_SECONDS=${KESTREL_FUZZ_SECONDS:-20}
  part "fuzz run ($KESTREL_FUZZ_SECONDS s per target)" ctest --preset debug-fuzz -j "$jobs"
  echo "== fuzz: executions per target =="
  for log in build/debug/tests/fuzz/logs/*.log; do
    printf '  %-22s %12s execs %8s/s  corpus %s\n' "$(basename "$log" .log)" \
      "$(sed -n 's/^stat::number_of_executed_units: *//p' "$log")" \
      "$(sed -n 's/^stat::average_exec_per_sec: *//p' "$log")" \
      "$(find "build/debug/tests/fuzz/corpus/$(basename "$log" .log)" -type f | wc -l)"
  done
fi
if [ "${KESTREL_SKIP_TSAN:-0}" != "1" ]; then
  part "tsan build" bash tools/build.sh tsan --target kestrel_tsan_suite
  part "tsan stress suite" ctest --preset tsan -j "$jobs"
fi
