// An EuRoC ASL folder (EurocReader): the IMU, camera (cam0, cam1), depth and ground-truth
// CSVs, the sensor.yaml files and Kestrel's rig and events files, unpacked
// from one input. Seeds: the log fixture exported by export_euroc.
#include "folder_fuzz.hpp"
#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/log_export.hpp"

namespace {
const std::vector<std::string> kNames = {
    "mav0/imu0/data.csv", "mav0/imu0/sensor.yaml", "mav0/cam0/data.csv", "mav0/cam0/sensor.yaml",
    "mav0/depth0/data.csv", "mav0/depth0/sensor.yaml", "mav0/state_groundtruth_estimate0/data.csv",
    "mav0/kestrel_rig.yaml", "mav0/kestrel_events.csv",
    // Appended (older inputs keep their meaning): the right camera of a stereo pair (docs/stereo.md).
    "mav0/cam1/data.csv", "mav0/cam1/sensor.yaml"};
std::unique_ptr<kestrel::drivers::LogSource> open(const std::string& dir) {
  return std::make_unique<kestrel::drivers::EurocReader>(dir);
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  kestrel::fuzz::fuzz_folder("euroc", kNames, data, size, open);
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  return write_exported_seed(dir, "euroc", kNames, kestrel::drivers::export_euroc, open);
}
