#!/bin/sh
# Installs the independent MAVLink implementation the encoder test decodes
# with (node-mavlink + mavlink-mappings from npm) into CACHE_DIR, once.
# Usage: install_node_mavlink.sh CACHE_DIR. Exit 0 when usable, 1 otherwise
# (the reason on stderr: no node, no npm, no network).
set -u
cache="$1"
version="2.3.0"
if ! command -v node >/dev/null 2>&1; then echo "node not installed (apt-get install nodejs npm)" >&2; exit 1; fi
if [ -f "$cache/node_modules/node-mavlink/package.json" ] &&
   grep -q "\"version\": \"$version\"" "$cache/node_modules/node-mavlink/package.json"; then
  exit 0
fi
if ! command -v npm >/dev/null 2>&1; then echo "npm not installed (apt-get install npm)" >&2; exit 1; fi
mkdir -p "$cache" || exit 1
# A lock so parallel ctest processes do not install into the same folder at once.
exec 9>"$cache/.install.lock"
flock 9
if [ -f "$cache/node_modules/node-mavlink/package.json" ]; then exit 0; fi
npm install --prefix "$cache" --no-audit --no-fund --no-save --loglevel=error "node-mavlink@$version" >"$cache/npm-install.log" 2>&1 ||
  { echo "npm install node-mavlink@$version failed (offline?): see $cache/npm-install.log" >&2; tail -5 "$cache/npm-install.log" >&2; exit 1; }
exit 0
