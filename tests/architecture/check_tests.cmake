# One naming for the tests (issue 45's gate), checked on the sources:
#  - a source under tests/ that defines gtest cases (TEST, TEST_F, TEST_P) is
#    named test_*.cpp, or bench_*.cpp for a benchmark that reports through gtest;
#  - no file is named *_test.* or *_bench.* (the two conventions this replaced);
#  - every kestrel_add_test() target is named test_* or bench_*.
# Support files (a shared evaluator, a profiling probe, fuzz targets) keep
# their own names. Run: cmake -DSRC=<source dir> -P check_tests.cmake
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
if(_bad)
  list(JOIN _bad "\n  " _msg)
  message(FATAL_ERROR "test naming:\n  ${_msg}")
endif()
message(STATUS "every test source and target is named test_* or bench_*")
