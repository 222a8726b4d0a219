# Run at build time (cmake -P): writes OUT with the source tree's revision,
# and only when it changed, so `kestrel version` names the commit that was
# built without recompiling anything on a build that changed nothing. A
# revision read at configure time went stale with the first commit after it
# (tools/build.sh configures a build folder once).
execute_process(COMMAND git rev-parse --short HEAD
  WORKING_DIRECTORY "${SRC}" OUTPUT_VARIABLE rev OUTPUT_STRIP_TRAILING_WHITESPACE
  RESULT_VARIABLE rc ERROR_QUIET)
if(NOT rc EQUAL 0 OR NOT rev)
  set(rev "unknown")
else()
  execute_process(COMMAND git status --porcelain --untracked-files=no
    WORKING_DIRECTORY "${SRC}" OUTPUT_VARIABLE dirty ERROR_QUIET)
  if(dirty)
    set(rev "${rev}-dirty")
  endif()
endif()
set(text "#pragma once\n#define KESTREL_GIT_REV \"${rev}\"\n")
if(EXISTS "${OUT}")
  file(READ "${OUT}" old)
endif()
if(NOT "${old}" STREQUAL "${text}")
  file(WRITE "${OUT}" "${text}")
endif()
