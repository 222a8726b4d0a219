#!/usr/bin/env bash
# Fails when a configured cross build names a file of the build machine where it should name the
# sysroot's: a library under /usr/lib/<triplet> or /lib/<triplet>, or a header folder under /usr/include,
# on a compile or link line or as a ninja dependency. Such a path works only where the host happens to
# have the same file (arm64 packages installed beside the amd64 ones), which is how the issue 47
# `liblapack.so ... missing` stayed hidden; this check sees it on any machine, before anything is built.
# Host tools (/usr/bin/cmake, /usr/share/cmake-*) are the host's by design and are not looked at.
# Usage: tools/cross/check_host_paths.sh BUILD_DIR   (a configured `aarch64` preset tree)
set -euo pipefail
build=${1:?usage: check_host_paths.sh BUILD_DIR}
ninja_file=$build/build.ninja
[ -f "$ninja_file" ] || { echo "check_host_paths: $ninja_file missing: configure the tree first" >&2; exit 2; }
# A path counts when it starts a word: after a space, a colon (ninja's `build out: in`), `=`, `-I`,
# `-L`, `-isystem ` or `-Wl,-rpath,`. Paths inside the sysroot carry its prefix and do not match.
pattern='(^|[ :=,]|-I|-L)(/usr)?/lib/(aarch64|x86_64)-linux-gnu/|(^|[ :=,]|-I|-isystem )/usr/include(/|[ ]|$)'
# ninja's .ninja files: build.ninja and the per-target ones it includes.
mapfile -t files < <(find "$build" -maxdepth 3 -name '*.ninja' -print)
# Each offending path once, with the first file that names it.
hits=$(grep -HoE "($pattern)[^ ]*" "${files[@]}" | sed -E 's/:(-I|-L|-isystem |[ :=,])/: /' |
  sort -t: -k2 -u || true)
if [ -n "$hits" ]; then
  echo "check_host_paths: FAILED: the cross build names $(echo "$hits" | wc -l) path(s) of the build machine:" >&2
  echo "$hits" >&2
  echo "(a CMake package file in the sysroot with an absolute path: tools/cross/relocate_cmake_files.sh;" \
    "docs/embedded.md)" >&2
  exit 1
fi
echo "check_host_paths: no host library or header path in ${#files[@]} ninja file(s) of $build"
