// Kalibr's camera chain and IMU YAML (`kestrel calib import-kalibr`): the
// input is both files (fuzz_target.hpp's packing). Refusing is allowed
// (std::runtime_error naming file and field); a rig it makes must survive the
// rig YAML round trip exactly.
// Seeds: the Kalibr import tests' files, with the camera chain's variants they use.
#include "fuzz_target.hpp"
#include "kalibr_fixtures.hpp"
#include "kestrel/drivers/kalibr.hpp"
#include "kestrel/drivers/rig_yaml.hpp"

namespace {
kestrel::drivers::KalibrImport import(const uint8_t* data, size_t size) {
  const auto parts = kestrel::fuzz::unpack(data, size, 2);
  kestrel::Rig base;
  base.camera_rate_hz = 30;
  return kestrel::drivers::import_kalibr_text(parts[0], "camchain.yaml", parts.size() > 1 ? parts[1] : "",
                                              "imu.yaml", "cam0", base);
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  kestrel::drivers::KalibrImport imp;
  try {
    imp = import(data, size);
  } catch (const std::runtime_error&) {
    return 0;
  }
  const kestrel::Rig back =
      kestrel::drivers::rig_from_yaml(kestrel::drivers::rig_to_yaml(imp.rig), "again.yaml");
  if (!kestrel::drivers::rig_equal(back, imp.rig)) std::abort();
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  using kestrel::test::kCamchain;
  using kestrel::test::kImuYaml;
  std::string eq = kCamchain;
  eq.replace(eq.find("radtan"), 6, "equidistant");
  for (const auto& [name, camchain] :
       {std::pair<std::string, std::string>{"radtan", kCamchain}, {"equidistant", eq}}) {
    const std::string seed = pack({camchain, kImuYaml});
    write_file(dir + "/" + name + ".bin", seed);
    import(reinterpret_cast<const uint8_t*>(seed.data()),
           seed.size());  // a seed the import refuses starts nothing
  }
  return 2;
}
