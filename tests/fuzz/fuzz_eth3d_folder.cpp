// An ETH3D SLAM folder (Eth3dReader): the stamp lists, association,
// calibration, ground truth, IMU table and Kestrel's rig beside them, unpacked
// from one input. Seeds: the log fixture exported by export_eth3d.
#include "folder_fuzz.hpp"
#include "kestrel/drivers/dataset_logs.hpp"
#include "kestrel/drivers/log_export.hpp"

namespace {
const std::vector<std::string> kNames = {"rgb.txt",         "depth.txt", "associated.txt",  "calibration.txt",
                                         "groundtruth.txt", "imu.txt",   "kestrel_rig.yaml"};
std::unique_ptr<kestrel::drivers::LogSource> open(const std::string& dir) {
  return std::make_unique<kestrel::drivers::Eth3dReader>(dir);
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  kestrel::fuzz::fuzz_folder("eth3d", kNames, data, size, open);
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  return write_exported_seed(dir, "eth3d", kNames, kestrel::drivers::export_eth3d, open);
}
