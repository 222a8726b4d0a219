// Runs a shell command from a test and captures what it prints: the CLI
// tests' one way to call `kestrel` (and node) as a user would.
#pragma once

#include <sys/wait.h>

#include <array>
#include <cstdio>
#include <string>

namespace kestrel::test {

struct CmdResult {
  int code = -1;    // exit status; -1: could not run or did not exit normally
  std::string out;  // stdout and stderr together
};

inline CmdResult run_command(const std::string& cmd) {
  CmdResult r;
  FILE* p = popen((cmd + " 2>&1").c_str(), "r");
  if (p == nullptr) return r;
  std::array<char, 4096> buf{};
  size_t n;
  while ((n = fread(buf.data(), 1, buf.size(), p)) > 0) r.out.append(buf.data(), n);
  const int status = pclose(p);
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return r;
}

#ifdef KESTREL_BIN_DIR
#ifndef KESTREL_RUN_PREFIX
#define KESTREL_RUN_PREFIX ""
#endif
// The command line that starts PROGRAM of this build: through the emulator
// (with a trailing space) in a cross build, directly otherwise.
inline std::string built_program(const std::string& program) {
  return std::string(KESTREL_RUN_PREFIX) + KESTREL_BIN_DIR + "/" + program;
}

// `kestrel ARGS` from this build.
inline CmdResult run_kestrel(const std::string& args) {
  return run_command(built_program("kestrel") + " " + args);
}

// True in a cross build whose tests run under an emulator: tools that inspect
// our binaries from the host (valgrind) cannot run them.
inline bool cross_emulated() { return std::string(KESTREL_RUN_PREFIX).size() > 0; }
#endif

}  // namespace kestrel::test
