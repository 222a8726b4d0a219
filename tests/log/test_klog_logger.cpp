// KlogLogger: a producer at 400 Hz IMU + 30 Hz VGA RGB + depth, run faster
// than real time, loses nothing and the file reads back identical.
#include <gtest/gtest.h>

#include <chrono>
#include <thread>

#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/klog_logger.hpp"
#include "log_fixtures.hpp"
#include "test_data.hpp"
#include "test_scale.hpp"

namespace kestrel::test {
namespace {

using drivers::RecordType;

uint8_t pixel(uint32_t seq, size_t k, bool depth) {
  return static_cast<uint8_t>((k * 31 + seq * 7 + depth) & 0xff);
}

TEST(KlogLogger, RgbdAndImuThroughputWithoutDrops) {
  const std::string path = temp_dir("klog_logger") + "/rt.klog";
  constexpr int kW = 640, kH = 480;
  constexpr double kSeconds = 2.0;
  // Faster than real time, with margin for a loaded CI machine. Sanitizer-sized
  // runs (the ASan suite, whose objects also carry the fuzzer's coverage
  // counters) feed at half real time: there the test is about memory safety
  // under two threads, and at 2x the instrumented writer fell behind and dropped.
  const double speedup = small_scale() ? 0.5 : 2.0;
  constexpr int64_t kImuPeriodNs = 2'500'000;   // 400 Hz
  constexpr int64_t kCamPeriodNs = 33'333'333;  // 30 Hz
  std::vector<uint8_t> rgb(kW * kH * 3), depth(kW * kH * 2);

  drivers::KlogLogger logger(path, fixture_rig());
  size_t n_imu = 0, n_cam = 0;
  std::thread producer([&] {
    const auto start = std::chrono::steady_clock::now();
    int64_t next_cam = 0;
    for (int64_t t = 0; t <= static_cast<int64_t>(kSeconds * 1e9); t += kImuPeriodNs) {
      std::this_thread::sleep_until(start + std::chrono::nanoseconds(static_cast<int64_t>(t / speedup)));
      ImuSample s = fixture_imu(static_cast<uint32_t>(n_imu));
      s.t_ns = t;
      EXPECT_TRUE(logger.log_imu(s));
      ++n_imu;
      if (t >= next_cam) {
        const auto seq = static_cast<uint32_t>(n_cam);
        for (size_t k = 0; k < rgb.size(); ++k) rgb[k] = pixel(seq, k, false);
        for (size_t k = 0; k < depth.size(); ++k) depth[k] = pixel(seq, k, true);
        EXPECT_TRUE(logger.log_image(RecordType::kRgb, t, t + 1000, seq, 5000,
                                     ImageView{kW, kH, kW * 3, PixelFormat::kRgb8, rgb.data()}));
        EXPECT_TRUE(logger.log_image(RecordType::kDepth, t, t + 1000, seq, 5000,
                                     ImageView{kW, kH, kW * 2, PixelFormat::kDepthU16, depth.data()}));
        ++n_cam;
        next_cam += kCamPeriodNs;
      }
    }
    EXPECT_TRUE(logger.log_event(static_cast<int64_t>(kSeconds * 1e9), EventCode::kInfo, "done"));
  });
  producer.join();
  logger.stop();
  const auto st = logger.stats();
  EXPECT_EQ(st.imu_drops, 0u);
  EXPECT_EQ(st.image_drops, 0u);
  EXPECT_EQ(st.event_drops, 0u);
  EXPECT_EQ(st.records_lost_to_write_errors, 0u);
  EXPECT_EQ(logger.error(), "");
  EXPECT_EQ(st.records_written, n_imu + 2 * n_cam + 1);
  EXPECT_EQ(n_imu, 801u);
  EXPECT_EQ(n_cam, 61u);

  drivers::KlogReader r(path);
  drivers::LogRecord rec;
  size_t imu = 0, rgb_n = 0, depth_n = 0, ev = 0;
  while (r.next(rec)) {
    if (rec.type == RecordType::kImu) {
      const ImuSample want = fixture_imu(static_cast<uint32_t>(imu));
      EXPECT_EQ(rec.imu.t_ns, static_cast<int64_t>(imu) * kImuPeriodNs);
      EXPECT_EQ(rec.imu.gyro_rps, want.gyro_rps);
      EXPECT_EQ(rec.imu.seq, want.seq);
      ++imu;
    } else if (rec.type == RecordType::kEvent) {
      EXPECT_EQ(rec.event.text, "done");
      ++ev;
    } else {
      const bool is_depth = rec.type == RecordType::kDepth;
      const uint32_t seq = rec.image.seq;
      EXPECT_EQ(seq, is_depth ? depth_n : rgb_n);
      ASSERT_EQ(rec.image.pixels.size(), static_cast<size_t>(kW * kH * (is_depth ? 2 : 3)));
      size_t bad = 0;
      for (size_t k = 0; k < rec.image.pixels.size(); ++k)
        bad += rec.image.pixels[k] != pixel(seq, k, is_depth);
      EXPECT_EQ(bad, 0u);
      ++(is_depth ? depth_n : rgb_n);
    }
  }
  EXPECT_EQ(imu, n_imu);
  EXPECT_EQ(rgb_n, n_cam);
  EXPECT_EQ(depth_n, n_cam);
  EXPECT_EQ(ev, 1u);
  EXPECT_TRUE(r.problems().empty());
}

TEST(KlogLogger, OversizeFramesAndFullPoolAreCountedNotBlocking) {
  const std::string path = temp_dir("klog_logger_full") + "/full.klog";
  drivers::KlogLogger::Options o;
  o.max_image_bytes = 64;
  drivers::KlogLogger logger(path, fixture_rig(), o);
  std::vector<uint8_t> px(100, 1);
  EXPECT_FALSE(
      logger.log_image(RecordType::kRgb, 0, 0, 0, 0, ImageView{10, 10, 10, PixelFormat::kGray8, px.data()}));
  EXPECT_TRUE(
      logger.log_image(RecordType::kRgb, 1, 1, 1, 0, ImageView{8, 8, 10, PixelFormat::kGray8, px.data()}));
  EXPECT_FALSE(
      logger.log_image(RecordType::kImu, 2, 2, 2, 0, ImageView{8, 8, 8, PixelFormat::kGray8, px.data()}));
  logger.stop();
  EXPECT_EQ(logger.stats().image_drops, 2u);
  EXPECT_EQ(logger.stats().records_written, 1u);
  EXPECT_THROW(drivers::KlogLogger(temp_dir("klog_logger_full") + "/no/such/dir/x.klog", fixture_rig()),
               std::runtime_error);
}

// The config's `threads: kst-log:` reaches the logger thread; a CPU the
// process may not use is reported, and the logger runs anyway.
TEST(KlogLogger, ThreadSpecIsAppliedAndReported) {
  const std::string path = temp_dir("klog_logger_thread") + "/t.klog";
  drivers::KlogLogger::Options o;
  o.thread = rt::ThreadSpec{"kst-log", 0, 4095, 0};
  drivers::KlogLogger logger(path, fixture_rig(), o);
  EXPECT_STREQ(logger.thread_spec().name, "kst-log");
  EXPECT_TRUE(logger.thread_report().name_set);
  EXPECT_FALSE(logger.thread_report().pinned);
  EXPECT_FALSE(logger.thread_report().fully_granted());
  ImuSample s{};
  s.t_ns = 1;
  EXPECT_TRUE(logger.log_imu(s));
  logger.stop();
  EXPECT_EQ(logger.stats().records_written, 1u);
}

}  // namespace
}  // namespace kestrel::test
