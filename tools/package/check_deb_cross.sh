#!/usr/bin/env bash
# The arm64 package from the cross-built tree (docs/package.md "arm64"; the `arm64 package` part of
# tools/cross-aarch64.sh). check_deb.sh installs its package; an arm64 one cannot be installed on the
# x86-64 build machine (and must not be: docs/embedded.md), so this one checks the files instead and
# runs the packaged binary under qemu from the unpacked package:
#   cpack; Architecture arm64 on both files; no development files; Depends names the package of every
#   library the binary needs (cpack passes --ignore-missing-info to dpkg-shlibdeps, which would drop
#   one silently); the .ddeb holds the debug file of the binary's build id; the packaged binary is an
#   aarch64 ELF, stripped, with no .debug_info left; the unit, rules, conffile, configs and docs are in
#   it; under qemu the packaged `kestrel version` runs and the shipped config parses.
# Usage: tools/package/check_deb_cross.sh [BUILD_DIR [SYSROOT]]
#   (default build/aarch64 and KESTREL_AARCH64_SYSROOT or ~/.cache/kestrel/aarch64-sysroot)
set -euo pipefail
root=$(cd "$(dirname "$0")/../.." && pwd)
build=$(cd "${1:-$root/build/aarch64}" && pwd)
sysroot=${2:-${KESTREL_AARCH64_SYSROOT:-$HOME/.cache/kestrel/aarch64-sysroot}}
fail() { echo "check_deb_cross: FAILED: $*" >&2; exit 1; }
[ -x "$build/bin/kestrel" ] || fail "$build/bin/kestrel missing: build the cross tree first (tools/cross-aarch64.sh)"
[ -f "$sysroot/DEBIAN/shlibs" ] || fail "$sysroot/DEBIAN/shlibs missing: not a sysroot of tools/cross-aarch64.sh"
readelf=aarch64-linux-gnu-readelf
command -v "$readelf" >/dev/null || fail "$readelf missing (crossbuild-essential-arm64)"
command -v qemu-aarch64-static >/dev/null || fail "qemu-aarch64-static missing (qemu-user-static)"

mkdir -p "$build/package"
rm -f "$build"/package/kestrel*.deb "$build"/package/kestrel*.ddeb
t0=$(date +%s)
(cd "$build" && cpack -G DEB >"$build/package/cpack.log" 2>&1) || { cat "$build/package/cpack.log"; fail "cpack"; }
echo "cpack: $(( $(date +%s) - t0 )) s"
deb=$(ls "$build"/package/kestrel_*_arm64.deb) || fail "no kestrel_*_arm64.deb"
dbg=$(ls "$build"/package/kestrel-dbgsym_*_arm64.ddeb) || fail "no kestrel-dbgsym_*_arm64.ddeb"
printf '  %-52s %6d KiB\n' "$(basename "$deb")" $(( $(stat -c %s "$deb") / 1024 ))
printf '  %-52s %6d KiB\n' "$(basename "$dbg")" $(( $(stat -c %s "$dbg") / 1024 ))
printf '  %-52s %6d KiB\n' "bin/kestrel in the build tree (unstripped)" $(( $(stat -c %s "$build/bin/kestrel") / 1024 ))
dpkg-deb -f "$deb" Package Version Architecture Depends
[ "$(dpkg-deb -f "$deb" Architecture)" = arm64 ] || fail "$(basename "$deb"): Architecture is not arm64"
[ "$(dpkg-deb -f "$dbg" Architecture)" = arm64 ] || fail "$(basename "$dbg"): Architecture is not arm64"
if dpkg-deb -c "$deb" | grep -E '\.a$|/include/|/cmake/|\.pc$'; then fail "development files in the runtime package"; fi

