# The layer rules of docs/architecture.md, checked on the sources themselves
# (the configure step checks the link graph; this catches an include that
# reaches around it, e.g. through a relative path). Run by ctest as
#   cmake -DSRC=<source dir> -P check_layers.cmake
# Fails listing every offending file:line.
if(NOT SRC)
  message(FATAL_ERROR "pass -DSRC=<source dir>")
endif()
set(_bad "")
# layer folder, regex of includes it must never contain
set(_rules
  "rt|#include \"(kestrel/(core|drivers|tools|mavlink)/|\\.\\./)"
  "core|#include \"(kestrel/(drivers|tools|mavlink)/|\\.\\./)"
  "drivers|#include \"(kestrel/(core|tools|mavlink)/|\\.\\./)")
foreach(rule ${_rules})
  string(REPLACE "|" ";" _parts "${rule}")
  list(GET _parts 0 _layer)
  string(REGEX REPLACE "^[a-z]+\\|" "" _re "${rule}")
  file(GLOB_RECURSE _files "${SRC}/${_layer}/*.cpp" "${SRC}/${_layer}/*.hpp" "${SRC}/${_layer}/*.h")
  foreach(f ${_files})
    file(STRINGS "${f}" _lines REGEX "^[ \t]*#[ \t]*include")
    foreach(l ${_lines})
      if(l MATCHES "${_re}")
        file(RELATIVE_PATH _rel "${SRC}" "${f}")
        list(APPEND _bad "${_rel}: ${l}")
      endif()
    endforeach()
  endforeach()
endforeach()
# Every concern folder says what it owns.
foreach(_layer core drivers tools)
  file(GLOB _dirs LIST_DIRECTORIES true "${SRC}/${_layer}/*")
  foreach(d ${_dirs})
    if(IS_DIRECTORY "${d}" AND EXISTS "${d}/CMakeLists.txt" AND NOT EXISTS "${d}/README.md")
      file(RELATIVE_PATH _rel "${SRC}" "${d}")
      list(APPEND _bad "${_rel}: no README.md saying what the folder owns")
    endif()
  endforeach()
endforeach()
if(_bad)
  list(JOIN _bad "\n  " _msg)
  message(FATAL_ERROR "layer rules broken:\n  ${_msg}")
endif()
message(STATUS "layer rules hold for rt/, core/, drivers/")
