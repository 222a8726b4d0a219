# clang-tidy's checks (.clang-tidy at the top, which says what is left out and
# why) as errors on rt/, drivers/ and core/ (issue 45's gate; core/ since
# session 31, about 3.5 min of the gate's ~4.5 on two cores). tools/ is not
# gated yet. Only the sources this build compiles are checked (compile_commands.json
# of BUILD), through run-clang-tidy on two processes.
# Run: cmake -DSRC=<source dir> -DBUILD=<build dir> -DRUN_CLANG_TIDY=<run-clang-tidy> -P check_tidy.cmake
if(NOT RUN_CLANG_TIDY)
  message(FATAL_ERROR "run-clang-tidy not found at configure time: tools/install-deps.sh installs clang-tidy")
endif()
if(NOT EXISTS "${BUILD}/compile_commands.json")
  message(FATAL_ERROR "${BUILD}/compile_commands.json is missing: configure with CMAKE_EXPORT_COMPILE_COMMANDS=ON")
endif()
file(READ "${BUILD}/compile_commands.json" _db)
file(GLOB_RECURSE _files "${SRC}/rt/*.cpp" "${SRC}/drivers/*.cpp" "${SRC}/core/*.cpp")
set(_checked "")
foreach(f IN LISTS _files)
  string(FIND "${_db}" "\"file\": \"${f}\"" _at)
  if(_at EQUAL -1)
    string(FIND "${_db}" "\"${f}\"" _at)
  endif()
  if(NOT _at EQUAL -1)
    list(APPEND _checked "${f}")
  endif()
endforeach()
list(LENGTH _checked _n)
if(_n LESS 30)
  message(FATAL_ERROR "only ${_n} sources of rt/, drivers/ and core/ are in ${BUILD}/compile_commands.json: wrong build directory?")
endif()
# run-clang-tidy takes regular expressions: each path, escaped, anchored.
set(_res "")
foreach(f IN LISTS _checked)
  string(REGEX REPLACE "([.+])" "\\\\\\1" _re "${f}")
  list(APPEND _res "^${_re}$")
endforeach()
# Debian's run-clang-tidy (LLVM 14) has no -warnings-as-errors: any
# diagnostic it prints about our sources fails the gate.
execute_process(COMMAND "${RUN_CLANG_TIDY}" -p "${BUILD}" -j 2 -quiet "-header-filter=(rt|drivers|core)/.*\\.hpp$"
                        -extra-arg=-fno-color-diagnostics ${_res}
                RESULT_VARIABLE _rc OUTPUT_VARIABLE _out ERROR_VARIABLE _err)
# Colour codes, in case a clang-tidy ignores the flag.
string(ASCII 27 _esc)
string(REGEX REPLACE "${_esc}\\[[0-9;]*m" "" _all "${_out}\n${_err}")
string(REGEX MATCHALL "[^\n]*: (warning|error): [^\n]*" _found "${_all}")
if(_found OR NOT _rc EQUAL 0)
  list(REMOVE_DUPLICATES _found)
  list(JOIN _found "\n" _list)
  message(FATAL_ERROR "clang-tidy found problems in rt/, drivers/ or core/ (checks: .clang-tidy; exit ${_rc}):\n${_list}")
endif()
message(STATUS "clang-tidy: ${_n} sources of rt/, drivers/ and core/ pass")
