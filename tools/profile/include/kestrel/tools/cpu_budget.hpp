// The CPU budget of `kestrel bench --cpu-budget` (issue 19): instructions per
// frame for each tracking stage and per optimizer solve, counted by callgrind,
// and what they would cost on the ARM cores companions carry.
//
// Instruction counts, not milliseconds: the same log gives the same count on an
// idle or a loaded machine (this VM exposes no hardware counters to perf, so
// valgrind's callgrind does the counting; docs/embedded.md).
#pragma once

#include <cstdint>
#include <map>
#include <string>
#include <vector>

namespace kestrel::tools {

// What callgrind charged to one function, summed over every call site.
struct CallgrindCost {
  std::uint64_t calls = 0;
  std::uint64_t inclusive_ir = 0;  // instructions executed inside it and everything it called
};

// Reads a callgrind.out file written with --compress-strings=no (names spelled
// out on every line) and returns, for each needle, the cost of the functions
// whose demangled name contains it: the sum of the inclusive cost over every
// call arc into them, leaving out arcs from a matching function into itself
// (recursion would count its cost twice). Throws std::runtime_error naming the
// file and line on a file that is not callgrind output or lacks the Ir event.
std::map<std::string, CallgrindCost> callgrind_inclusive(const std::string& path,
                                                         const std::vector<std::string>& needles);

// A core the budget is translated to: time = instructions / (IPC x clock).
struct CoreModel {
  const char* name;
  const char* example;  // the boards that carry it
  double clock_ghz;
  double ipc;  // sustained instructions per cycle assumed on this code
};
// Cortex-A72 (Raspberry Pi 4: 1.5 GHz, IPC 1.0) and Cortex-A78AE (Jetson Orin:
// 2.2 GHz, IPC 2.0). docs/embedded.md states where the figures come from.
const std::vector<CoreModel>& arm_core_models();

inline double estimated_ms(double instructions, const CoreModel& c) {
  return instructions / (c.ipc * c.clock_ghz * 1e9) * 1e3;
}

}  // namespace kestrel::tools
