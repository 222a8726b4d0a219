// The text `rs-enumerate-devices -c` prints, imported as a rig (drivers/rig
// realsense_import; `kestrel calib import-realsense`). Refusing is allowed
// (std::runtime_error naming the file, line and field); a rig it makes must
// survive the rig YAML round trip exactly, with the colour camera and with
// Infrared 1 as the camera.
// Seeds: the import tests' D435i and D455 dumps (tests/log/realsense_fixtures.hpp) and cuts of them.
#include "fuzz_target.hpp"
#include "kestrel/drivers/realsense_import.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "realsense_fixtures.hpp"

namespace {
void import(const std::string& text, const char* camera) {
  kestrel::Rig base;
  base.camera_rate_hz = 30;
  kestrel::drivers::RealSenseImportOptions o;
  o.camera = camera;
  kestrel::drivers::RealSenseImport imp;
  try {
    imp = kestrel::drivers::import_realsense_text(text, "dump.txt", o, base);
  } catch (const std::runtime_error&) {
    return;
  }
  const kestrel::Rig back =
      kestrel::drivers::rig_from_yaml(kestrel::drivers::rig_to_yaml(imp.rig), "again.yaml");
  if (!kestrel::drivers::rig_equal(back, imp.rig)) std::abort();
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  import(text, "Color");
  import(text, "Infrared 1");
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  const std::string d435i = kestrel::test::kRealSenseD435iDump, d455 = kestrel::test::kRealSenseD455Dump;
  write_file(dir + "/d435i.txt", d435i);
  write_file(dir + "/d455.txt", d455);
  // The intrinsics alone, and the extrinsics alone: the paths that name what is missing.
  const size_t motion = d435i.find("Motion Intrinsic Parameters:");
  write_file(dir + "/intrinsics_only.txt", d435i.substr(0, motion));
  write_file(dir + "/extrinsics_only.txt", d435i.substr(d435i.find("Extrinsic Parameters:")));
  return 4;
}
