// klog -> EuRoC folder -> EurocReader, and the TUM trajectory export.
#include <gtest/gtest.h>

#include <cstring>
#include <fstream>
#include <sstream>

#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/log_export.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "log_fixtures.hpp"
#include "test_data.hpp"

namespace kestrel::test {
namespace {

using drivers::LogRecord;
using drivers::RecordType;

TEST(LogExport, KlogToEurocFolderRoundTrips) {
  const std::string dir = temp_dir("export_euroc");
  const std::string klog = dir + "/in.klog";
  {
    drivers::KlogWriter w;
    w.open(klog, fixture_rig());
    for (uint32_t i = 0; i < 40; ++i) {
      w.write_imu(fixture_imu(i));
      if (i % 8 == 0) {
        auto rgb = fixture_image(i, PixelFormat::kRgb8);
        rgb.t_ns = fixture_imu(i).t_ns;
        w.write_image(RecordType::kRgb, rgb);
        auto depth = fixture_image(i, PixelFormat::kDepthU16);
        depth.t_ns = rgb.t_ns;
        w.write_image(RecordType::kDepth, depth);
      }
      if (i % 2 == 0) {
        auto g = fixture_gt(i, i % 4 == 0);
        g.t_ns = fixture_imu(i).t_ns;
        w.write_ground_truth(g);
      }
    }
    w.write_event(Event{fixture_imu(39).t_ns, EventCode::kClockJump, "jump, 3 ms"});
  }
  drivers::KlogReader in(klog);
  const auto st = drivers::export_euroc(in, dir + "/out");
  EXPECT_EQ(st.imu, 40u);
  EXPECT_EQ(st.rgb, 5u);
  EXPECT_EQ(st.depth, 5u);
  EXPECT_EQ(st.ground_truth, 20u);
  EXPECT_EQ(st.events, 1u);

  drivers::EurocReader back(dir + "/out");
  EXPECT_TRUE(back.problems().empty()) << back.problems()[0].where << " " << back.problems()[0].detail;
  // The klog reader moved the camera stamps onto the IMU's clock, so the
  // export carries them shifted and its rig has no offset left.
  Rig expected = fixture_rig();
  expected.time_offset_cam_imu_ns = 0;
  EXPECT_TRUE(drivers::rig_equal(back.rig(), expected));
  const auto a = all_records(in);
  const auto b = all_records(back);
  ASSERT_EQ(a.size(), b.size());
  // Both are time-ordered with IMU first at equal times, so records pair up one to one.
  auto by_type = [](const std::vector<LogRecord>& v, RecordType t) {
    std::vector<LogRecord> o;
    for (const auto& r : v)
      if (r.type == t) o.push_back(r);
    return o;
  };
  const auto ia = by_type(a, RecordType::kImu), ib = by_type(b, RecordType::kImu);
  ASSERT_EQ(ia.size(), ib.size());
  for (size_t i = 0; i < ia.size(); ++i) {
    EXPECT_EQ(ia[i].imu.t_ns, ib[i].imu.t_ns);
    EXPECT_EQ(std::memcmp(ia[i].imu.gyro_rps.data(), ib[i].imu.gyro_rps.data(), 24), 0);
    EXPECT_EQ(std::memcmp(ia[i].imu.acc_mps2.data(), ib[i].imu.acc_mps2.data(), 24), 0);
  }
  const auto ga = by_type(a, RecordType::kGroundTruth), gb = by_type(b, RecordType::kGroundTruth);
  ASSERT_EQ(ga.size(), gb.size());
  for (size_t i = 0; i < ga.size(); ++i) {
    EXPECT_EQ(ga[i].gt.t_ns, gb[i].gt.t_ns);
    EXPECT_EQ(ga[i].gt.p_WB, gb[i].gt.p_WB);
    EXPECT_EQ(ga[i].gt.q_WB, gb[i].gt.q_WB);
    EXPECT_EQ(ga[i].gt.has_velocity, gb[i].gt.has_velocity);
    EXPECT_EQ(ga[i].gt.v_WB, gb[i].gt.v_WB);
  }
  for (RecordType t : {RecordType::kRgb, RecordType::kDepth}) {
    const auto xa = by_type(a, t), xb = by_type(b, t);
    ASSERT_EQ(xa.size(), xb.size());
    for (size_t i = 0; i < xa.size(); ++i) {
      EXPECT_EQ(xa[i].image.t_ns, xb[i].image.t_ns);
      EXPECT_EQ(xa[i].image.format, xb[i].image.format);
      EXPECT_EQ(xa[i].image.pixels, xb[i].image.pixels);
    }
  }
  const auto ea = by_type(a, RecordType::kEvent), eb = by_type(b, RecordType::kEvent);
  ASSERT_EQ(eb.size(), 1u);
  EXPECT_EQ(eb[0].event.text, ea[0].event.text);
  EXPECT_EQ(eb[0].event.code, EventCode::kClockJump);
}

TEST(LogExport, TumTrajectoryHasSecondsAndXyzwQuaternions) {
  const std::string dir = temp_dir("export_tum");
  {
    drivers::KlogWriter w;
    w.open(dir + "/in.klog", fixture_rig());
    for (uint32_t i = 0; i < 5; ++i) w.write_ground_truth(fixture_gt(i, false));
  }
  drivers::KlogReader in(dir + "/in.klog");
  EXPECT_EQ(drivers::export_tum_groundtruth(in, dir + "/gt.txt"), 5u);
  std::ifstream f(dir + "/gt.txt");
  std::string line;
  uint32_t i = 0;
  while (std::getline(f, line)) {
    if (line[0] == '#') continue;
    const auto g = fixture_gt(i++, false);
    std::istringstream s(line);
    std::string t;
    double v[7];
    s >> t;
    for (double& x : v) s >> x;
    EXPECT_EQ(t, std::to_string(g.t_ns / 1000000000) + "." +
                     std::to_string(g.t_ns % 1000000000 + 1000000000).substr(1));
    EXPECT_EQ(v[0], g.p_WB[0]);
    EXPECT_EQ(v[3], g.q_WB[1]);
    EXPECT_EQ(v[5], g.q_WB[3]);
    EXPECT_EQ(v[6], g.q_WB[0]);
  }
  EXPECT_EQ(i, 5u);
}

}  // namespace
}  // namespace kestrel::test
