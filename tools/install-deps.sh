#!/usr/bin/env bash
# Installs everything Kestrel builds and tests with, from Debian 12 packages.
# Idempotent: when every package is present it does nothing (no apt-get update).
set -euo pipefail

packages=(
  build-essential cmake ninja-build ccache pkg-config git
  libeigen3-dev libopencv-dev libceres-dev libcli11-dev libyaml-cpp-dev zlib1g-dev libzip-dev nlohmann-json3-dev
  libgtest-dev libgmock-dev libbenchmark-dev libboost-dev
  clang libclang-rt-14-dev   # the fuzz preset: clang 14 and libFuzzer (libclang_rt.fuzzer), tests/fuzz
  clang-format   # tests/architecture: architecture_format checks every C++ source against .clang-format
  clang-tidy     # tests/architecture: architecture_tidy runs .clang-tidy's checks as errors on rt/ and drivers/
  libusb-1.0-0-dev libopenni2-dev   # V4L2 needs only linux/videodev2.h (linux-libc-dev, via build-essential)
  librosbag-dev libsensor-msgs-dev libgeometry-msgs-dev
  libwebsocketpp-dev nlohmann-json3-dev   # tools/viewer: HTTP + WebSocket server (over Boost.Asio), its messages
  libjs-three                             # the viewer page's 3-D view, served from /usr/share/javascript/three
  libzstd-dev liblz4-dev   # drivers/log: compressed .klog images (docs/log-format.md)
  libsqlite3-dev   # drivers/rosbag2: rosbag2's sqlite3 storage (.db3; docs/ros2.md)
  liboctomap-dev   # tools/dense: the dense map's OctoMap .bt export, and tests/dense reads it back (docs/dense.md)
  file adduser systemd   # tools/package: cpack's DEB generator finds unstripped ELF files with `file`; the
                         # package's postinst (adduser); test.sh checks its unit with `systemd-analyze verify`
  valgrind   # `kestrel bench --cpu-budget` counts instructions with callgrind (tests/profile); this VM's perf has no counters
  libssl-dev   # tests/mavlink: OpenSSL's SHA-256, the reference for MAVLink signing's own (tests only)
  pybind11-dev python3-dev python3-numpy python3-pytest   # tools/python: `import kestrel` and its pytest suite
  nodejs   # tests/mavlink: node-mavlink decoder. Debian ships npm apart (apt-get install npm where `npm` is missing;
           # not listed: it conflicts with a NodeSource nodejs, which bundles npm). Without npm the test skips loudly.
)

missing=()
for p in "${packages[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done

if [ ${#missing[@]} -eq 0 ]; then
  echo "install-deps: all ${#packages[@]} packages present"
  exit 0
fi

echo "install-deps: installing ${missing[*]}"
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  if command -v sudo >/dev/null 2>&1; then SUDO=sudo; else
    echo "install-deps: need root (or sudo) to apt-get install: ${missing[*]}" >&2
    exit 1
  fi
fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
echo "install-deps: done"