# Every NEEDED library maps to a package through the sysroot's merged shlibs/symbols (what
# dpkg-shlibdeps read); that package must be in Depends.
depends=$(dpkg-deb -f "$deb" Depends)
needed=$("$readelf" -d "$build/bin/kestrel" | sed -n 's/.*(NEEDED).*\[\(.*\)\]/\1/p')
[ -n "$needed" ] || fail "no NEEDED entries read from bin/kestrel"
python3 - "$sysroot/DEBIAN" "$depends" $needed <<'EOF' || fail "Depends misses libraries of bin/kestrel"
import re, sys
debian, depends, needed = sys.argv[1], sys.argv[2], sys.argv[3:]
owner = {}
for line in open(debian + "/symbols", errors="replace"):
    m = re.match(r"^(\S+\.so[^\s]*) (\S+)", line)   # "libfoo.so.1 libfoo1 #MINVER#"
    if m:
        owner.setdefault(m.group(1), m.group(2))
for line in open(debian + "/shlibs", errors="replace"):
    f = line.split()   # "[type:] libfoo 1 libfoo1 (>= 1.2)"
    if f and f[0].endswith(":"):
        f = f[1:]
    if len(f) >= 3:
        owner.setdefault(f"{f[0]}.so.{f[1]}", f[2])
dep_names = {re.split(r"[\s(:]", d.strip())[0] for d in re.split(r"[,|]", depends)}
missing = []
for so in needed:
    pkg = owner.get(so)
    if pkg is None:
        missing.append(f"{so}: no package in the sysroot's shlibs/symbols names it")
    elif pkg not in dep_names:
        missing.append(f"{so}: its package {pkg} is not in Depends")
for m in missing:
    print("  " + m)
print(f"  Depends covers {len(needed) - len(missing)} of {len(needed)} NEEDED libraries of bin/kestrel")
sys.exit(1 if missing else 0)
EOF

build_id=$("$readelf" -n "$build/bin/kestrel" | sed -n 's/.*Build ID: *//p')
[ -n "$build_id" ] || fail "bin/kestrel has no build id"
dpkg-deb -c "$dbg" | grep -q "usr/lib/debug/.build-id/${build_id:0:2}/${build_id:2}.debug" ||
  fail "kestrel-dbgsym lacks the debug file of build id $build_id"

unpacked=$build/package/unpacked
rm -rf "$unpacked"
dpkg-deb -x "$deb" "$unpacked"
bin=$unpacked/usr/bin/kestrel
file -L "$bin" | grep -q 'ARM aarch64' || fail "packaged kestrel is not an aarch64 binary: $(file -L "$bin")"
file -L "$bin" | grep -q ', stripped' || fail "packaged kestrel is not stripped"
if "$readelf" -S "$bin" | grep -q '\.debug_info'; then fail "packaged kestrel still has .debug_info"; fi
printf '  %-52s %6d KiB\n' "/usr/bin/kestrel in the package (stripped)" $(( $(stat -c %s "$bin") / 1024 ))
for f in lib/systemd/system/kestrel.service lib/udev/rules.d/60-kestrel.rules etc/kestrel/kestrel.yaml \
  usr/share/kestrel/configs/realsense_d435i.yaml usr/share/kestrel/viewer/index.html usr/share/doc/kestrel/package.md; do
  [ -f "$unpacked/$f" ] || fail "/$f not in the package"
done
dpkg-deb -I "$deb" conffiles | grep -qx /etc/kestrel/kestrel.yaml || fail "kestrel.yaml is not a conffile"
qemu=(qemu-aarch64-static -L "$sysroot")
"${qemu[@]}" "$bin" version || fail "packaged kestrel version (qemu)"
"${qemu[@]}" "$bin" run --config "$unpacked/etc/kestrel/kestrel.yaml" --print-config >/dev/null ||
  fail "packaged kestrel run --config kestrel.yaml --print-config (qemu)"
rm -rf "$unpacked" "$build/package/_CPack_Packages"
echo "check_deb_cross: built and checked $(basename "$deb") and $(basename "$dbg"); the packaged binary runs under qemu"
