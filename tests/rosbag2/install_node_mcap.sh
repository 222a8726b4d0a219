#!/bin/sh
# Installs the independent MCAP / ROS 2 CDR implementations the rosbag2 tests
# check against (@mcap/core, @foxglove/rosmsg, @foxglove/rosmsg2-serialization,
# the pure-JS fzstd / lz4js decompressors, and @foxglove/ws-protocol + ws for
# the Foxglove live test) from npm into CACHE_DIR, once.
# Usage: install_node_mcap.sh CACHE_DIR. Exit 0 when usable, 1 otherwise (the reason on stderr).
set -u
cache="$1"
pkgs="@mcap/core@2.2.2 @foxglove/rosmsg@5.0.5 @foxglove/rosmsg2-serialization@3.1.0 fzstd@0.1.1 lz4js@0.2.0
  @foxglove/ws-protocol@0.8.0 ws@8.18.0"
ready() {
  for p in @mcap/core @foxglove/rosmsg @foxglove/rosmsg2-serialization fzstd lz4js @foxglove/ws-protocol ws; do
    [ -f "$cache/node_modules/$p/package.json" ] || return 1
  done
  return 0
}
if ! command -v node >/dev/null 2>&1; then echo "node not installed (apt-get install nodejs npm)" >&2; exit 1; fi
if ready; then exit 0; fi
if ! command -v npm >/dev/null 2>&1; then echo "npm not installed (apt-get install npm)" >&2; exit 1; fi
mkdir -p "$cache" || exit 1
exec 9>"$cache/.install.lock"
flock 9
if ready; then exit 0; fi
# shellcheck disable=SC2086
npm install --prefix "$cache" --no-audit --no-fund --no-save --loglevel=error $pkgs >"$cache/npm-install.log" 2>&1 ||
  { echo "npm install $pkgs failed (offline?): see $cache/npm-install.log" >&2; tail -5 "$cache/npm-install.log" >&2; exit 1; }
ready || { echo "npm install left packages missing: see $cache/npm-install.log" >&2; exit 1; }
exit 0
