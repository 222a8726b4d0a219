# One naming and one layout for the tests (issue 45's gate), checked on the sources:
#  - a source under tests/ that defines gtest cases (TEST, TEST_F, TEST_P) is
#    named test_*.cpp, or bench_*.cpp for a benchmark that reports through gtest;
#  - no file is named *_test.* or *_bench.* (the two conventions this replaced);
#  - every kestrel_add_test() target is named test_* or bench_*.
# Support files (a shared evaluator, a profiling probe, fuzz targets) keep
# their own names. Run: cmake -DSRC=<source dir> -P check_tests.cmake
cmake_policy(SET CMP0057 NEW)  # if(... IN_LIST ...) in a -P script
file(GLOB_RECURSE _sources RELATIVE "${SRC}" "${SRC}/tests/*.cpp" "${SRC}/tests/*.sh")
set(_bad "")
foreach(f IN LISTS _sources)
  get_filename_component(_name "${f}" NAME)
  if(_name MATCHES "_(test|bench)\\.(cpp|sh)$")
    list(APPEND _bad "${f}: named *_test / *_bench, where the convention is test_* / bench_*")
  endif()
  if(_name MATCHES "\\.cpp$" AND NOT _name MATCHES "^(test|bench)_")
    file(STRINGS "${SRC}/${f}" _cases REGEX "^TEST(_F|_P)?\\(")
    if(_cases)
      list(APPEND _bad "${f}: defines test cases but is not named test_*.cpp (or bench_*.cpp)")
    endif()
  endif()
endforeach()
file(GLOB_RECURSE _lists "${SRC}/tests/*/CMakeLists.txt")
foreach(l IN LISTS _lists)
  file(STRINGS "${l}" _adds REGEX "kestrel_add_test\\(NAME [A-Za-z0-9_]+")
  foreach(a IN LISTS _adds)
    string(REGEX MATCH "kestrel_add_test\\(NAME ([A-Za-z0-9_]+)" _m "${a}")
    set(_target "${CMAKE_MATCH_1}")
    if(NOT _target MATCHES "^(test|bench)_")
      file(RELATIVE_PATH _rel "${SRC}" "${l}")
      list(APPEND _bad "${_rel}: test target ${_target} is not named test_* or bench_*")
    endif()
  endforeach()
endforeach()
# The folders mirror the sources: each tests/<dir> is named after the source
# folder it tests (rt, a module folder of core/, drivers/ or tools/, or a
# layer itself for the tests that span its modules), or is one of the suites
# that span layers:
#  - architecture: the tree's own rules (layers, format, tidy, docs, naming);
#  - pipeline: the whole chain, reader to outputs, under faults and budgets;
#  - cli: the `kestrel` program's commands, run as a user runs them;
#  - fuzz: one target per parser, whatever layer it lives in;
#  - common, sanitizers: helpers and suppressions, no tests of their own.
set(_spanning architecture pipeline cli fuzz common sanitizers)
file(GLOB _dirs LIST_DIRECTORIES true RELATIVE "${SRC}/tests" "${SRC}/tests/*")
foreach(d IN LISTS _dirs)
  if(NOT IS_DIRECTORY "${SRC}/tests/${d}" OR d IN_LIST _spanning OR d MATCHES "^(rt|core|drivers|tools)$")
    continue()
  endif()
  if(NOT IS_DIRECTORY "${SRC}/core/${d}" AND NOT IS_DIRECTORY "${SRC}/drivers/${d}" AND NOT IS_DIRECTORY "${SRC}/tools/${d}")
    list(APPEND _bad "tests/${d}: names no source folder (rt, core/*, drivers/*, tools/*) and is not a suite that spans layers")
  endif()
endforeach()
if(_bad)
  list(JOIN _bad "\n  " _msg)
  message(FATAL_ERROR "test naming and layout:\n  ${_msg}")
endif()
message(STATUS "every test source and target is named test_* or bench_*, and tests/ mirrors the source folders")
