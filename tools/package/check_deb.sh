#!/usr/bin/env bash
# The `deb package` part of tools/test.sh (docs/package.md): packages an already-built tree (no
# rebuild: cpack installs the `runtime` component of what is there), installs the .deb with apt-get
# (dependencies resolved), checks what it put in place, runs `kestrel version`, removes and purges it.
# Usage: tools/package/check_deb.sh [BUILD_DIR]   (default build/release; needs root or sudo)
set -euo pipefail
root=$(cd "$(dirname "$0")/../.." && pwd)
build=$(cd "${1:-$root/build/release}" && pwd)
fail() { echo "check_deb: FAILED: $*" >&2; exit 1; }
sudo=""
if [ "$(id -u)" != 0 ]; then
  command -v sudo >/dev/null || fail "installing a package needs root or sudo"
  sudo="sudo"
fi
[ -x "$build/bin/kestrel" ] || fail "$build/bin/kestrel missing: build the release tree first"
if dpkg-query -W -f='${Status}' kestrel 2>/dev/null | grep -q 'install ok'; then
  fail "a kestrel package is already installed here; this check would replace and remove it (dpkg -r kestrel first)"
fi

mkdir -p "$build/package"
rm -f "$build"/package/kestrel*.deb "$build"/package/kestrel*.ddeb
t0=$(date +%s)
(cd "$build" && cpack -G DEB >"$build/package/cpack.log" 2>&1) || { cat "$build/package/cpack.log"; fail "cpack"; }
echo "cpack: $(( $(date +%s) - t0 )) s"
deb=$(ls "$build"/package/kestrel_*.deb)
dbg=$(ls "$build"/package/kestrel-dbgsym_*.ddeb)
printf '  %-52s %6d KiB\n' "$(basename "$deb")" $(( $(stat -c %s "$deb") / 1024 ))
printf '  %-52s %6d KiB\n' "$(basename "$dbg")" $(( $(stat -c %s "$dbg") / 1024 ))
printf '  %-52s %6d KiB\n' "bin/kestrel in the build tree (unstripped)" $(( $(stat -c %s "$build/bin/kestrel") / 1024 ))
dpkg-deb -f "$deb" Package Version Architecture Depends
# The runtime package carries no libraries or headers, and the debug package the binary's symbols.
if dpkg-deb -c "$deb" | grep -E '\.a$|/include/|/cmake/|\.pc$'; then fail "development files in the runtime package"; fi
build_id=$(readelf -n "$build/bin/kestrel" | sed -n 's/.*Build ID: *//p')
[ -n "$build_id" ] || fail "bin/kestrel has no build id"
dpkg-deb -c "$dbg" | grep -q "usr/lib/debug/.build-id/${build_id:0:2}/${build_id:2}.debug" ||
  fail "kestrel-dbgsym lacks the debug file of build id $build_id"

$sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "$deb" >"$build/package/apt.log" 2>&1 ||
  { cat "$build/package/apt.log"; fail "apt-get install $deb"; }
# From here on the package is removed whatever happens.
trap '$sudo dpkg --purge kestrel >/dev/null 2>&1 || true' EXIT
/usr/bin/kestrel version || fail "kestrel version"
file -L /usr/bin/kestrel | grep -q ', stripped' || fail "/usr/bin/kestrel is not stripped"
printf '  %-52s %6d KiB\n' "/usr/bin/kestrel installed (stripped)" $(( $(stat -c %s /usr/bin/kestrel) / 1024 ))
for f in /lib/systemd/system/kestrel.service /lib/udev/rules.d/60-kestrel.rules /etc/kestrel/kestrel.yaml \
  /usr/share/kestrel/configs/realsense_d435i.yaml /usr/share/kestrel/viewer/index.html \
  /usr/share/doc/kestrel/package.md; do
  [ -f "$f" ] || fail "$f not installed"
done
dpkg-query -W -f='${Conffiles}\n' kestrel | grep -q /etc/kestrel/kestrel.yaml || fail "kestrel.yaml is not a conffile"
getent passwd kestrel >/dev/null || fail "postinst made no kestrel user"
grep -q '^ExecStart=/usr/bin/kestrel run --config /etc/kestrel/kestrel.yaml$' /lib/systemd/system/kestrel.service ||
  fail "unit: ExecStart"
grep -q '^AmbientCapabilities=CAP_SYS_NICE CAP_IPC_LOCK$' /lib/systemd/system/kestrel.service || fail "unit: capabilities"
systemd-analyze verify /lib/systemd/system/kestrel.service || fail "systemd-analyze verify kestrel.service"
# The shipped config parses: the binary reads it as the service would (--print-config exits before the sensors).
/usr/bin/kestrel run --config /etc/kestrel/kestrel.yaml --print-config >/dev/null ||
  fail "kestrel run --config /etc/kestrel/kestrel.yaml --print-config"
grep -q 'SUBSYSTEM=="video4linux", ATTRS{idVendor}=="8086", GROUP="kestrel"' /lib/udev/rules.d/60-kestrel.rules ||
  fail "udev: RealSense rule"
grep -q 'ATTR{idVendor}=="1209", ATTR{idProduct}=="0001"' /lib/udev/rules.d/60-kestrel.rules || fail "udev: USB IMU bridge rule"

$sudo dpkg -r kestrel >/dev/null || fail "dpkg -r kestrel"
[ ! -e /usr/bin/kestrel ] || fail "/usr/bin/kestrel left after dpkg -r"
[ ! -e /lib/systemd/system/kestrel.service ] || fail "kestrel.service left after dpkg -r"
$sudo dpkg --purge kestrel >/dev/null || fail "dpkg --purge kestrel"
[ ! -e /etc/kestrel/kestrel.yaml ] || fail "/etc/kestrel/kestrel.yaml left after purge"
trap - EXIT
# The staging tree is the size of the unstripped binary and more; the .deb and .ddeb stay.
rm -rf "$build/package/_CPack_Packages"
echo "check_deb: built, installed, checked, removed and purged $(basename "$deb")"
