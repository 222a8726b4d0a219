// A TUM-VI folder (TumviReader): the ASL tables of cam0, cam1, imu0 and mocap0,
// the Kalibr chain in dso/camchain.yaml and dso/imu_config.yaml, unpacked from
// one input. Seed: the log fixture exported to EuRoC, its ground truth as
// mocap0, and the Kalibr tests' files with a second camera.
#include "folder_fuzz.hpp"
#include "kalibr_fixtures.hpp"
#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/log_export.hpp"

namespace {
const std::vector<std::string> kNames = {"mav0/imu0/data.csv",   "mav0/cam0/data.csv", "mav0/cam1/data.csv",
                                         "mav0/mocap0/data.csv", "dso/camchain.yaml",  "dso/imu_config.yaml"};
std::unique_ptr<kestrel::drivers::LogSource> open(const std::string& dir) {
  return std::make_unique<kestrel::drivers::TumviReader>(dir);
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  kestrel::fuzz::fuzz_folder("tumvi", kNames, data, size, open);
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  namespace fs = std::filesystem;
  const std::string out = exported_fixture("tumvi", kestrel::drivers::export_euroc);
  fs::create_directories(out + "/mav0/mocap0");
  fs::create_directories(out + "/mav0/cam1");
  fs::create_directories(out + "/dso");
  fs::copy_file(out + "/mav0/state_groundtruth_estimate0/data.csv", out + "/mav0/mocap0/data.csv",
                fs::copy_options::overwrite_existing);
  fs::copy_file(out + "/mav0/cam0/data.csv", out + "/mav0/cam1/data.csv",
                fs::copy_options::overwrite_existing);
  // cam1: cam0 moved 10 cm along its x, so the pairing check and the stereo import both run.
  std::string chain = kestrel::test::kCamchain;
  std::string cam1 = chain.substr(chain.find('\n') + 1);
  cam1.replace(cam1.find("0.015]"), 6, "-0.085]");
  chain += "cam1:\n" + cam1;
  write_file(out + "/dso/camchain.yaml", chain);
  write_file(out + "/dso/imu_config.yaml", kestrel::test::kImuYaml);
  write_folder_seed(dir + "/exported.bin", "tumvi", kNames, pack_folder(out, kNames), open);
  return 1;
}
