# AArch64 (arm64) cross build: Debian's aarch64-linux-gnu GCC (crossbuild-essential-arm64)
# against a sysroot unpacked from Debian 12 arm64 packages. tools/cross-aarch64.sh builds the
# sysroot and drives this file through the `aarch64` preset (docs/embedded.md).
#
# A sysroot rather than the host's multiarch :arm64 -dev packages because those are not
# co-installable here: on Debian 12, `apt-get install libopencv-dev:arm64 libceres-dev:arm64`
# removes the amd64 OpenCV, Ceres, glog and yaml-cpp development packages (their -dev packages
# are not Multi-Arch: same), i.e. the host build. The sysroot never touches the host's dpkg.
set(CMAKE_SYSTEM_NAME Linux)
set(CMAKE_SYSTEM_PROCESSOR aarch64)
set(CMAKE_C_COMPILER aarch64-linux-gnu-gcc)
set(CMAKE_CXX_COMPILER aarch64-linux-gnu-g++)

# Outside the source tree: CMake refuses to export include paths that lie inside it.
set(KESTREL_AARCH64_SYSROOT "$ENV{HOME}/.cache/kestrel/aarch64-sysroot" CACHE PATH
  "Root of the arm64 sysroot (tools/cross-aarch64.sh)")
# The environment wins over the cache: a tree configured once keeps following the sysroot the script
# is given (a plain CACHE set would keep the first one and link against a sysroot no longer meant).
if(DEFINED ENV{KESTREL_AARCH64_SYSROOT} AND NOT "$ENV{KESTREL_AARCH64_SYSROOT}" STREQUAL "")
  set(KESTREL_AARCH64_SYSROOT "$ENV{KESTREL_AARCH64_SYSROOT}" CACHE PATH
    "Root of the arm64 sysroot (tools/cross-aarch64.sh)" FORCE)
endif()
if(NOT KESTREL_AARCH64_SYSROOT OR NOT EXISTS "${KESTREL_AARCH64_SYSROOT}/usr/include/opencv4")
  message(FATAL_ERROR "aarch64 toolchain: KESTREL_AARCH64_SYSROOT='${KESTREL_AARCH64_SYSROOT}' is not a sysroot "
    "with our dependencies (no usr/include/opencv4 in it); tools/cross-aarch64.sh builds one")
endif()
# try_compile() projects read this file again and need the sysroot too.
list(APPEND CMAKE_TRY_COMPILE_PLATFORM_VARIABLES KESTREL_AARCH64_SYSROOT)

set(CMAKE_SYSROOT "${KESTREL_AARCH64_SYSROOT}")
set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)   # build tools are the host's
set(CMAKE_FIND_ROOT_PATH_MODE_LIBRARY ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_INCLUDE ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_PACKAGE ONLY)

# pkg-config (libusb, OpenNI2, libzip) must read the sysroot's .pc files and prefix their paths.
set(ENV{PKG_CONFIG_SYSROOT_DIR} "${KESTREL_AARCH64_SYSROOT}")
set(ENV{PKG_CONFIG_LIBDIR}
  "${KESTREL_AARCH64_SYSROOT}/usr/lib/aarch64-linux-gnu/pkgconfig:${KESTREL_AARCH64_SYSROOT}/usr/share/pkgconfig")

# ctest and gtest_discover_tests() run every test binary through qemu user-mode emulation,
# with the sysroot as the dynamic loader's root (no binfmt_misc is needed).
set(CMAKE_CROSSCOMPILING_EMULATOR qemu-aarch64-static -L "${KESTREL_AARCH64_SYSROOT}")
