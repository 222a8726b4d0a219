#!/usr/bin/env bash
# CrossScripts.*: the two scripts that keep the build machine's files out of the cross build, on
# hand-written fixtures (seconds, no sysroot needed; label unit):
#  - relocate_cmake_files.sh re-roots the absolute library paths of an exported-targets file shaped
#    like Debian's CeresTargets.cmake, leaves the import-prefix lines and ${_IMPORT_PREFIX} paths alone,
#    is idempotent, and CMake then resolves the imported target's link libraries into CMAKE_SYSROOT;
#  - check_host_paths.sh fails on a ninja file naming /usr/lib/aarch64-linux-gnu/liblapack.so (the
#    issue 47 leak) or -I/usr/include/..., and passes the same file with the paths in the sysroot.
# Usage: test_cross_scripts.sh SOURCE_DIR WORK_DIR
set -euo pipefail
src=${1:?source dir}
work=${2:?work dir}
fail() { echo "FAIL: $*"; exit 1; }
rm -rf "$work"
sysroot=$work/sysroot
cmdir=$sysroot/usr/lib/aarch64-linux-gnu/cmake/Fake
mkdir -p "$cmdir" "$sysroot/lib/aarch64-linux-gnu" "$sysroot/usr/include"
: > "$sysroot/usr/lib/aarch64-linux-gnu/libfake.so"
: > "$sysroot/usr/lib/aarch64-linux-gnu/liblapack.so"
: > "$sysroot/lib/aarch64-linux-gnu/libblas.so.3"
cat > "$cmdir/FakeConfig.cmake" <<'CMAKE'
get_filename_component(_IMPORT_PREFIX "${CMAKE_CURRENT_LIST_FILE}" PATH)
get_filename_component(_IMPORT_PREFIX "${_IMPORT_PREFIX}" PATH)
get_filename_component(_IMPORT_PREFIX "${_IMPORT_PREFIX}" PATH)
get_filename_component(_IMPORT_PREFIX "${_IMPORT_PREFIX}" PATH)
get_filename_component(_realCurr "${_IMPORT_PREFIX}" REALPATH)
if(_realCurr STREQUAL "/usr/lib/aarch64-linux-gnu/cmake/Fake")
  set(_IMPORT_PREFIX "/usr")
endif()
add_library(Fake::fake SHARED IMPORTED)
set_target_properties(Fake::fake PROPERTIES
  IMPORTED_LOCATION "${_IMPORT_PREFIX}/lib/aarch64-linux-gnu/libfake.so"
  INTERFACE_LINK_LIBRARIES "Threads::Threads;\$<LINK_ONLY:Other::lib>;/usr/lib/aarch64-linux-gnu/liblapack.so;/lib/aarch64-linux-gnu/libblas.so.3;Eigen3::Eigen"
)
list(APPEND _check_files "/usr/lib/aarch64-linux-gnu/liblapack.so" )
CMAKE
cfg=$cmdir/FakeConfig.cmake
before=$(cat "$cfg")
out=$("$src/tools/cross/relocate_cmake_files.sh" "$sysroot")
echo "$out"
echo "$out" | grep -q 'usr/lib/aarch64-linux-gnu/cmake/Fake/FakeConfig.cmake' || fail "relocate did not name the file"
grep -qF ';${CMAKE_SYSROOT}/usr/lib/aarch64-linux-gnu/liblapack.so;${CMAKE_SYSROOT}/lib/aarch64-linux-gnu/libblas.so.3;' "$cfg" ||
  fail "link libraries not re-rooted: $(grep INTERFACE_LINK "$cfg")"
grep -qF '"${CMAKE_SYSROOT}/usr/lib/aarch64-linux-gnu/liblapack.so" )' "$cfg" || fail "quoted path not re-rooted"
grep -qF 'if(_realCurr STREQUAL "/usr/lib/aarch64-linux-gnu/cmake/Fake")' "$cfg" || fail "the import-prefix line changed"
grep -qF 'IMPORTED_LOCATION "${_IMPORT_PREFIX}/lib/aarch64-linux-gnu/libfake.so"' "$cfg" || fail "a prefix-relative path changed"
[ "$(diff <(echo "$before") "$cfg" | grep -c '^>')" -eq 2 ] || fail "other lines changed: $(diff <(echo "$before") "$cfg")"
once=$(cat "$cfg")
"$src/tools/cross/relocate_cmake_files.sh" "$sysroot" | grep -q 'no absolute library path' || fail "second run not a no-op"
[ "$once" = "$(cat "$cfg")" ] || fail "second run changed the file"

# CMake itself: with CMAKE_SYSROOT set, the imported target's libraries are the sysroot's files.
proj=$work/proj
mkdir -p "$proj"
cat > "$proj/CMakeLists.txt" <<CMAKE
cmake_minimum_required(VERSION 3.16)
project(p LANGUAGES NONE)
set(Fake_DIR "$cmdir")
find_package(Fake REQUIRED)
get_target_property(libs Fake::fake INTERFACE_LINK_LIBRARIES)
foreach(l IN LISTS libs)
  if(l MATCHES "^/")
    if(NOT EXISTS "\${l}")
      message(FATAL_ERROR "link library \${l} does not exist")
    endif()
    message(STATUS "link library: \${l}")
  endif()
endforeach()
CMAKE
log=$(cmake -S "$proj" -B "$proj/build" -DCMAKE_SYSROOT="$sysroot" 2>&1) || { echo "$log"; fail "cmake configure"; }
echo "$log" | grep 'link library'
echo "$log" | grep -qF "link library: $sysroot/usr/lib/aarch64-linux-gnu/liblapack.so" || fail "CMake did not resolve into the sysroot"

# check_host_paths.sh: the leak is found, the sysroot's paths and the host's tools are not.
tree=$work/tree
mkdir -p "$tree/CMakeFiles"
cat > "$tree/build.ninja" <<NINJA
rule RERUN_CMAKE
  command = /usr/bin/cmake --regenerate-during-build -S/src -B/build
build bin/test_features_orb: CXX_EXECUTABLE_LINKER a.o | /usr/lib/aarch64-linux-gnu/liblapack.so $sysroot/usr/lib/aarch64-linux-gnu/libblas.so
  LINK_LIBRARIES = /usr/lib/aarch64-linux-gnu/liblapack.so $sysroot/usr/lib/aarch64-linux-gnu/libblas.so
build a.o: CXX_COMPILER a.cpp
  INCLUDES = -isystem /usr/include/eigen3 -I$sysroot/usr/include/opencv4
build build.ninja: RERUN_CMAKE /usr/share/cmake-3.25/Modules/FindLAPACK.cmake
NINJA
if out=$("$src/tools/cross/check_host_paths.sh" "$tree" 2>&1); then fail "check_host_paths passed a leaking tree: $out"; fi
echo "$out"
echo "$out" | grep -q ': /usr/lib/aarch64-linux-gnu/liblapack.so$' || fail "the liblapack.so leak not named"
echo "$out" | grep -q ': /usr/include/eigen3$' || fail "the /usr/include leak not named"
echo "$out" | grep -q 'names 2 path' || fail "expected exactly 2 leaked paths"
sed -i "s| /usr/lib/aarch64-linux-gnu/| $sysroot/usr/lib/aarch64-linux-gnu/|g; s|-isystem /usr/include|-isystem $sysroot/usr/include|" \
  "$tree/build.ninja"
"$src/tools/cross/check_host_paths.sh" "$tree" || fail "check_host_paths failed a clean tree"
echo PASS
