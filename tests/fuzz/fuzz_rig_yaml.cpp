// Any text as a rig YAML (configs/*.yaml, the .klog header, exported
// folders). Refusing is allowed (std::runtime_error naming the field); a rig it
// accepts must write back to YAML that reads to the same rig, exactly.
// Seeds: the log fixtures' rig and a default rig, as rig_to_yaml writes them.
#include "fuzz_target.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "log_fixtures.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  kestrel::Rig rig;
  try {
    rig = kestrel::drivers::rig_from_yaml(text, "fuzz.yaml");
  } catch (const std::runtime_error&) {
    return 0;
  }
  const kestrel::Rig back = kestrel::drivers::rig_from_yaml(kestrel::drivers::rig_to_yaml(rig), "again.yaml");
  if (!kestrel::drivers::rig_equal(back, rig)) std::abort();
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  write_file(dir + "/fixture.yaml", kestrel::drivers::rig_to_yaml(kestrel::test::fixture_rig()));
  write_file(dir + "/default.yaml", kestrel::drivers::rig_to_yaml(kestrel::Rig{}));
  return 2;
}
