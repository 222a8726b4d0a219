# clang-tidy's checks (.clang-tidy at the top, which says what is left out and
# why) as errors on the LAYERS' sources (issue 45's gate): `architecture_tidy`
# checks rt, drivers, core and tools (tools since session 35). Only the
# sources this build compiles are checked (compile_commands.json of BUILD),
# through run-clang-tidy on two processes.
# Run: cmake -DSRC=<source dir> -DBUILD=<build dir> -DRUN_CLANG_TIDY=<run-clang-tidy> "-DLAYERS=rt;drivers;core"
#      -DMIN_SOURCES=30 -P check_tidy.cmake
cmake_policy(SET CMP0057 NEW)  # if(... IN_LIST ...) in a -P script
if(NOT RUN_CLANG_TIDY)
  message(FATAL_ERROR "run-clang-tidy not found at configure time: tools/install-deps.sh installs clang-tidy")
endif()
if(NOT EXISTS "${BUILD}/compile_commands.json")
  message(FATAL_ERROR "${BUILD}/compile_commands.json is missing: configure with CMAKE_EXPORT_COMPILE_COMMANDS=ON")
endif()
file(READ "${BUILD}/compile_commands.json" _db)
if(NOT LAYERS)
  message(FATAL_ERROR "LAYERS is empty: name the top-level folders to check, e.g. -DLAYERS=rt;drivers;core")
endif()
if(NOT MIN_SOURCES)
  set(MIN_SOURCES 10)
endif()
set(_globs "")
foreach(l IN LISTS LAYERS)
  list(APPEND _globs "${SRC}/${l}/*.cpp")
endforeach()
list(JOIN LAYERS "|" _layers_re)
list(JOIN LAYERS "/, " _layers_text)
set(_layers_text "${_layers_text}/")
file(GLOB_RECURSE _files ${_globs})
# A unity build (the presets' default, docs/testing.md) compiles a folder's
# sources through generated Unity/unity_N_cxx.cxx files that #include them:
# clang-tidy then parses the third-party headers once per batch instead of
# once per source, and reports in our .cpp files as in included files (hence
# .cpp in the header filter below, and bugprone-suspicious-include off: the
# unity sources include .cpp files by design). Sources left out of a batch
# are checked on their own.
string(REGEX MATCHALL "\"file\": \"[^\"]*/Unity/unity_[0-9]+_cxx\\.cxx\"" _unity_entries "${_db}")
set(_units "")
set(_covered "")
foreach(e IN LISTS _unity_entries)
  string(REGEX REPLACE "^\"file\": \"([^\"]*)\"$" "\\1" _u "${e}")
  # A test program's batch that compiles one of our sources again is not the
  # source's own unit, and clang cannot read the tests' GCC precompiled header.
  if(_u MATCHES "^${BUILD}/tests/")
    continue()
  endif()
  file(STRINGS "${_u}" _incs REGEX "^#include \"")
  set(_ours FALSE)
  foreach(i IN LISTS _incs)
    string(REGEX REPLACE "^#include \"([^\"]*)\".*" "\\1" _f "${i}")
    if(_f IN_LIST _files)
      list(APPEND _covered "${_f}")
      set(_ours TRUE)
    endif()
  endforeach()
  if(_ours)
    list(APPEND _units "${_u}")
  endif()
endforeach()
set(_checked "")
foreach(f IN LISTS _files)
  if(f IN_LIST _covered)
    list(APPEND _checked "${f}")
    continue()
  endif()
  string(FIND "${_db}" "\"file\": \"${f}\"" _at)
  if(_at EQUAL -1)
    string(FIND "${_db}" "\"${f}\"" _at)
  endif()
  if(NOT _at EQUAL -1)
    list(APPEND _checked "${f}")
    list(APPEND _units "${f}")
  endif()
endforeach()
list(LENGTH _checked _n)
list(LENGTH _units _nu)
if(_n LESS MIN_SOURCES)
  message(FATAL_ERROR "only ${_n} sources of ${_layers_text} are in ${BUILD}/compile_commands.json (at least ${MIN_SOURCES} expected): wrong build directory?")
endif()
# run-clang-tidy takes regular expressions: each path, escaped, anchored.
set(_res "")
foreach(f IN LISTS _units)
  string(REGEX REPLACE "([.+])" "\\\\\\1" _re "${f}")
  list(APPEND _res "^${_re}$")
endforeach()
# Debian's run-clang-tidy (LLVM 14) has no -warnings-as-errors: any
# diagnostic it prints about our sources fails the gate.
execute_process(COMMAND "${RUN_CLANG_TIDY}" -p "${BUILD}" -j 2 -quiet "-header-filter=(${_layers_re})/.*\\.(hpp|cpp)$"
                        -extra-arg=-fno-color-diagnostics -extra-arg=-Wno-unknown-warning-option
                        -checks=-bugprone-suspicious-include ${_res}
                RESULT_VARIABLE _rc OUTPUT_VARIABLE _out ERROR_VARIABLE _err)
# Colour codes, in case a clang-tidy ignores the flag.
string(ASCII 27 _esc)
string(REGEX REPLACE "${_esc}\\[[0-9;]*m" "" _all "${_out}\n${_err}")
string(REGEX MATCHALL "[^\n]*: (warning|error): [^\n]*" _found "${_all}")
if(_found OR NOT _rc EQUAL 0)
  list(REMOVE_DUPLICATES _found)
  list(JOIN _found "\n" _list)
  if(NOT _found)
    # A failure without a diagnostic (a tool that crashed, a file it could not
    # read): the end of what it printed.
    string(LENGTH "${_all}" _len)
    math(EXPR _from "${_len} - 3000")
    if(_from LESS 0)
      set(_from 0)
    endif()
    string(SUBSTRING "${_all}" ${_from} -1 _list)
  endif()
  message(FATAL_ERROR "clang-tidy found problems in ${_layers_text} (checks: .clang-tidy; exit ${_rc}):\n${_list}")
endif()
message(STATUS "clang-tidy: ${_n} sources of ${_layers_text} pass (${_nu} translation units)")
