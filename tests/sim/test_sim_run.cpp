// run_simulation end to end into an in-memory sink: determinism, record
// order, counts, camera timing, GT-file and hybrid modes, errors.
#include <gtest/gtest.h>

#include <cstring>
#include <fstream>

#include "kestrel/tools/simulator.hpp"
#include "test_data.hpp"

namespace kt = kestrel::tools;
using kestrel::drivers::RecordType;

namespace {

// Hashes every byte it is given (FNV-1a) and keeps what the tests look at.
class RecordingSink final : public kt::SimSink {
 public:
  uint64_t hash = 1469598103934665603ull;
  kestrel::Rig rig;
  std::vector<kestrel::ImuSample> imu_samples;
  std::vector<kestrel::GroundTruthPose> gts;
  std::vector<std::pair<int64_t, uint32_t>> frames;  // rgb stamp, seq
  std::vector<std::string> events;
  std::vector<int64_t> all_times;
  bool ended = false;

  void begin(const kestrel::Rig& r) override { rig = r; }
  void imu(const kestrel::ImuSample& s) override {
    imu_samples.push_back(s);
    all_times.push_back(s.t_ns);
    mix(&s.t_ns, sizeof s.t_ns);
    mix(s.gyro_rps.data(), sizeof(double) * 3);
    mix(s.acc_mps2.data(), sizeof(double) * 3);
    mix(&s.flags, sizeof s.flags);
  }
  void image(RecordType type, int64_t t_ns, uint32_t seq, const kestrel::ImageView& v) override {
    if (type == RecordType::kRgb) frames.emplace_back(t_ns, seq);
    all_times.push_back(t_ns);
    EXPECT_EQ(v.stride_bytes, v.width * kestrel::bytes_per_pixel(v.format));
    mix(&t_ns, sizeof t_ns);
    mix(v.data, static_cast<size_t>(v.stride_bytes) * v.height);
  }
  void ground_truth(const kestrel::GroundTruthPose& g) override {
    gts.push_back(g);
    all_times.push_back(g.t_ns);
    mix(&g.t_ns, sizeof g.t_ns);
    mix(g.p_WB.data(), sizeof(double) * 3);
    mix(g.q_WB.data(), sizeof(double) * 4);
  }
  void event(const kestrel::Event& e) override {
    events.push_back(e.text);
    all_times.push_back(e.t_ns);
    mix(e.text.data(), e.text.size());
  }
  void end() override { ended = true; }

 private:
  void mix(const void* p, size_t n) {
    const auto* b = static_cast<const uint8_t*>(p);
    for (size_t i = 0; i < n; ++i) hash = (hash ^ b[i]) * 1099511628211ull;
  }
};

kt::SimOptions small(const std::string& scenario, double duration) {
  kt::SimOptions o;
  o.scenario = scenario;
  o.duration_s = duration;
  o.width = 160;
  o.height = 120;
  return o;
}

RecordingSink run(const kt::SimOptions& o) {
  RecordingSink s;
  kt::run_simulation(o, s);
  return s;
}

}  // namespace

TEST(SimRun, SameSeedSameRecordsDifferentSeedDifferent) {
  kt::SimOptions o = small("figure8", 1.5);
  o.seed = 5;
  const RecordingSink a = run(o), b = run(o);
  o.seed = 6;
  const RecordingSink c = run(o);
  EXPECT_EQ(a.hash, b.hash);
  EXPECT_NE(a.hash, c.hash);
  // The motion is the same flight whatever the seed.
  ASSERT_EQ(a.gts.size(), c.gts.size());
  EXPECT_EQ(a.gts.back().p_WB, c.gts.back().p_WB);
}

TEST(SimRun, CountsRatesOrderAndRig) {
  kt::SimOptions o = small("hover", 2.0);
  kt::SimSummary sum;
  RecordingSink s;
  sum = kt::run_simulation(o, s);
  EXPECT_TRUE(s.ended);
  EXPECT_EQ(sum.frames, 61u);        // 0 .. 2 s at 30 Hz
  EXPECT_EQ(sum.imu_samples, 801u);  // 0 .. 2 s at 400 Hz
  EXPECT_EQ(s.imu_samples.size(), 801u);
  EXPECT_EQ(sum.gt_records, s.gts.size());
  EXPECT_GE(s.gts.size(), 401u);  // 200 Hz plus frame times off that grid
  EXPECT_TRUE(std::is_sorted(s.all_times.begin(), s.all_times.end()));
  EXPECT_EQ(s.rig.rgb.width, 160);
  EXPECT_NEAR(s.rig.rgb.fx, 525.0 / 4, 1e-9);
  EXPECT_EQ(s.rig.imu_rate_hz, 400.0);
  EXPECT_EQ(s.rig.imu.acc_bias_tau_s, 300.0);
  EXPECT_NEAR(s.rig.imu.gyro_noise_density_rad_s_sqrthz, 2.4435e-4, 1e-8);
  for (const auto& g : s.gts) EXPECT_TRUE(g.has_velocity);
  // A ground-truth pose at every frame time.
  for (const auto& f : s.frames)
    EXPECT_TRUE(std::any_of(s.gts.begin(), s.gts.end(), [&](const auto& g) { return g.t_ns == f.first; }));
  // The first event describes the run; then the true biases once a second.
  ASSERT_GE(s.events.size(), 3u);
  EXPECT_NE(s.events[0].find("scenario hover"), std::string::npos);
  EXPECT_EQ(s.events[1].rfind("true_bias gyro_rps=", 0), 0u);
  EXPECT_GT(sum.render_fps, 0.0);

  // --no-noise: the biases are zero, no bias events.
  o.noise = false;
  const RecordingSink clean = run(o);
  EXPECT_EQ(clean.rig.imu.gyro_noise_density_rad_s_sqrthz, 0.0);
  EXPECT_EQ(clean.events.size(), 1u);
}

