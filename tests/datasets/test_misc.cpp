// open_log's detection and the format names.
#include <gtest/gtest.h>

#include <filesystem>

#include "dataset_fixtures.hpp"
#include "kestrel/drivers/dataset_logs.hpp"
#include "kestrel/drivers/log_export.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/drivers/rig_yaml.hpp"

namespace kestrel::test {
namespace {

TEST(OpenLogDatasets, FormatNamesParse) {
  EXPECT_EQ(drivers::parse_log_format("eth3d"), drivers::LogFormat::kEth3d);
  EXPECT_EQ(drivers::parse_log_format("openloris"), drivers::LogFormat::kOpenLoris);
  EXPECT_EQ(drivers::parse_log_format("rosbag"), drivers::LogFormat::kRosbag);
  try {
    drivers::parse_log_format("bag");
    FAIL();
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("openloris"), std::string::npos) << e.what();
  }
}

TEST(OpenLogDatasets, DetectsEachLayoutAndTumStaysTum) {
  const std::string dir = temp_dir("open_detect");
  write_small_klog(dir + "/a.klog");
  auto k = drivers::open_log(dir + "/a.klog");
  drivers::export_eth3d(*k, dir + "/eth3d");
  drivers::export_openloris(*k, dir + "/ol");
  EXPECT_EQ(drivers::open_log(dir + "/eth3d")->format_name(), "eth3d");
  EXPECT_EQ(drivers::open_log(dir + "/ol")->format_name(), "openloris");
  // A TUM folder (rgb.txt, no calibration.txt / associated.txt / imu.txt) is not taken for ETH3D.
  std::filesystem::create_directories(dir + "/tum");
  write_text(dir + "/tum/rgb.txt", "# none\n");
  EXPECT_EQ(drivers::open_log(dir + "/tum")->format_name(), "tum");
  // Forcing a format on the wrong input is an error naming the path.
  try {
    drivers::open_log(dir + "/tum", drivers::LogFormat::kOpenLoris);
    FAIL();
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find(dir + "/tum"), std::string::npos) << e.what();
  }
  // A file that is neither klog nor bag.
  write_text(dir + "/x.txt", "hello");
  EXPECT_THROW(drivers::open_log(dir + "/x.txt"), std::runtime_error);
  EXPECT_FALSE(drivers::is_rosbag_file(dir + "/x.txt"));
}

TEST(OpenLogDatasets, RigOptionReachesTheDatasetReaders) {
  const std::string dir = temp_dir("open_rig");
  write_small_klog(dir + "/a.klog");
  auto k = drivers::open_log(dir + "/a.klog");
  drivers::export_eth3d(*k, dir + "/eth3d");
  write_text(dir + "/rig.yaml", drivers::rig_to_yaml(small_rig()));
  drivers::LogOpenOptions o;
  o.rig_path = dir + "/rig.yaml";
  EXPECT_EQ(drivers::open_log(dir + "/eth3d", o)->rig().T_BC, small_rig().T_BC);
  EXPECT_EQ(drivers::open_log(dir + "/eth3d")->rig().T_BC, small_rig().T_BC)
      << "the export's kestrel_rig.yaml";
  std::filesystem::remove(dir + "/eth3d/kestrel_rig.yaml");
  EXPECT_EQ(drivers::open_log(dir + "/eth3d")->rig().T_BC, kIdentity4);
  o.rig_path = dir + "/nothere.yaml";
  EXPECT_THROW(drivers::open_log(dir + "/eth3d", o), std::runtime_error);
}

}  // namespace
}  // namespace kestrel::test

namespace kestrel::test {
namespace {

// Damaged text files (cut short, bytes changed, lines doubled) in every file of an exported
// ETH3D and OpenLORIS folder: the reader either refuses with an error naming the file, or reads
// what is intact and reports the rest. Never a crash, never an exception of another type.
TEST(DatasetsMutation, DamagedTextFilesNeverCrashAReader) {
  const std::string dir = temp_dir("datasets_mutation");
  write_small_klog(dir + "/a.klog", small_rig(), 4);
  {
    auto k = drivers::open_log(dir + "/a.klog");
    drivers::export_eth3d(*k, dir + "/eth3d");
    drivers::export_openloris(*k, dir + "/ol");
  }
  const auto slurp = [](const std::string& p) {
    std::ifstream f(p, std::ios::binary);
    return std::string(std::istreambuf_iterator<char>(f), {});
  };
  uint64_t rng = 12345;
  const auto next = [&rng] {
    rng = rng * 6364136223846793005ull + 1442695040888963407ull;
    return static_cast<uint32_t>(rng >> 33);
  };
  size_t refused = 0, read = 0;
  for (const auto& [folder, format] :
       {std::pair<std::string, drivers::LogFormat>{"eth3d", drivers::LogFormat::kEth3d},
        {"ol", drivers::LogFormat::kOpenLoris}}) {
    for (const auto& entry : std::filesystem::directory_iterator(dir + "/" + folder)) {
      if (!entry.is_regular_file()) continue;
      const std::string path = entry.path().string();
      const std::string original = slurp(path);
      for (int m = 0; m < 40; ++m) {
        std::string s = original;
        const size_t at = s.empty() ? 0 : next() % s.size();
        switch (m % 4) {
          case 0:
            s.resize(at);
            break;  // cut short
          case 1:
            if (!s.empty()) s[at] = "x-.:[{ \n9e"[next() % 11];
            break;  // a byte changed
          case 2:
            s.insert(at, s.substr(at, std::min<size_t>(40, s.size() - at)));
            break;  // bytes doubled
          case 3:
            s.insert(at, "\n1e309 nan -inf 99999999999999999999999 ]]]\n");
            break;  // hostile numbers
        }
        write_text(path, s);
        try {
          auto log = drivers::open_log(dir + "/" + folder, format);
          read_all(*log);
          ++read;
        } catch (const std::runtime_error& e) {
          EXPECT_NE(std::string(e.what()).find(dir + "/" + folder), std::string::npos)
              << e.what() << " (mutating " << path << ")";
          ++refused;
        }
      }
      write_text(path, original);
    }
  }
  EXPECT_GT(read, 0u);
  EXPECT_GT(refused, 0u);
}

}  // namespace
}  // namespace kestrel::test
