#!/usr/bin/env bash
# AArch64 build and tests, on this x86-64 machine (docs/embedded.md):
#   1. host tools: crossbuild-essential-arm64 (aarch64-linux-gnu-g++) and qemu-user-static
#   2. a sysroot: our dependencies' Debian 12 arm64 packages and everything they need,
#      downloaded with a private apt state and unpacked (never installed: see below)
#   3. the `aarch64` preset configured against it (tools/cross/aarch64-linux-gnu.cmake), checked
#      for paths of the build machine (tools/cross/check_host_paths.sh), then built
#   4. `ctest --preset aarch64` under qemu: every unit-labelled test at sanitizer-sized
#      flights (KESTREL_TEST_SCALE=small)
#   5. a replay smoke test: the cross-built `kestrel` simulates a short flight, replays it
#      through `window` and evaluates it, all under qemu; the ATE must stay under 5 cm
#      (1.3 cm natively) with at least 95 % of the frames posed (the rest is start-up)
#   6. the arm64 .deb (cpack in the cross tree), checked, and its `kestrel` run under qemu
#      (tools/package/check_deb_cross.sh)
# and prints what each part cost.
#
# Why a sysroot and not `apt-get install libopencv-dev:arm64 …` (multiarch): on Debian 12
# that install removes the amd64 OpenCV, Ceres, glog and yaml-cpp development packages
# (measured here; their -dev packages are not co-installable across architectures), i.e.
# it breaks the host build. The sysroot leaves the host's dpkg untouched.
#
# Environment: KESTREL_AARCH64_SYSROOT (default ~/.cache/kestrel/aarch64-sysroot; kept
# between runs and rebuilt when the package list below changes), KESTREL_CROSS_SKIP_TESTS=1
# (build only), KESTREL_CROSS_TARGETS (what to build; default the suite and `kestrel`: a
# single small target such as test_features_orb proves the sysroot in minutes),
# KESTREL_CROSS_SKIP_PACKAGE=1 (no arm64 .deb; needed when the targets leave `kestrel` out).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
jobs=$(nproc 2>/dev/null || echo 2)
export KESTREL_AARCH64_SYSROOT=${KESTREL_AARCH64_SYSROOT:-$HOME/.cache/kestrel/aarch64-sysroot}
sysroot=$KESTREL_AARCH64_SYSROOT

# Our dependencies as arm64 development packages: install-deps.sh's libraries, minus the
# host-only tools (compilers, valgrind, node) and with the C/C++ runtime made explicit.
packages=(
  libc6-dev libstdc++-12-dev linux-libc-dev
  libeigen3-dev libopencv-dev libceres-dev libcli11-dev libyaml-cpp-dev zlib1g-dev libzip-dev nlohmann-json3-dev
  libgtest-dev libgmock-dev libboost-dev libwebsocketpp-dev
  libusb-1.0-0-dev libopenni2-dev
  libzstd-dev liblz4-dev   # compressed .klog images (drivers/log)
  librosbag-dev libsensor-msgs-dev libgeometry-msgs-dev
  libsqlite3-dev   # drivers/rosbag2 (.db3)
  liboctomap-dev   # tools/dense, tests/dense
  libssl-dev       # tests/mavlink's reference SHA-256
)

script_name=cross-aarch64.sh
# shellcheck source=tools/timed_parts.sh
source "$root/tools/timed_parts.sh"

