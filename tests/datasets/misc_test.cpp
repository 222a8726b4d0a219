// open_log's detection and the format names.
#include <gtest/gtest.h>

#include <filesystem>

#include "dataset_fixtures.hpp"
#include "kestrel/drivers/dataset_logs.hpp"
#include "kestrel/drivers/log_export.hpp"
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
