// Recording throughput: a synthetic rig at real-time pace — VGA RGB + depth at
// 30 Hz (46 MB/s) and IMU at 400 Hz, one producer thread per stream as the
// live drivers have — through KlogLogger into a file. Zero drops required.
// The default run covers 10 s; bench_drivers_record runs 60 s. The logger's
// image staging is sized for a 4 s disk stall (docs/drivers/README.md,
// "Recording"), as `kestrel record` sizes it.
#include <gtest/gtest.h>

#include <atomic>
#include <cstdio>
#include <filesystem>
#include <thread>
#include <vector>

#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/klog_logger.hpp"
#include "kestrel/rt/clock.hpp"

#ifndef KESTREL_RECORD_SECONDS
#define KESTREL_RECORD_SECONDS 10
#define KESTREL_RECORD_TEST RealTime10sVgaRgbdAndImuWithoutDrops
#endif

namespace kestrel::drivers {
namespace {

TEST(RecordThroughput, KESTREL_RECORD_TEST) {
  const double seconds = KESTREL_RECORD_SECONDS;
  const auto path = std::filesystem::temp_directory_path() /
                    ("kestrel_record_throughput_" + std::to_string(::getpid()) + ".klog");
  Rig rig;
  rig.name = "throughput";
  rig.rgb.width = 640;
  rig.rgb.height = 480;
  rig.rgb.fx = rig.rgb.fy = 500;
  KlogLogger::Options o;
  o.max_image_bytes = 640 * 480 * 3;
  o.buffer_bytes = KlogLogger::staging_bytes_for(4.0, 30.0, 640 * 480 * 3, 640 * 480 * 2);
  auto logger = std::make_unique<KlogLogger>(path.string(), rig, o);

  std::vector<uint8_t> rgb(640 * 480 * 3), depth(640 * 480 * 2);
  for (size_t i = 0; i < rgb.size(); ++i) rgb[i] = static_cast<uint8_t>(i * 7);
  for (size_t i = 0; i < depth.size(); ++i) depth[i] = static_cast<uint8_t>(i * 13);
  const ImageView rgb_view{640, 480, 640 * 3, PixelFormat::kRgb8, rgb.data()};
  const ImageView depth_view{640, 480, 640 * 2, PixelFormat::kDepthU16, depth.data()};

  const int64_t t0 = rt::now_ns() + 10'000'000;
  const auto n_imu = static_cast<int64_t>(seconds * 400);
  const auto n_cam = static_cast<int64_t>(seconds * 30);
  std::atomic<uint64_t> imu_fail{0}, cam_fail{0};
  int64_t worst_cam_call_ns = 0;
  std::thread imu([&] {
    for (int64_t k = 0; k < n_imu; ++k) {
      const int64_t t = t0 + k * 2'500'000;
      rt::sleep_until_ns(t);
      ImuSample s;
      s.t_ns = t;
      s.t_recv_ns = rt::now_ns();
      s.seq = static_cast<uint32_t>(k);
      s.acc_mps2 = {0, 0, 9.81};
      if (!logger->log_imu(s)) ++imu_fail;
    }
  });
  std::thread cam([&] {
    for (int64_t k = 0; k < n_cam; ++k) {
      const int64_t t = t0 + k * 33'333'333;
      rt::sleep_until_ns(t);
      const int64_t a = rt::now_ns();
      if (!logger->log_image(RecordType::kRgb, t, a, static_cast<uint32_t>(k), 5000, rgb_view)) ++cam_fail;
      if (!logger->log_image(RecordType::kDepth, t, a, static_cast<uint32_t>(k), 5000, depth_view)) ++cam_fail;
      worst_cam_call_ns = std::max(worst_cam_call_ns, rt::now_ns() - a);
    }
  });
  imu.join();
  cam.join();
  const int64_t t_end = rt::now_ns();
  logger->stop();
  const KlogLogger::Stats st = logger->stats();
  const double mb = static_cast<double>(st.bytes_written) / 1e6;
  std::printf("[ figure ] record %.0f s real time: %llu records, %.1f MB (%.1f MB/s), drops imu %llu images %llu, "
              "worst producer call (rgb+depth copy) %.2f ms, staging peak %.1f of %.1f MB (%.2f s of images)\n",
              seconds, (unsigned long long)st.records_written, mb, mb / ((t_end - t0) * 1e-9),
              (unsigned long long)st.imu_drops, (unsigned long long)st.image_drops, worst_cam_call_ns * 1e-6,
              st.staging_peak_bytes / 1e6, st.staging_bytes / 1e6, st.staging_peak_bytes / (30.0 * 640 * 480 * 5));
  EXPECT_EQ(imu_fail.load(), 0u);
  EXPECT_EQ(cam_fail.load(), 0u);
  EXPECT_EQ(st.imu_drops + st.image_drops + st.records_lost_to_write_errors, 0u);
  EXPECT_EQ(st.records_written, static_cast<uint64_t>(n_imu + 2 * n_cam));
  EXPECT_TRUE(logger->error().empty()) << logger->error();

  // The file reads back whole.
  KlogReader reader(path.string());
  LogRecord rec;
  uint64_t imu_n = 0, img_n = 0;
  while (reader.next(rec)) (rec.type == RecordType::kImu ? imu_n : img_n)++;
  EXPECT_EQ(imu_n, static_cast<uint64_t>(n_imu));
  EXPECT_EQ(img_n, static_cast<uint64_t>(2 * n_cam));
  EXPECT_TRUE(reader.problems().empty());
  std::filesystem::remove(path);
}

}  // namespace
}  // namespace kestrel::drivers
