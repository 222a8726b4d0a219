# The companion computer's .deb (docs/package.md): `cpack` in a configured and built tree, or
# `cmake --build --preset release --target package`. Included last by the top-level CMakeLists.txt.
#
# One package, `kestrel`, from the `runtime` install component only: the binary, the config templates,
# the `--view` page (tools/viewer), the systemd unit, the udev rules and the docs. The static libraries, headers and CMake/pkg-config
# files (the unnamed install component, docs/api.md) are left out: they build programs, a companion
# computer runs one. The debug symbols go to kestrel-dbgsym (a .ddeb, Debian's naming).

# Files only the package installs: absolute paths outside the prefix, so EXCLUDE_FROM_ALL keeps them out
# of a plain `cmake --install --prefix P` (which must not write /etc); cpack installs by component.
set(_pkg ${CMAKE_CURRENT_LIST_DIR})
# The shipped config: the D435i template, marked as one, so that `systemctl start kestrel` on an
# unedited install reads a valid file and says which sensors it looks for.
file(READ ${CMAKE_SOURCE_DIR}/configs/realsense_d435i.yaml _template)
file(WRITE ${CMAKE_BINARY_DIR}/package/kestrel.yaml
  "# TEMPLATE installed by the kestrel package: a copy of configs/realsense_d435i.yaml (the other rigs are in\n"
  "# /usr/share/kestrel/configs/). The kestrel service reads this file. Replace the calibration with your own\n"
  "# (docs/realsense.md, docs/own-sensors.md) before flying; an upgrade keeps your edits (dpkg conffile).\n"
  "#\n${_template}")
set_property(DIRECTORY APPEND PROPERTY CMAKE_CONFIGURE_DEPENDS ${CMAKE_SOURCE_DIR}/configs/realsense_d435i.yaml)
install(FILES ${CMAKE_BINARY_DIR}/package/kestrel.yaml DESTINATION /etc/kestrel
  COMPONENT runtime EXCLUDE_FROM_ALL)
install(FILES ${_pkg}/kestrel.service DESTINATION /lib/systemd/system COMPONENT runtime EXCLUDE_FROM_ALL)
install(FILES ${_pkg}/60-kestrel.rules DESTINATION /lib/udev/rules.d COMPONENT runtime EXCLUDE_FROM_ALL)
install(FILES ${CMAKE_SOURCE_DIR}/README.md DESTINATION ${CMAKE_INSTALL_DOCDIR} COMPONENT runtime EXCLUDE_FROM_ALL)
install(DIRECTORY ${CMAKE_SOURCE_DIR}/docs/ DESTINATION ${CMAKE_INSTALL_DOCDIR} COMPONENT runtime EXCLUDE_FROM_ALL
  FILES_MATCHING PATTERN "*.md")

set(CPACK_GENERATOR DEB)
set(CPACK_PACKAGE_NAME kestrel)
set(CPACK_PACKAGE_VERSION ${PROJECT_VERSION})
set(CPACK_PACKAGE_VENDOR "Kestrel")
set(CPACK_PACKAGE_CONTACT "Kestrel maintainers <kestrel@localhost>")
set(CPACK_PACKAGE_DESCRIPTION_SUMMARY "onboard visual-inertial estimator for quadrotors (RGB-D + IMU)")
set(CPACK_PACKAGING_INSTALL_PREFIX /usr)
set(CPACK_PACKAGE_DIRECTORY ${CMAKE_BINARY_DIR}/package)
set(CPACK_DEB_COMPONENT_INSTALL ON)
set(CPACK_COMPONENTS_ALL runtime)
set(CPACK_COMPONENTS_GROUPING ALL_COMPONENTS_IN_ONE)
set(CPACK_DEBIAN_PACKAGE_NAME kestrel)
set(CPACK_DEBIAN_FILE_NAME DEB-DEFAULT)   # kestrel_<version>_<arch>.deb
# Architecture: CPack asks `dpkg --print-architecture`, the build machine's; a cross build names the target.
if(CMAKE_CROSSCOMPILING AND CMAKE_SYSTEM_PROCESSOR MATCHES "^(aarch64|arm64)$")
  set(CPACK_DEBIAN_PACKAGE_ARCHITECTURE arm64)
