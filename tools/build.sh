#!/usr/bin/env bash
# Configures and builds one preset (default: release). Used by demo.sh and test.sh.
set -euo pipefail
preset=${1:-release}
shift || true
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
# Relative paths in the ccache hash: a fresh clone elsewhere reuses the cache.
export CCACHE_BASEDIR="$root"
if [ ! -f "build/$preset/build.ninja" ]; then
  cmake --preset "$preset" >/dev/null
fi
jobs=$(nproc 2>/dev/null || echo 2)
cmake --build --preset "$preset" -j "$jobs" "$@"