SUDO=""
if [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1; then SUDO=sudo; fi

host_tools() {
  local missing=()
  for p in crossbuild-essential-arm64 qemu-user-static; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
  done
  if [ ${#missing[@]} -eq 0 ]; then echo "host tools present"; return; fi
  echo "installing ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
}

# apt with its own state: arm64 is its only architecture and nothing counts as installed,
# so --download-only fetches the whole dependency closure. The host's sources and keys are
# used; the host's package state and caches are not touched.
private_apt() {
  local state=$1 sandbox=()
  shift
  # As root apt drops to the _apt user to download, which cannot write into root's home.
  [ "$(id -u)" -eq 0 ] && sandbox=(-o APT::Sandbox::User=root)
  apt-get -q "${sandbox[@]}" -o Dir::State="$state/state" -o Dir::State::status="$state/state/status" \
    -o Dir::Cache="$state/cache" -o APT::Architecture=arm64 -o APT::Architectures::=arm64 \
    -o APT::Install-Recommends=false "$@"
}

build_sysroot() {
  local want
  # The preparation's version joins the package list in the stamp: a sysroot made by an older
  # script (without relocate_cmake_files.sh) is rebuilt, not reused.
  want=$( (echo "prepare 3"; printf '%s\n' "${packages[@]}") | sha256sum | cut -c1-16)
  if [ -f "$sysroot/.kestrel-sysroot" ] && [ "$(cat "$sysroot/.kestrel-sysroot")" = "$want" ]; then
    echo "sysroot up to date: $sysroot"
    return
  fi
  local state="$sysroot.apt" new="$sysroot.new"
  mkdir -p "$state/state/lists/partial" "$state/cache/archives/partial"
  : > "$state/state/status"
  private_apt "$state" update
  private_apt "$state" -y --download-only install "${packages[@]}" > "$state/download.txt"
  tail -n 2 "$state/download.txt"
  rm -rf "$new"
  mkdir -p "$new"
  local n=0 d ctl="$state/control"
  # The packages' shlibs and symbols files, merged into the sysroot's DEBIAN/: dpkg-shlibdeps, run
  # by cpack on the arm64 binary, finds its libraries in the sysroot, where no dpkg database knows
  # them, and then reads these files from the "package build tree" holding the library, i.e. the
  # sysroot (tools/package/package.cmake; docs/package.md).
  mkdir -p "$new/DEBIAN"
  : > "$new/DEBIAN/shlibs"
  : > "$new/DEBIAN/symbols"
  for d in "$state"/cache/archives/*.deb; do
    dpkg-deb -x "$d" "$new"
    rm -rf "$ctl"
    dpkg-deb -e "$d" "$ctl"
    [ -f "$ctl/shlibs" ] && cat "$ctl/shlibs" >> "$new/DEBIAN/shlibs"
    [ -f "$ctl/symbols" ] && cat "$ctl/symbols" >> "$new/DEBIAN/symbols"
    n=$((n + 1))
  done
  rm -rf "$ctl"
  echo "unpacked $n packages into $new; shlibs of $(grep -c '^[a-z]' "$new/DEBIAN/shlibs") and symbols of" \
    "$(grep -c '^[a-z]' "$new/DEBIAN/symbols") libraries in DEBIAN/"
  # Absolute symlinks (libz.so -> /lib/...) would point into the host: make them relative.
  local link target
  while IFS= read -r -d '' link; do
    target=$(readlink "$link")
    ln -sfn "$(realpath -m --relative-to="$(dirname "$link")" "$new$target")" "$link"
  done < <(find "$new" -type l -lname '/*' -print0)
  # libblas/liblapack are chosen by update-alternatives in a package script, which
  # unpacking does not run: pick an implementation as its priorities would (ATLAS first).
  local lib=$new/usr/lib/aarch64-linux-gnu name dir
  for name in libblas.so.3 libblas.so liblapack.so.3 liblapack.so; do
    [ -e "$lib/$name" ] && continue
    for dir in atlas openblas-pthread blas lapack; do
      if [ -e "$lib/$dir/$name" ]; then ln -sfn "$dir/$name" "$lib/$name"; break; fi
    done
    [ -e "$lib/$name" ] || { echo "sysroot: no implementation of $name in $lib" >&2; exit 1; }
  done
  # Absolute library paths in the packages' CMake files (Ceres: LAPACK/BLAS) would name the host's.
  tools/cross/relocate_cmake_files.sh "$new"
  echo "$want" > "$new/.kestrel-sysroot"
  rm -rf "$sysroot"
  mv "$new" "$sysroot"
  du -sh "$sysroot"
}

# The cross-built `kestrel` end to end under qemu: simulate, replay through the default
# backend, evaluate. A short, small flight: qemu runs it some 10x slower than native.
smoke() {
  local dir=build/aarch64/smoke qemu=(qemu-aarch64-static -L "$sysroot") bin=build/aarch64/bin/kestrel
  rm -rf "$dir"
  mkdir -p "$dir"
  file -L "$bin"
  "${qemu[@]}" "$bin" version
  "${qemu[@]}" "$bin" sim --scenario figure8 --duration 8 --width 320 --height 240 --seed 3 --out "$dir/f8.klog"
  "${qemu[@]}" "$bin" replay "$dir/f8.klog" --estimator window --traj-out "$dir/window.tum" \
    --metrics-out "$dir/metrics.json" -q
  "${qemu[@]}" "$bin" eval --gt "$dir/f8.klog" --est "$dir/window.tum" --align se3 --json > "$dir/eval.json"
  python3 - "$dir" <<'EOF'
import json, sys
d = sys.argv[1]
e = json.load(open(d + "/eval.json"))
m = json.load(open(d + "/metrics.json"))
ate = e["ate_rmse_m"]
frames_in = m["estimator_counters"]["frames_in"]
share = e["matched"] / max(frames_in, 1)
print(f"aarch64 smoke: window, figure8 8 s 320x240 seed 3: ATE {ate*100:.2f} cm, "
      f"{e['matched']} of {frames_in} frames posed ({share:.1%}), problems: {m['problems'] or 'none'}")
if not ate < 0.05:
    sys.exit(f"aarch64 smoke: ATE {ate} m is not under 0.05 m")
if share < 0.95:   # the first frames go to initialisation
    sys.exit(f"aarch64 smoke: only {share:.1%} of frames posed")
EOF
}

part "host tools" host_tools
part "sysroot" build_sysroot
# The tests the preset runs (kestrel_asan_suite) and the program the smoke test drives.
# Configured on every run (the sysroot may be new) and checked before any compiler runs: a path of
# the build machine on a link line passes here only by luck (tools/cross/check_host_paths.sh).
part "aarch64 configure" cmake --preset aarch64 --log-level=WARNING
part "host path check" tools/cross/check_host_paths.sh build/aarch64
read -r -a targets <<< "${KESTREL_CROSS_TARGETS:-kestrel_asan_suite kestrel}"
part "aarch64 build" bash tools/build.sh aarch64 --target "${targets[@]}"
if [ "${KESTREL_CROSS_SKIP_TESTS:-0}" != "1" ]; then
  part "aarch64 unit tests (qemu)" ctest --preset aarch64 -j "$jobs"
  part "aarch64 replay smoke (qemu)" smoke
else
  echo "== aarch64 tests and smoke SKIPPED (KESTREL_CROSS_SKIP_TESTS=1) =="
fi
# The arm64 .deb from this tree, checked and its binary run under qemu (docs/package.md "arm64").
if [ "${KESTREL_CROSS_SKIP_PACKAGE:-0}" != "1" ]; then
  part "arm64 package" tools/package/check_deb_cross.sh build/aarch64 "$sysroot"
else
  echo "== arm64 package SKIPPED (KESTREL_CROSS_SKIP_PACKAGE=1) =="
fi