TEST(SimRun, CameraTimingOffsetJitterAndDrops) {
  kt::SimOptions o = small("static", 4.0);
  o.time_offset_ms = 5.0;
  const RecordingSink off = run(o);
  EXPECT_EQ(off.rig.time_offset_cam_imu_ns, 5'000'000);
  // Frame k stamped at true time - offset; the true time has a GT record.
  EXPECT_EQ(off.frames[3].first, off.imu_samples[0].t_ns + 100'000'000 - 5'000'000);
  EXPECT_TRUE(std::is_sorted(off.all_times.begin(), off.all_times.end()));

  o.time_offset_ms = 0.0;
  o.timestamp_jitter_us = 500.0;
  const RecordingSink jit = run(o);
  double sum2 = 0;
  for (size_t k = 0; k < jit.frames.size(); ++k) {
    const double e = static_cast<double>(jit.frames[k].first -
                                         (1'000'000'000 + static_cast<int64_t>(std::llround(k * 1e9 / 30))));
    sum2 += e * e;
    EXPECT_LE(std::abs(e), 0.4e9 / 30);
  }
  EXPECT_NEAR(std::sqrt(sum2 / jit.frames.size()), 500e3, 150e3);

  o.timestamp_jitter_us = 0.0;
  o.frame_drop_rate = 0.3;
  kt::SimSummary sum;
  RecordingSink drop;
  sum = kt::run_simulation(o, drop);
  EXPECT_EQ(sum.frames + sum.frames_dropped, 121u);
  EXPECT_GT(sum.frames_dropped, 15u);
  EXPECT_LT(sum.frames_dropped, 60u);
  // Real drops leave gaps in seq and nothing else.
  EXPECT_EQ(drop.frames.size(), sum.frames);
  EXPECT_GT(drop.frames.back().second, drop.frames.size() - 1);
}

TEST(SimRun, GroundTruthFileFramesAtItsSampleTimes) {
  const std::string dir = kestrel::test::temp_dir("sim_run_gt");
  const auto truth = kt::make_scenario("figure8", 6);
  {
    std::ofstream f(dir + "/groundtruth.txt");
    f << "# timestamp tx ty tz qx qy qz qw\n";
    f.precision(10);
    for (int k = 0; k <= 120; ++k) {  // 20 Hz
      const auto s = truth->state(k * 0.05);
      char stamp[32];
      std::snprintf(stamp, sizeof stamp, "%d.%09d ", 1305031098 + k / 20, (k % 20) * 50'000'000);
      f << stamp << s.p_WB.x() << ' ' << s.p_WB.y() << ' ' << s.p_WB.z() << ' ' << s.q_WB.x() << ' '
        << s.q_WB.y() << ' ' << s.q_WB.z() << ' ' << s.q_WB.w() << '\n';
    }
  }
  kt::SimOptions o;
  o.trajectory_path = dir + "/groundtruth.txt";
  o.width = 160;
  o.height = 120;
  o.start_s = 1.0;
  o.duration_s = 2.0;
  const RecordingSink s = run(o);
  ASSERT_EQ(s.frames.size(), 41u);
  EXPECT_EQ(s.frames[0].first, 1305031099'000'000'000);
  EXPECT_EQ(s.frames[1].first - s.frames[0].first, 50'000'000);
  EXPECT_NEAR(s.rig.camera_rate_hz, 20.0, 1e-6);
  // Synthetic IMU along the spline: starts at the span's first sample.
  EXPECT_EQ(s.imu_samples.front().t_ns, 1305031099'000'000'000);
  EXPECT_EQ(s.imu_samples.size(), 801u);

  o.fps = 10.0;
  EXPECT_EQ(run(o).frames.size(), 21u);
}

TEST(SimRun, HybridWritesTheRealImuAndEurocCameraPlacement) {
  KESTREL_REQUIRE_SHARED("euroc/V1_02_medium/imu0.csv");
  kt::SimOptions o;
  o.trajectory_path = kestrel::test::shared_path("euroc/V1_02_medium/gt_body_20hz.csv");
  o.imu_path = kestrel::test::shared_path("euroc/V1_02_medium/imu0.csv");
  o.start_s = 20.0;
  o.duration_s = 1.0;
  o.width = 160;
  o.height = 120;
  const RecordingSink s = run(o);
  const auto real = kt::load_euroc_imu_csv(o.imu_path);
  ASSERT_GE(s.imu_samples.size(), 199u);
  ASSERT_LE(s.imu_samples.size(), 201u);
  const auto it =
      std::find_if(real.begin(), real.end(), [&](const auto& m) { return m.t_ns == s.imu_samples[0].t_ns; });
  ASSERT_NE(it, real.end());
  EXPECT_EQ(it->gyro_rps, s.imu_samples[0].gyro_rps);
  EXPECT_EQ(it->acc_mps2, s.imu_samples[0].acc_mps2);
  EXPECT_EQ(s.frames.size(), 21u);  // the GT's own 20 Hz times
  EXPECT_EQ(s.rig.imu_rate_hz, 200.0);
  EXPECT_NEAR(s.rig.imu.gyro_noise_density_rad_s_sqrthz, 1.6968e-4, 1e-10);
  EXPECT_NEAR(s.rig.T_BC[3], -0.0216401454975, 1e-12);  // cam0 T_BS
  EXPECT_NEAR(s.rig.T_BC[1], -0.999880929698, 1e-6);
}

TEST(SimRun, BadOptionsAndFilesAreReported) {
  auto option_error = [](kt::SimOptions o, const std::string& needle) {
    try {
      RecordingSink s;
      kt::run_simulation(o, s);
      ADD_FAILURE() << "no error, expected " << needle;
    } catch (const kt::SimOptionError& e) {
      EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
    }
  };
  kt::SimOptions o = small("hover", 1.0);
  o.scenario = "loop";
  option_error(o, "--scenario");
  o = small("hover", 1.0);
  o.frame_drop_rate = 1.0;
  option_error(o, "--frame-drop-rate");
  o = small("hover", 1.0);
  o.width = 4;
  option_error(o, "--width");
  o = small("hover", 1.0);
  o.trajectory_path = "/nonexistent/gt.csv";
  option_error(o, "no such file");
  o = small("hover", 1.0);
  o.imu_path = "imu0.csv";
  option_error(o, "--imu");
  o = small("hover", 1.0);
  o.texture_path = "/nonexistent.png";
  option_error(o, "--texture");

  const std::string dir = kestrel::test::temp_dir("sim_run_bad");
  std::ofstream(dir + "/gt.csv") << "1,0,0,1,1,0,0,0\n2,0,0,1,1,0,0,0\nthree,0,0,1,1,0,0,0\n";
  o = small("hover", 1.0);
  o.trajectory_path = dir + "/gt.csv";
  o.duration_s = -1;
  try {
    RecordingSink s;
    kt::run_simulation(o, s);
    ADD_FAILURE() << "no error";
  } catch (const kt::SimOptionError& e) {
    ADD_FAILURE() << "a malformed file is not an option error: " << e.what();
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("gt.csv:3"), std::string::npos) << e.what();
  }
}

TEST(SimRun, RigFileOverridesTheBuiltInRig) {
  const std::string dir = kestrel::test::temp_dir("sim_run_rig");
  std::ofstream(dir + "/rig.yaml")
      << "name: test-rig\n"
         "camera: {width_px: 320, height_px: 240, fx_px: 300, fy_px: 300, cx_px: 160,"
         " cy_px: 120, distortion: none, rate_hz: 15}\n"
         "depth: {max_range_m: 4.0}\n"
         "imu: {rate_hz: 100, gyro_noise_density_rad_s_sqrthz: 1.0e-3}\n";
  kt::SimOptions o = small("hover", 1.0);
  o.width.reset();
  o.height.reset();
  o.rig_path = dir + "/rig.yaml";
  const RecordingSink s = run(o);
  EXPECT_EQ(s.rig.name, "test-rig");
  EXPECT_EQ(s.rig.rgb.width, 320);
  EXPECT_EQ(s.rig.rgb.fx, 300.0);
  EXPECT_EQ(s.rig.depth.max_range_m, 4.0);
  EXPECT_EQ(s.rig.imu.gyro_noise_density_rad_s_sqrthz, 1.0e-3);
  EXPECT_EQ(s.frames.size(), 16u);
  EXPECT_EQ(s.imu_samples.size(), 101u);

  std::ofstream(dir + "/bad.yaml")
      << "camera: {width_px: wide, height_px: 240, fx_px: 1, fy_px: 1, cx_px: 0, cy_px: 0}\n";
  o.rig_path = dir + "/bad.yaml";
  try {
    run(o);
    ADD_FAILURE() << "no error";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("bad.yaml"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("width_px"), std::string::npos) << e.what();
  }
}
