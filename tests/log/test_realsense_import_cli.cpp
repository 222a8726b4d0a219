// `kestrel calib import-realsense`: the command writes a rig a live config
// can use and names a missing dump. Apart from test_realsense_import.cpp
// (the importer itself, also under ASan) because it runs the `kestrel`
// program, which the ASan suite does not build (tests/CMakeLists.txt).
#include <gtest/gtest.h>

#include <fstream>
#include <string>

#include "kestrel/drivers/rig_yaml.hpp"
#include "realsense_fixtures.hpp"
#include "run_command.hpp"
#include "test_data.hpp"

namespace kestrel::test {
namespace {

TEST(RealSenseImport, CommandWritesARigAndNamesAMissingDump) {
  const std::string dir = temp_dir("realsense_cli");
  std::ofstream(dir + "/d435i.txt") << kRealSenseD435iDump;
  const std::string base_cfg = std::string(KESTREL_SOURCE_DIR) + "/configs/realsense_d435i.yaml";
  const CmdResult r = run_kestrel("calib import-realsense " + dir + "/d435i.txt --base " + base_cfg +
                                  " --out " + dir + "/my_rig.yaml");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("depth registered from the Depth stream"), std::string::npos) << r.out;
  const Rig rig = drivers::load_rig_file(dir + "/my_rig.yaml");
  EXPECT_DOUBLE_EQ(rig.rgb.fx, 615.896179199219);
  EXPECT_TRUE(rig.depth_camera.present);
  EXPECT_DOUBLE_EQ(rig.depth.max_range_m, drivers::load_rig_file(dir + "/my_rig.yaml").depth.max_range_m);
  const CmdResult ir =
      run_kestrel("calib import-realsense " + dir + "/d435i.txt --camera infrared1 --size 848x480 " +
                  "--out " + dir + "/ir.yaml");
  ASSERT_EQ(ir.code, 0) << ir.out;
  EXPECT_FALSE(drivers::load_rig_file(dir + "/ir.yaml").depth_camera.present);
  // The contract: a missing DUMP exits non-zero and names it.
  const CmdResult bad = run_kestrel("calib import-realsense " + dir + "/nope.txt --out " + dir + "/x.yaml");
  EXPECT_NE(bad.code, 0) << bad.out;
  EXPECT_NE(bad.out.find(dir + "/nope.txt: cannot open"), std::string::npos) << bad.out;
  EXPECT_FALSE(std::ifstream(dir + "/x.yaml").good());
  EXPECT_EQ(run_kestrel("calib import-realsense " + dir + "/d435i.txt --size 640").code, 2);
}

}  // namespace
}  // namespace kestrel::test
