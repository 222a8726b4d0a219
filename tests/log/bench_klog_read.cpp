// Throughput of writing and reading a VGA RGB-D + 400 Hz IMU klog.
// Label bench (not in the default run): 60 s of data is ~2.8 GB on disk.
// KESTREL_BENCH_SECONDS overrides the duration.
#include <gtest/gtest.h>

#include <chrono>
#include <cstdlib>
#include <filesystem>

#include "kestrel/drivers/klog.hpp"
#include "log_fixtures.hpp"
#include "test_data.hpp"

namespace kestrel::test {
namespace {

using Clock = std::chrono::steady_clock;
double secs(Clock::time_point a, Clock::time_point b) { return std::chrono::duration<double>(b - a).count(); }

TEST(KlogBench, ReadsVgaRgbdLogStreaming) {
  const char* env = std::getenv("KESTREL_BENCH_SECONDS");
  const double seconds = env ? std::atof(env) : 60.0;
  const std::string path = temp_dir("klog_bench") + "/rgbd.klog";
  constexpr int kW = 640, kH = 480;
  std::vector<uint8_t> rgb(kW * kH * 3), depth(kW * kH * 2);
  for (size_t k = 0; k < rgb.size(); ++k) rgb[k] = static_cast<uint8_t>(k * 13);
  for (size_t k = 0; k < depth.size(); ++k) depth[k] = static_cast<uint8_t>(k * 5);
  size_t frames = 0, imu = 0;
  const auto t0 = Clock::now();
  {
    drivers::KlogWriter w;
    // Raw images: this measures the file layer (bench_log_klog_compression the codecs).
    drivers::KlogWriter::Options raw;
    raw.compression.codec = drivers::klog::ImageCodec::kRaw;
    w.open(path, fixture_rig(), raw);
    int64_t next_cam = 0;
    for (int64_t t = 0; t < static_cast<int64_t>(seconds * 1e9); t += 2'500'000) {
      ImuSample s = fixture_imu(static_cast<uint32_t>(imu++));
      s.t_ns = t;
      w.write_imu(s);
      if (t >= next_cam) {
        w.write_image(drivers::RecordType::kRgb, t, t, static_cast<uint32_t>(frames), 0,
                      ImageView{kW, kH, kW * 3, PixelFormat::kRgb8, rgb.data()});
        w.write_image(drivers::RecordType::kDepth, t, t, static_cast<uint32_t>(frames), 0,
                      ImageView{kW, kH, kW * 2, PixelFormat::kDepthU16, depth.data()});
        ++frames;
        next_cam += 33'333'333;
      }
    }
  }
  const auto t1 = Clock::now();
  const double bytes = static_cast<double>(std::filesystem::file_size(path));
  drivers::KlogReader r(path);
  drivers::LogRecord rec;
  size_t n = 0, images = 0;
  uint64_t sum = 0;
  while (r.next(rec)) {
    ++n;
    if (rec.type != drivers::RecordType::kImu) {
      ++images;
      sum += rec.image.pixels[rec.image.pixels.size() / 2];
    }
  }
  const auto t2 = Clock::now();
  EXPECT_EQ(images, 2 * frames);
  EXPECT_EQ(n, imu + 2 * frames);
  EXPECT_TRUE(r.problems().empty());
  std::printf("klog bench: %.0f s of data, %zu frame pairs, %zu IMU, %.2f GB\n", seconds, frames, imu,
              bytes / 1e9);
  std::printf("  write %.2f s (%.0f MB/s), read %.2f s (%.0f MB/s, %.0f records/s) [checksum %llu]\n",
              secs(t0, t1), bytes / 1e6 / secs(t0, t1), secs(t1, t2), bytes / 1e6 / secs(t1, t2),
              n / secs(t1, t2), static_cast<unsigned long long>(sum));
  std::filesystem::remove(path);
}

}  // namespace
}  // namespace kestrel::test
