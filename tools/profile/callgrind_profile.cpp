#include <cstdlib>
#include <fstream>
#include <sstream>
#include <stdexcept>

#include "kestrel/tools/cpu_budget.hpp"

namespace kestrel::tools {

namespace {

bool starts_with(const std::string& s, const char* p) { return s.rfind(p, 0) == 0; }

// "fn=name" or, should a file be compressed after all, "fn=(12) name" / "fn=(12)".
std::string name_after(const std::string& line, std::size_t eq, std::map<std::string, std::string>& ids) {
  std::string v = line.substr(eq + 1);
  if (!v.empty() && v[0] == '(') {
    const std::size_t close = v.find(')');
    if (close != std::string::npos) {
      const std::string id = v.substr(0, close + 1);
      std::string rest = v.substr(close + 1);
      if (!rest.empty() && rest[0] == ' ') rest.erase(0, 1);
      if (rest.empty()) return ids[id];
      ids[id] = rest;
      return rest;
    }
  }
  return v;
}

}  // namespace

std::map<std::string, CallgrindCost> callgrind_inclusive(const std::string& path,
                                                         const std::vector<std::string>& needles) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error(path + ": cannot open");
  std::map<std::string, CallgrindCost> out;
  for (const auto& n : needles) out[n] = {};
  std::map<std::string, std::string> fn_ids;
  std::string line, fn, cfn;
  int ir_column = -1;  // which cost column is Ir
  bool expect_call_cost = false;
  std::uint64_t pending_calls = 0;
  std::size_t lineno = 0;
  bool header_seen = false;
  while (std::getline(in, line)) {
    ++lineno;
    if (lineno == 1 && !starts_with(line, "# callgrind format") && !starts_with(line, "version:"))
      throw std::runtime_error(path + ":1: not a callgrind output file");
    if (starts_with(line, "events:")) {
      std::istringstream ev(line.substr(7));
      std::string e;
      for (int i = 0; ev >> e; ++i)
        if (e == "Ir") ir_column = i;
      if (ir_column < 0)
        throw std::runtime_error(path + ":" + std::to_string(lineno) + ": no Ir event in '" + line + "'");
      header_seen = true;
      continue;
    }
    if (expect_call_cost) {
      // The line after calls=: "<position...> <inclusive cost...>". Positions
      // come first (one per `positions:` entry; line only, as written here).
      expect_call_cost = false;
      std::istringstream ls(line);
      std::string pos, tok;
      ls >> pos;
      std::uint64_t ir = 0;
      for (int i = 0; ls >> tok; ++i)
        if (i == ir_column) ir = std::strtoull(tok.c_str(), nullptr, 10);
      for (auto& [needle, cost] : out) {
        if (cfn.find(needle) == std::string::npos) continue;
        if (fn.find(needle) != std::string::npos) continue;  // recursion: already inside
        cost.calls += pending_calls;
        cost.inclusive_ir += ir;
      }
      continue;
    }
    if (starts_with(line, "fn=")) {
      fn = name_after(line, 2, fn_ids);
    } else if (starts_with(line, "cfn=")) {
      cfn = name_after(line, 3, fn_ids);
    } else if (starts_with(line, "calls=")) {
      if (!header_seen)
        throw std::runtime_error(path + ":" + std::to_string(lineno) + ": calls= before the events: line");
      pending_calls = std::strtoull(line.c_str() + 6, nullptr, 10);
      expect_call_cost = true;
    }
  }
  if (!header_seen)
    throw std::runtime_error(path + ": no events: line (not a callgrind output file, or cut short)");
  return out;
}

const std::vector<CoreModel>& arm_core_models() {
  static const std::vector<CoreModel> models{
      {"Cortex-A72", "Raspberry Pi 4, NXP i.MX 8QM", 1.5, 1.0},
      {"Cortex-A78AE", "Jetson Orin NX/AGX", 2.2, 2.0},
  };
  return models;
}

}  // namespace kestrel::tools
