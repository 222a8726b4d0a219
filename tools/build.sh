#!/usr/bin/env bash
# Configures and builds one preset (default: release). Used by demo.sh and test.sh.
set -euo pipefail
preset=${1:-release}
shift || true
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
# Relative paths in the ccache hash, and the build folder left out of it
# (ccache hashes the working directory of every -g compile by default): a fresh
# clone or worktree elsewhere (CI) reuses the cache. The price is that debug
# info of a cache hit names the folder that first compiled it.
export CCACHE_BASEDIR="$root"
export CCACHE_NOHASHDIR=1
# The test programs' precompiled header (tests/CMakeLists.txt): ccache caches a
# compile that uses one only with these sloppiness flags (its manual,
# "Precompiled headers"); without them every test is a miss on a warm cache.
export CCACHE_SLOPPINESS=pch_defines,time_macros,include_file_mtime,include_file_ctime
if [ ! -f "build/$preset/build.ninja" ]; then
  cmake --preset "$preset" >/dev/null
fi
jobs=$(nproc 2>/dev/null || echo 2)
cmake --build --preset "$preset" -j "$jobs" "$@"
