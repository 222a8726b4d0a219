// Any text as a whole config file (`kestrel run --config`, `kestrel replay
// --config`; tools/config/config_file.hpp): every section through the reader
// that owns it, then the live sensors' view of it. Refusing is allowed
// (std::runtime_error naming the file and key); anything else is a finding.
// Seeds: every file of configs/ as the repository ships it, and a log-driven one.
#include <filesystem>

#include "fuzz_target.hpp"
#include "kestrel/tools/config_file.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  // A config may name files (`rig: FILE`, `drivers.log.path`), which the
  // reader opens. A name with a slash could reach a device (/dev/zero, a
  // FIFO) that never ends: outside the reader's contract, so not fuzzed.
  // Names without one resolve in the working folder, which holds only
  // regular files.
  if (text.find('/') != std::string::npos) return 0;
  kestrel::tools::Config c;
  try {
    c = kestrel::tools::config_from_yaml(text, "fuzz.yaml");
  } catch (const std::runtime_error&) {
    return 0;
  }
  if (!c.has_drivers) return 0;
  try {
    (void)kestrel::tools::live_config(c);
  } catch (const std::runtime_error&) {
  }
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  size_t n = 0;
  for (const auto& e : std::filesystem::directory_iterator(KESTREL_FUZZ_CONFIGS)) {
    if (e.path().extension() != ".yaml") continue;
    std::string text = read_file(e.path().string());
    // The seeds keep to the target's rule: no slashes (comments and paths go).
    std::replace(text.begin(), text.end(), '/', '_');
    write_file(dir + "/" + e.path().filename().string(), text);
    ++n;
  }
  write_file(dir + "/log_driven.yaml",
             "drivers: {camera: {type: log}, imu: {type: log}, log: {path: f.klog, pace: lockstep}}\n"
             "estimator: {backend: window}\n");
  write_file(dir + "/unknown_section.yaml", "windw: {}\n");
  return n + 2;
}
