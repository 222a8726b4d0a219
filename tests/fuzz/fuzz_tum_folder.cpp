// A TUM RGB-D folder (TumReader): rgb.txt, depth.txt, groundtruth.txt and
// accelerometer.txt, unpacked from one input. Kestrel exports no TUM folder;
// ETH3D's lists are TUM's, so the seed is the fixture exported by
// export_eth3d with its IMU table cut to TUM's accelerometer columns.
#include "folder_fuzz.hpp"
#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/log_export.hpp"
#include "kestrel/drivers/text.hpp"

namespace {
const std::vector<std::string> kNames = {"rgb.txt", "depth.txt", "groundtruth.txt", "accelerometer.txt"};
std::unique_ptr<kestrel::drivers::LogSource> open(const std::string& dir) {
  return std::make_unique<kestrel::drivers::TumReader>(dir);
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  kestrel::fuzz::fuzz_folder("tum", kNames, data, size, open);
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  namespace tx = kestrel::drivers::text;
  const std::string out = exported_fixture("tum", kestrel::drivers::export_eth3d);
  std::vector<std::string> lines;
  tx::read_lines(out + "/imu.txt", lines);
  std::string acc = "# accelerometer data\n# timestamp ax ay az\n";
  for (const auto& l : lines) {
    const auto f = tx::split_ws(l);
    if (f.size() == 7 && l[0] != '#') acc += f[0] + " " + f[4] + " " + f[5] + " " + f[6] + "\n";
  }
  write_file(out + "/accelerometer.txt", acc);
  write_folder_seed(dir + "/exported.bin", "tum", kNames, pack_folder(out, kNames), open);
  return 1;
}
