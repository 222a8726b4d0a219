#!/usr/bin/env bash
# The README's test command: installs what is missing, builds `release`, runs
# the default ctest labels (everything but bench and fuzz), then the two-thread
# stress tests again under ThreadSanitizer.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
bash tools/install-deps.sh
bash tools/build.sh release
jobs=$(nproc 2>/dev/null || echo 2)
ctest --preset release -j "$jobs"
if [ "${KESTREL_SKIP_TSAN:-0}" != "1" ]; then
  echo "== ThreadSanitizer: stress label =="
  bash tools/build.sh tsan --target rt_stress_test
  ctest --preset tsan -j "$jobs"
fi
