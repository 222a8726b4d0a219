// KlogLogger's image staging byte ring: frames of different sizes wrap
// around a small ring many times and read back bit-exact; a frame that finds
// no space is refused and counted, never blocks; the sizing helper.
#include <gtest/gtest.h>

#include <filesystem>
#include <thread>
#include <vector>

#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/klog_logger.hpp"

namespace kestrel::drivers {
namespace {

uint8_t pattern(uint32_t seq, size_t k) {
  return static_cast<uint8_t>((k * 131 + seq * 17 + (k >> 9)) & 0xff);
}

Rig small_rig() {
  Rig rig;
  rig.name = "staging";
  rig.rgb.width = 64;
  rig.rgb.height = 48;
  rig.rgb.fx = rig.rgb.fy = 50;
  return rig;
}

TEST(KlogLoggerStaging, FramesWrapAroundTheRingAndReadBackExact) {
  const auto path =
      std::filesystem::temp_directory_path() / ("kestrel_staging_" + std::to_string(::getpid()) + ".klog");
  constexpr int kW = 64, kH = 48;
  const size_t rgb_bytes = kW * kH * 3, depth_bytes = kW * kH * 2;
  KlogLogger::Options o;
  o.max_image_bytes = rgb_bytes;
  // Room for two and a half frames, an odd size: every few frames one does
  // not fit before the end and starts over at the beginning.
  o.buffer_bytes = 2 * rgb_bytes + depth_bytes / 2 + 7;
  KlogLogger logger(path.string(), small_rig(), o);
  std::vector<uint8_t> px(rgb_bytes);
  constexpr uint32_t kFrames = 200;
  uint64_t refused = 0;
  for (uint32_t seq = 0; seq < kFrames; ++seq) {
    const bool depth = seq % 3 == 2;
    const size_t n = depth ? depth_bytes : rgb_bytes;
    for (size_t k = 0; k < n; ++k) px[k] = pattern(seq, k);
    const ImageView v = depth ? ImageView{kW, kH, kW * 2, PixelFormat::kDepthU16, px.data()}
                              : ImageView{kW, kH, kW * 3, PixelFormat::kRgb8, px.data()};
    // A full ring refuses at once; this test producer then waits for the logger.
    while (!logger.log_image(depth ? RecordType::kDepth : RecordType::kRgb, seq, seq, seq, 0, v)) {
      ++refused;
      std::this_thread::sleep_for(std::chrono::microseconds(200));
    }
  }
  logger.stop();
  const auto st = logger.stats();
  EXPECT_EQ(st.records_written, kFrames);
  EXPECT_EQ(st.image_drops, refused);  // each refusal counted
  EXPECT_LE(st.staging_peak_bytes, o.buffer_bytes);
  EXPECT_EQ(st.staging_bytes, o.buffer_bytes);
  std::printf(
      "[ figure ] %u frames through a %.1f-frame ring: %llu refusals while full, peak %zu of %zu bytes\n",
      kFrames, static_cast<double>(o.buffer_bytes) / rgb_bytes, (unsigned long long)refused,
      st.staging_peak_bytes, st.staging_bytes);

  KlogReader r(path.string());
  LogRecord rec;
  uint32_t seq = 0;
  size_t bad = 0;
  while (r.next(rec)) {
    ASSERT_EQ(rec.image.seq, seq);
    const bool depth = seq % 3 == 2;
    EXPECT_EQ(rec.type, depth ? RecordType::kDepth : RecordType::kRgb);
    ASSERT_EQ(rec.image.pixels.size(), depth ? depth_bytes : rgb_bytes);
    for (size_t k = 0; k < rec.image.pixels.size(); ++k) bad += rec.image.pixels[k] != pattern(seq, k);
    ++seq;
  }
  EXPECT_EQ(seq, kFrames);
  EXPECT_EQ(bad, 0u);
  EXPECT_TRUE(r.problems().empty());
  std::filesystem::remove(path);
}

TEST(KlogLoggerStaging, SizingHelperCoversTheStallPlusOneFrame) {
  // 4 s of 30 Hz VGA RGB + depth: 120 frames plus one for the unused tail.
  EXPECT_EQ(KlogLogger::staging_bytes_for(4.0, 30.0, 921600, 614400), 121u * 1536000u);
  EXPECT_EQ(KlogLogger::staging_bytes_for(0.0, 30.0, 100, 50), 150u);
  EXPECT_EQ(KlogLogger::staging_bytes_for(1.01, 10.0, 100, 0), 1200u);  // partial frames round up
}

TEST(KlogLoggerStaging, DefaultStagingIsSixtyFourLargestFrames) {
  const auto path = std::filesystem::temp_directory_path() /
                    ("kestrel_staging_default_" + std::to_string(::getpid()) + ".klog");
  KlogLogger::Options o;
  o.max_image_bytes = 1000;
  KlogLogger logger(path.string(), small_rig(), o);
  logger.stop();
  EXPECT_EQ(logger.stats().staging_bytes, 64000u);
  std::filesystem::remove(path);
}

}  // namespace
}  // namespace kestrel::drivers
