// An OpenLORIS-Scene folder (OpenLorisReader): stamp lists, the two IMU
// streams it merges, ground truth and the two calibration YAMLs, unpacked
// from one input. Seeds: the log fixture exported by export_openloris.
#include "folder_fuzz.hpp"
#include "kestrel/drivers/dataset_logs.hpp"
#include "kestrel/drivers/log_export.hpp"

namespace {
const std::vector<std::string> kNames = {"color.txt",          "aligned_depth.txt", "d400_accelerometer.txt",
                                         "d400_gyroscope.txt", "groundtruth.txt",   "sensors.yaml",
                                         "trans_matrix.yaml"};
std::unique_ptr<kestrel::drivers::LogSource> open(const std::string& dir) {
  return std::make_unique<kestrel::drivers::OpenLorisReader>(dir);
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  kestrel::fuzz::fuzz_folder("openloris", kNames, data, size, open);
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  return write_exported_seed(dir, "openloris", kNames, kestrel::drivers::export_openloris, open);
}
