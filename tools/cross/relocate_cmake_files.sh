#!/usr/bin/env bash
# Re-roots the absolute library paths that CMake package files in a sysroot were written with.
# A package's exported targets name the libraries it linked by absolute path (Debian's
# CeresTargets.cmake: "...;/usr/lib/aarch64-linux-gnu/liblapack.so;.../libblas.so;..."). CMake re-roots
# find_*() results into CMAKE_SYSROOT but never an imported target's paths, so the cross build depended
# on the host's /usr/lib/aarch64-linux-gnu, which exists only where arm64 packages are installed on the
# host (issue 47: `liblapack.so ... missing` on a fresh machine). Every such path, as a quoted string or
# a list element, gets a ${CMAKE_SYSROOT} prefix (the toolchain file sets it), which keeps the sysroot
# movable. Only library files (.so, .so.N..., .a): the `_realCurr STREQUAL "/usr/lib/.../cmake/X"`
# lines that choose a package's import prefix must keep the path as packaged.
# Usage: tools/cross/relocate_cmake_files.sh SYSROOT [TRIPLET]   (default aarch64-linux-gnu)
set -euo pipefail
dir=${1:?usage: relocate_cmake_files.sh SYSROOT [TRIPLET]}
triplet=${2:-aarch64-linux-gnu}
path="/(?:usr/)?lib/${triplet}/[^\";\$]*?\.(?:so|a)(?:\.[0-9]+)*"
mapfile -d '' files < <(grep -rlZP --include='*.cmake' "(?<=[\";])${path}(?=[\";])" "$dir" || true)
if [ ${#files[@]} -eq 0 ]; then
  echo "relocate_cmake_files: no absolute library path in the CMake files of $dir"
  exit 0
fi
P="$path" perl -pi -e 's{(?<=[";])($ENV{P})(?=[";])}{\$\{CMAKE_SYSROOT\}$1}g' "${files[@]}"
printf 'relocate_cmake_files: re-rooted the library paths of %s\n' "${files[@]#"$dir"/}"
