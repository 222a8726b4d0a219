// A simulated flight through the RealSense D4xx driver's fake nodes: its
// frames must come out with the log's stamps and pixels, and `kestrel replay`
// + `kestrel eval` must score it as they score the log. Apart from
// test_realsense_d4xx.cpp because it runs the `kestrel` program, which the
// ASan suite does not build (tests/CMakeLists.txt).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "kestrel/drivers/d4xx_camera.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/tools/simulator.hpp"
#include "realsense_fake_nodes.hpp"
#include "run_command.hpp"
#include "test_data.hpp"

namespace kestrel::drivers::d4xx {
namespace {

// ---- a simulated flight through the fake nodes ---------------------------------------------------
class Capture final : public tools::SimSink {
 public:
  struct Img {
    int64_t t_ns;
    uint32_t seq;
    LogImage img;
  };
  Rig rig;
  std::vector<ImuSample> imu_samples;
  std::vector<Img> rgb, depth;
  std::vector<GroundTruthPose> gt;
  void begin(const Rig& r) override { rig = r; }
  void imu(const ImuSample& s) override { imu_samples.push_back(s); }
  void image(RecordType type, int64_t t_ns, uint32_t seq, const ImageView& v) override {
    Img i{t_ns, seq, {}};
    i.img.t_ns = t_ns;
    i.img.seq = seq;
    i.img.width = v.width;
    i.img.height = v.height;
    i.img.format = v.format;
    i.img.pixels.assign(v.data, v.data + static_cast<size_t>(v.stride_bytes) * v.height);
    (type == RecordType::kRgb ? rgb : depth).push_back(std::move(i));
  }
  void ground_truth(const GroundTruthPose& g) override { gt.push_back(g); }
  void event(const Event&) override {}
  void end() override {}
};

TEST(RealSenseD4xx, SimulatedFlightMatchesItsKlogInStampsPixelsAndAte) {
  tools::SimOptions so;
  so.scenario = "figure8";
  so.duration_s = 6.0;
  so.width = 160;
  so.height = 120;
  so.seed = 43;
  Capture cap;
  tools::run_simulation(so, cap);
  ASSERT_GT(cap.rgb.size(), 150u);
  ASSERT_EQ(cap.rgb.size(), cap.depth.size());
  const int w = cap.rig.rgb.width, h = cap.rig.rgb.height;

  FakeDevice dev;
  dev["/dev/video4"].format = video_format(v4l2::kYuyv, w, h, cap.rig.camera_rate_hz, 2);
  dev["/dev/video5"].format = meta_format();
  dev["/dev/video0"].format = video_format(v4l2::kZ16, w, h, cap.rig.camera_rate_hz, 2);
  dev["/dev/video1"].format = meta_format();
  const DeviceTime dt;
  std::mt19937 rng(7);
  std::uniform_int_distribution<int64_t> jitter(0, 900'000);  // USB + scheduling above the floor
  const int64_t exposure = 6'000'000, readout = 12'000'000, floor = 120'000;
  for (size_t i = 0; i < cap.rgb.size(); ++i) {
    const int64_t t = cap.rgb[i].t_ns;
    const int64_t lat = floor + jitter(rng);
    FakeBuf c;
    c.seq = static_cast<uint32_t>(i);
    c.bytes = rgb_to_yuyv(cap.rgb[i].img.pixels.data(), w, h);
    c.t_ns = t + exposure / 2 + readout + lat + 1'000'000;
    dev["/dev/video4"].bufs.push_back(std::move(c));
    dev["/dev/video5"].bufs.push_back(
        {frame_metadata(dt, t, exposure, readout, lat, static_cast<uint32_t>(i), false),
         static_cast<uint32_t>(i), v4l2::kBufFlagTimestampMonotonic, 0});
    FakeBuf d;
    d.seq = static_cast<uint32_t>(i);
    d.bytes = cap.depth[i].img.pixels;  // DepthU16 little-endian = Z16 at the rig's unit
    d.t_ns = t + readout;
    dev["/dev/video0"].bufs.push_back(std::move(d));
    dev["/dev/video1"].bufs.push_back({frame_metadata(dt, cap.depth[i].t_ns, exposure, readout, lat + 50'000,
                                                      static_cast<uint32_t>(i), true),
                                       static_cast<uint32_t>(i), v4l2::kBufFlagTimestampMonotonic, 0});
  }

  dev["/dev/video5"].gate = &dev["/dev/video4"];
  dev["/dev/video1"].gate = &dev["/dev/video0"];
  Camera cam(fake_factory(dev));
  Options o;
  o.color = {true, "/dev/video4", "/dev/video5", {}};
  o.depth = {true, "/dev/video0", "/dev/video1", {}};
  o.depth_unit_m = cap.rig.depth.scale_m_per_unit;
  o.rig_depth_scale_m = cap.rig.depth.scale_m_per_unit;
  o.clock.latency_floor_ns = floor;
  SharedDeviceClock shared;
  o.shared_clock = &shared;
  ASSERT_EQ(cam.open(o), "");

  KlogWriter out;
  // The flight as the driver delivered it goes to a .klog, replayed below beside the simulator's own.
  const std::string dir = test::temp_dir("realsense_flight");
  const char* env = std::getenv("KESTREL_REALSENSE_KLOG_OUT");
  const std::string klog_path = env != nullptr ? std::string(env) : dir + "/d4xx.klog";
  const char* klog = klog_path.c_str();
  std::vector<std::pair<int64_t, int>> order;  // for the by-hand ATE: the flight as the driver delivered it
  std::vector<LogImage> got_rgb, got_depth;
  Frame f;
  double sum_abs_us = 0, worst_us = 0, worst_late_us = 0, sum_rgb_err = 0;
  // The IMU on the same line: each sample's raw 32-bit device stamp mapped, as the IMU thread would, with
  // the line the camera last published. What matters to the estimator is camera time minus IMU time.
  size_t next_imu = 0;
  double worst_rel_us = 0, worst_imu_abs_us = 0;
  size_t n = 0;
  while (cam.grab(10, f) == Camera::Result::kFrame) {
    const uint32_t i = f.image_meta.seq;
    ASSERT_LT(i, cap.rgb.size());
    ASSERT_NE(f.depth, nullptr) << i;
    EXPECT_EQ(f.depth_meta.seq, i);
    // Depth is bit for bit the log's.
    EXPECT_EQ(f.depth->pixels, cap.depth[i].img.pixels) << i;
    const std::vector<uint8_t>& want = cap.rgb[i].img.pixels;
    double e = 0;
    for (size_t k = 0; k < want.size(); ++k) e += std::abs(int(f.image->pixels[k]) - int(want[k]));
    sum_rgb_err += e / static_cast<double>(want.size());
    ClockLine now;
    if (shared.read(now)) {
      const double frame_err_us = (f.image_meta.t_ns - cap.rgb[i].t_ns) * 1e-3;
      for (; next_imu < cap.imu_samples.size() && cap.imu_samples[next_imu].t_ns <= cap.rgb[i].t_ns;
           ++next_imu) {
        const int64_t t = cap.imu_samples[next_imu].t_ns;
        if (t < cap.rgb[i].t_ns - 5'000'000) continue;  // the samples beside this frame
        const double imu_err_us = (now.to_host_ns(now.unwrap_us32_ns(dt.us(t))) - t) * 1e-3;
        worst_imu_abs_us = std::max(worst_imu_abs_us, std::abs(imu_err_us));
        if (i > 0) worst_rel_us = std::max(worst_rel_us, std::abs(frame_err_us - imu_err_us));
      }
    }
    if (i > 0) {
      EXPECT_EQ(f.image_meta.source, StampSource::kHardware);
      const double err_us = (f.image_meta.t_ns - cap.rgb[i].t_ns) * 1e-3;
      if (f.image_meta.t_ns > cap.rgb.front().t_ns + 2'000'000'000)
        worst_late_us = std::max(worst_late_us, std::abs(err_us));
      sum_abs_us += std::abs(err_us);
      worst_us = std::max(worst_us, std::abs(err_us));
      ++n;
    }
    {
      got_rgb.push_back(*f.image);
      got_depth.push_back(*f.depth);
      got_depth.back().t_ns = got_rgb.back().t_ns;  // one frame, one time: the colour's
    }
  }
  ASSERT_EQ(n + 1, cap.rgb.size());
  const double mean_us = sum_abs_us / static_cast<double>(n);
  std::printf(
      "[ RealSense ] %zu frames: stamp error vs the log mean %.1f us, worst %.1f us (%.1f us after 2 s); "
      "colour YUYV round trip %.2f DN mean; clock skew %.2f ppm (true 40), %llu jumps\n",
      n + 1, mean_us, worst_us, worst_late_us, sum_rgb_err / static_cast<double>(n + 1),
      cam.clock().sync().skew() * 1e6, static_cast<unsigned long long>(cam.clock().sync().jumps()));
  // The clock fit's error (docs/realsense.md, "Time"): USB latency jitter of 0.9 ms shrinks to tens of us as
  // the envelope's window fills; the first frames, before the skew is fitted, are worst.
  EXPECT_LT(mean_us, 60.0);
  EXPECT_LT(worst_us, 400.0);
  EXPECT_LT(worst_late_us, 150.0);
  EXPECT_LT(sum_rgb_err / static_cast<double>(n + 1), 1.5);
  EXPECT_NEAR(cam.clock().sync().skew(), 40e-6, 5e-6);
  // Camera and IMU in one clock: the line's error (up to a few hundred us) is common to both and
  // cancels; what is left is the us quantisation of the two stamps.
  std::printf(
      "[ RealSense ] IMU through the camera's line: worst error vs true time %.1f us, worst camera - IMU "
      "relative error %.1f us\n",
      worst_imu_abs_us, worst_rel_us);
  EXPECT_GT(worst_imu_abs_us, 50.0);  // the line's own error is really there...
  EXPECT_LT(worst_rel_us, 5.0);       // ...and cancels between the two streams
  // The line published for the IMU maps a device time like the camera's own.
  ClockLine line;
  ASSERT_TRUE(shared.read(line));
  const uint32_t probe = dt.us(cap.rgb.back().t_ns);
  EXPECT_NEAR(static_cast<double>(line.to_host_ns(cam.clock().unwrap_ns(probe))),
              static_cast<double>(cam.clock().to_host_ns(probe)), 2'000.0);

  {
    // The same flight with the driver's frames, for `kestrel replay` against the simulator's own log.
    out.open(klog, cap.rig);
    size_t a = 0, b = 0, g = 0;
    while (a < cap.imu_samples.size() || b < got_rgb.size() || g < cap.gt.size()) {
      const int64_t ta = a < cap.imu_samples.size() ? cap.imu_samples[a].t_ns : INT64_MAX;
      const int64_t tb = b < got_rgb.size() ? got_rgb[b].t_ns : INT64_MAX;
      const int64_t tg = g < cap.gt.size() ? cap.gt[g].t_ns : INT64_MAX;
      if (tg <= ta && tg <= tb) {
        out.write_ground_truth(cap.gt[g++]);
      } else if (ta <= tb) {
        out.write_imu(cap.imu_samples[a++]);
      } else {
        out.write_image(RecordType::kRgb, got_rgb[b]);
        out.write_image(RecordType::kDepth, got_depth[b]);
        ++b;
      }
    }
    out.close();
    std::printf("[ RealSense ] wrote %s\n", klog);
  }

  // ATE: the same flight through its .klog and through the D4xx driver, replayed by `kestrel replay`
  // (lockstep: deterministic) and scored by `kestrel eval` against the simulator's ground truth.
  tools::SimOptions so_klog = so;
  so_klog.out_path = dir + "/sim.klog";
  tools::run_simulation(so_klog);
  auto ate = [&](const std::string& log) {
    const std::string tum = log + ".tum";
    const test::CmdResult r = test::run_kestrel("replay " + log + " -q --traj-out " + tum);
    EXPECT_EQ(r.code, 0) << r.out;
    const test::CmdResult e = test::run_kestrel("eval --gt " + so_klog.out_path + " --est " + tum);
    EXPECT_EQ(e.code, 0) << e.out;
    const size_t at = e.out.find("ate_rmse_m: ");
    EXPECT_NE(at, std::string::npos) << e.out;
    return at == std::string::npos ? -1.0 : std::atof(e.out.c_str() + at + 12);
  };
  const double ate_klog = ate(so_klog.out_path), ate_d4xx = ate(klog_path);
  std::printf("[ RealSense ] ATE RMSE: %.1f mm through the .klog, %.1f mm through the D4xx driver\n",
              1e3 * ate_klog, 1e3 * ate_d4xx);
  ASSERT_GT(ate_klog, 0.0);
  ASSERT_GT(ate_d4xx, 0.0);
  // Noise: other noise seeds of this flight score 16..37 mm (docs/realsense.md).
  EXPECT_LT(std::abs(ate_d4xx - ate_klog), 0.010);
}

}  // namespace
}  // namespace kestrel::drivers::d4xx