endif()
# A cross build (tools/cross-aarch64.sh): the host's binutils cannot read an arm64 binary, so the
# strip/split uses the toolchain's; dpkg-shlibdeps looks for the libraries in the sysroot (-l) and
# reads their shlibs/symbols from the sysroot's DEBIAN/, which the sysroot preparation merges from the
# packages it unpacked (no dpkg database knows them); DEB_HOST_ARCH makes it run the target's objdump
# and search the target's multiarch folders. The variable lives in the file cpack reads when it runs.
if(CMAKE_CROSSCOMPILING)
  if(NOT CPACK_DEBIAN_PACKAGE_ARCHITECTURE OR NOT CMAKE_LIBRARY_ARCHITECTURE)
    message(FATAL_ERROR "package.cmake: no Debian architecture for the cross target '${CMAKE_SYSTEM_PROCESSOR}'")
  endif()
  set(CPACK_OBJCOPY_EXECUTABLE ${CMAKE_OBJCOPY})
  set(CPACK_READELF_EXECUTABLE ${CMAKE_READELF})
  if(NOT EXISTS "${CMAKE_SYSROOT}/DEBIAN/shlibs")
    message(WARNING "package.cmake: ${CMAKE_SYSROOT}/DEBIAN/shlibs missing (a sysroot from an older "
      "tools/cross-aarch64.sh): the package's Depends will lack the libraries; run the script again")
  endif()
  set(CPACK_DEBIAN_PACKAGE_SHLIBDEPS_PRIVATE_DIRS
    "${CMAKE_SYSROOT}/usr/lib/${CMAKE_LIBRARY_ARCHITECTURE}" "${CMAKE_SYSROOT}/lib/${CMAKE_LIBRARY_ARCHITECTURE}")
  file(WRITE ${CMAKE_BINARY_DIR}/package/cross.cmake
    "set(ENV{DEB_HOST_ARCH} ${CPACK_DEBIAN_PACKAGE_ARCHITECTURE})\n")
  set(CPACK_PROJECT_CONFIG_FILE ${CMAKE_BINARY_DIR}/package/cross.cmake)
endif()
set(CPACK_DEBIAN_PACKAGE_SECTION science)
set(CPACK_DEBIAN_PACKAGE_PRIORITY optional)
# The run-time libraries from the binary's NEEDED entries (dpkg-shlibdeps), and adduser for postinst.
set(CPACK_DEBIAN_PACKAGE_SHLIBDEPS ON)
set(CPACK_DEBIAN_PACKAGE_DEPENDS "adduser")
# The `--view` page loads three.js from Debian's package (tools/viewer); the estimator runs without it.
set(CPACK_DEBIAN_PACKAGE_RECOMMENDS "libjs-three")
# Strip and split: CPack copies the DWARF of every unstripped ELF file to kestrel-dbgsym
# (/usr/lib/debug/.build-id/, where gdb finds it by the binary's build id) and strips the file.
set(CPACK_DEBIAN_DEBUGINFO_PACKAGE ON)
# zstd: gzip of the ~340 MB of debug info costs most of the packaging time (docs/package.md).
set(CPACK_DEBIAN_COMPRESSION_TYPE zstd)
configure_file(${_pkg}/conffiles.in ${CMAKE_BINARY_DIR}/package/control/conffiles @ONLY)
foreach(s postinst prerm postrm)
  configure_file(${_pkg}/${s} ${CMAKE_BINARY_DIR}/package/control/${s} COPYONLY)
endforeach()
set(CPACK_DEBIAN_PACKAGE_CONTROL_EXTRA
  ${CMAKE_BINARY_DIR}/package/control/conffiles ${CMAKE_BINARY_DIR}/package/control/postinst
  ${CMAKE_BINARY_DIR}/package/control/prerm ${CMAKE_BINARY_DIR}/package/control/postrm)
set(CPACK_DEBIAN_PACKAGE_CONTROL_STRICT_PERMISSION ON)
include(CPack)
