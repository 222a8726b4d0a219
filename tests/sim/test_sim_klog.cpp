// `kestrel sim` output as a .klog: byte-identical for a seed, and readable
// back through the log API with the rig, images and ground truth intact.
#include <gtest/gtest.h>

#include <fstream>
#include <iterator>

#include "kestrel/drivers/log_source.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/tools/simulator.hpp"
#include "test_data.hpp"

namespace kt = kestrel::tools;
using kestrel::drivers::RecordType;

namespace {

std::string slurp(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

kt::SimOptions small(const std::string& out, uint64_t seed) {
  kt::SimOptions o;
  o.scenario = "aggressive";
  o.duration_s = 1.0;
  o.width = 160;
  o.height = 120;
  o.seed = seed;
  o.time_offset_ms = 2.5;
  o.out_path = out;
  return o;
}

}  // namespace

TEST(SimKlog, SameSeedGivesIdenticalBytes) {
  const std::string dir = kestrel::test::temp_dir("sim_klog_det");
  kt::run_simulation(small(dir + "/a.klog", 1));
  kt::run_simulation(small(dir + "/b.klog", 1));
  const kt::SimSummary s = kt::run_simulation(small(dir + "/c.klog", 2));
  const std::string a = slurp(dir + "/a.klog"), b = slurp(dir + "/b.klog"), c = slurp(dir + "/c.klog");
  // 31 frames of RGB + depth at least, compressed (the sim's pixel noise keeps
  // them above a third of raw, docs/log-format.md "Compressed images").
  ASSERT_GT(a.size(), 31u * 160 * 120 * 5 / 3);
  EXPECT_EQ(s.output_bytes, c.size());
  EXPECT_TRUE(a == b) << "same seed, different bytes";
  EXPECT_FALSE(a == c) << "different seeds, same bytes";
}

TEST(SimKlog, ReadsBackThroughTheLogApi) {
  const std::string dir = kestrel::test::temp_dir("sim_klog_read");
  const std::string path = dir + "/sim.klog";
  const kt::SimSummary sum = kt::run_simulation(small(path, 3));
  auto log = kestrel::drivers::open_log(path);
  EXPECT_EQ(log->rig().time_offset_cam_imu_ns, 2'500'000);
  EXPECT_EQ(log->rig().rgb.width, 160);
  EXPECT_NEAR(log->rig().imu.acc_bias_tau_s, 300.0, 0.0);
  kestrel::drivers::LogRecord r;
  uint64_t imu = 0, rgb = 0, depth = 0, gt = 0;
  int64_t last = INT64_MIN;
  while (log->next(r)) {
    int64_t t = 0;
    switch (r.type) {
      case RecordType::kImu:
        ++imu;
        t = r.imu.t_ns;
        break;
      case RecordType::kRgb:
        ++rgb;
        t = r.image.t_ns;
        EXPECT_EQ(r.image.format, kestrel::PixelFormat::kRgb8);
        EXPECT_EQ(r.image.pixels.size(), 160u * 120 * 3);
        break;
      case RecordType::kDepth:
        ++depth;
        t = r.image.t_ns;
        EXPECT_EQ(r.image.format, kestrel::PixelFormat::kDepthU16);
        break;
      case RecordType::kGroundTruth:
        ++gt;
        t = r.gt.t_ns;
        break;
      case RecordType::kEvent:
        t = r.event.t_ns;
        break;
      case RecordType::kRight:
        ADD_FAILURE() << "the simulator writes no stereo records";
        break;
    }
    EXPECT_GE(t, last);
    last = t;
  }
  EXPECT_TRUE(log->problems().empty());
  EXPECT_EQ(imu, sum.imu_samples);
  EXPECT_EQ(rgb, sum.frames);
  EXPECT_EQ(depth, sum.frames);
  EXPECT_EQ(gt, sum.gt_records);
}
