#!/usr/bin/env bash
# CrossAarch64.FromScratch (label cross): tools/cross-aarch64.sh as a new user would run it, with a
# sysroot made anew in an empty folder (downloaded, unpacked, prepared) instead of the cached one, and
# every part on: host path check, build, the aarch64 suite and replay smoke under qemu, the arm64 .deb.
# The build tree build/aarch64 and ccache are reused (a cold build only costs time; the issue 47 failure
# was the sysroot's). KESTREL_CROSS_SCRATCH_DIR: where the fresh sysroot goes (default /tmp), removed
# after a pass and kept after a failure for a look.
# Usage: cross_from_scratch.sh SOURCE_DIR
set -euo pipefail
src=${1:?source dir}
scratch=$(mktemp -d "${KESTREL_CROSS_SCRATCH_DIR:-/tmp}/kestrel-cross-XXXXXX")
echo "fresh sysroot in $scratch/sysroot"
export KESTREL_AARCH64_SYSROOT=$scratch/sysroot
unset KESTREL_CROSS_SKIP_TESTS KESTREL_CROSS_SKIP_PACKAGE KESTREL_CROSS_TARGETS
if "$src/tools/cross-aarch64.sh"; then
  rm -rf "$scratch"
  echo PASS
else
  echo "FAIL: tools/cross-aarch64.sh (sysroot kept in $scratch)"
  exit 1
fi
