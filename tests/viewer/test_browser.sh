#!/bin/sh
# ctest's browser tests (label browser): MODE (viewer | report), the kestrel
# binary, a folder for the log, the screenshots and the logs.
# Installs Debian's chromium and chromium-driver when they are missing
# (apt-get, as root or through sudo); when that is impossible it says so and
# exits 77, which ctest reports as skipped, never as passed.
set -u
mode="$1"
kestrel="$2"
out="$3"
here=$(cd "$(dirname "$0")" && pwd)
mkdir -p "$out"

skip() {
  echo "SKIPPED: $mode browser test NOT run: $*"
  exit 77
}

have_browser() { command -v chromium >/dev/null 2>&1 && command -v chromedriver >/dev/null 2>&1; }

if ! have_browser; then
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then
    command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null || skip "chromium is not installed and this user cannot apt-get install it"
    SUDO="sudo -n"
  fi
  echo "installing chromium chromium-driver (Debian packages) ..."
  # One installer at a time: both browser tests may start together.
  (
    flock 9
    if ! have_browser; then
      export DEBIAN_FRONTEND=noninteractive
      $SUDO apt-get install -y -qq --no-install-recommends chromium chromium-driver >"$out/apt.log" 2>&1 ||
        { $SUDO apt-get update -qq >>"$out/apt.log" 2>&1 &&
          $SUDO apt-get install -y -qq --no-install-recommends chromium chromium-driver >>"$out/apt.log" 2>&1; }
    fi
  ) 9>/tmp/kestrel_chromium_install.lock
  have_browser || skip "apt-get install chromium chromium-driver failed (offline?): $(tail -3 "$out/apt.log" 2>/dev/null)"
fi
command -v python3 >/dev/null 2>&1 || skip "python3 is not installed"

# A short figure-8 flight with ground truth: VGA for the viewer (the size the
# cost figures are quoted at), smaller for the report (only its trajectory matters).
log="$out/flight.klog"
if [ "$mode" = viewer ]; then
  size="--width 640 --height 480 --duration 8"
else
  size="--width 320 --height 240 --duration 8"
fi
# shellcheck disable=SC2086
"$kestrel" sim --scenario figure8 $size --seed 3 --out "$log" >"$out/sim.log" 2>&1 ||
  { echo "kestrel sim failed:"; cat "$out/sim.log"; exit 1; }
exec python3 "$here/browser_check.py" "$mode" --kestrel "$kestrel" --log "$log" --out-dir "$out"
