// Compressed recordings end to end: `kestrel sim` and `kestrel convert` write
// compressed .klog images as the options say; a compressed log replays the
// same images and the same lockstep trajectory as the same log raw; the live
// config's `record:` section chooses the logger's compression.
#include <gtest/gtest.h>
#include <unistd.h>

#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>

#include "kestrel/drivers/devices.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/tools/config_file.hpp"
#include "run_command.hpp"
#include "test_data.hpp"

namespace fs = std::filesystem;

namespace {

using kestrel::test::CmdResult;
namespace drivers = kestrel::drivers;
CmdResult run(const std::string& args) { return kestrel::test::run_kestrel(args); }

std::string slurp(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  std::ostringstream s;
  s << f.rdbuf();
  return s.str();
}

bool same_bits(const void* a, const void* b, size_t n) { return std::memcmp(a, b, n) == 0; }

// Every record of two logs equal, field by field and pixel by pixel (the
// offsets differ: the compressed records are shorter).
void expect_same_records(const std::string& a_path, const std::string& b_path, size_t* images) {
  drivers::KlogReader a(a_path), b(b_path);
  drivers::LogRecord ra, rb;
  size_t n = 0;
  *images = 0;
  for (;;) {
    const bool ha = a.next(ra), hb = b.next(rb);
    ASSERT_EQ(ha, hb) << "record " << n;
    if (!ha) break;
    ++n;
    ASSERT_EQ(ra.type, rb.type) << "record " << n;
    switch (ra.type) {
      case drivers::RecordType::kImu:
        EXPECT_EQ(ra.imu.t_ns, rb.imu.t_ns);
        EXPECT_TRUE(same_bits(&ra.imu.gyro_rps, &rb.imu.gyro_rps, sizeof ra.imu.gyro_rps));
        EXPECT_TRUE(same_bits(&ra.imu.acc_mps2, &rb.imu.acc_mps2, sizeof ra.imu.acc_mps2));
        break;
      case drivers::RecordType::kRgb:
      case drivers::RecordType::kDepth:
      case drivers::RecordType::kRight:
        ++*images;
        EXPECT_EQ(ra.image.t_ns, rb.image.t_ns);
        EXPECT_EQ(ra.image.seq, rb.image.seq);
        EXPECT_EQ(ra.image.width, rb.image.width);
        EXPECT_EQ(ra.image.format, rb.image.format);
        EXPECT_TRUE(ra.image.pixels == rb.image.pixels) << "image record " << n << " differs";
        break;
      case drivers::RecordType::kGroundTruth:
        EXPECT_EQ(ra.gt.t_ns, rb.gt.t_ns);
        break;
      case drivers::RecordType::kEvent:
        EXPECT_EQ(ra.event.text, rb.event.text);
        break;
    }
  }
  EXPECT_TRUE(a.problems().empty());
  EXPECT_TRUE(b.problems().empty());
}

TEST(CliKlogCompression, CompressedLogReplaysTheSameImagesAndLockstepTrajectoryAsRaw) {
  const std::string dir = kestrel::test::temp_dir("cli_klogz");
  const std::string sim = "sim --scenario figure8 --duration 5 --seed 4 --width 320 --height 240 ";
  const CmdResult r0 = run(sim + "--image-codec none --out " + dir + "/raw.klog");
  const CmdResult r1 = run(sim + "--out " + dir + "/zstd.klog");  // the default compression
  const CmdResult r2 = run(sim + "--image-codec lz4 --out " + dir + "/lz4.klog");
  ASSERT_EQ(r0.code, 0) << r0.out;
  ASSERT_EQ(r1.code, 0) << r1.out;
  ASSERT_EQ(r2.code, 0) << r2.out;
  const auto raw_bytes = fs::file_size(dir + "/raw.klog");
  const auto zstd_bytes = fs::file_size(dir + "/zstd.klog");
  const auto lz4_bytes = fs::file_size(dir + "/lz4.klog");
  std::printf("[ figure ] sim figure8 320x240 5 s: raw %.1f MB, zstd %.1f MB (%.3f), lz4 %.1f MB (%.3f)\n",
              raw_bytes / 1e6, zstd_bytes / 1e6, double(zstd_bytes) / raw_bytes, lz4_bytes / 1e6,
              double(lz4_bytes) / raw_bytes);
  EXPECT_LT(zstd_bytes * 10, raw_bytes * 7);
  EXPECT_LT(lz4_bytes, raw_bytes);
  EXPECT_EQ(drivers::KlogReader(dir + "/raw.klog").version(), drivers::kKlogVersion);

  size_t images = 0;
  expect_same_records(dir + "/raw.klog", dir + "/zstd.klog", &images);
  EXPECT_GT(images, 200u);
  expect_same_records(dir + "/raw.klog", dir + "/lz4.klog", &images);

  // The estimator sees the same bytes, so not one pose may differ.
  std::string traj[3];
  const char* names[3] = {"raw", "zstd", "lz4"};
  for (int k = 0; k < 3; ++k) {
    const CmdResult r = run("replay " + dir + "/" + names[k] + ".klog --pace lockstep --traj-out " + dir +
                            "/" + names[k] + ".txt -q");
    ASSERT_EQ(r.code, 0) << r.out;
    traj[k] = slurp(dir + "/" + names[k] + ".txt");
  }
  EXPECT_GT(traj[0].size(), 1000u);
  EXPECT_EQ(traj[0], traj[1]);
  EXPECT_EQ(traj[0], traj[2]);

  // convert re-encodes either way without changing a pixel.
  const CmdResult c = run("convert " + dir + "/zstd.klog --out " + dir + "/back.klog --image-codec none -q");
  ASSERT_EQ(c.code, 0) << c.out;
  EXPECT_GE(fs::file_size(dir + "/back.klog"), raw_bytes - raw_bytes / 100);
  expect_same_records(dir + "/raw.klog", dir + "/back.klog", &images);
  const CmdResult c2 = run("convert " + dir + "/raw.klog --out " + dir + "/z3.klog --zstd-level 3 -q");
  ASSERT_EQ(c2.code, 0) << c2.out;
  EXPECT_LT(fs::file_size(dir + "/z3.klog"), raw_bytes);
  expect_same_records(dir + "/raw.klog", dir + "/z3.klog", &images);
}

TEST(CliKlogCompression, BadCompressionOptionsAreUsageErrors) {
  const std::string dir = kestrel::test::temp_dir("cli_klogz_bad");
  const CmdResult a =
      run("sim --duration 1 --width 64 --height 48 --image-codec brotli --out " + dir + "/a.klog");
  EXPECT_EQ(a.code, 2) << a.out;
  EXPECT_NE(a.out.find("--image-codec"), std::string::npos) << a.out;
  const CmdResult b = run("sim --duration 1 --width 64 --height 48 --zstd-level 99 --out " + dir + "/b.klog");
  EXPECT_EQ(b.code, 2) << b.out;
  EXPECT_NE(b.out.find("--zstd-level"), std::string::npos) << b.out;
}

std::string config_with(const std::string& record_section) {
  return slurp(std::string(KESTREL_SOURCE_DIR) + "/configs/openni2_bmx055_i2c.yaml") + "\n" + record_section;
}

TEST(CliKlogCompression, RecordSectionChoosesTheLoggersCompression) {
  const drivers::LiveConfig def = kestrel::tools::live_config_from_yaml(config_with(""), "c.yaml");
  EXPECT_EQ(def.record.compression.codec, drivers::klog::ImageCodec::kZstd);
  EXPECT_EQ(def.record.compression.zstd_level, 1);
  const drivers::LiveConfig lz =
      kestrel::tools::live_config_from_yaml(config_with("record:\n  image_codec: lz4\n"), "c.yaml");
  EXPECT_EQ(lz.record.compression.codec, drivers::klog::ImageCodec::kLz4);
  const drivers::LiveConfig z3 = kestrel::tools::live_config_from_yaml(
      config_with("record:\n  image_codec: zstd\n  zstd_level: 3\n"), "c.yaml");
  EXPECT_EQ(z3.record.compression.zstd_level, 3);
  const drivers::LiveConfig off =
      kestrel::tools::live_config_from_yaml(config_with("record:\n  image_codec: none\n"), "c.yaml");
  EXPECT_EQ(off.record.compression.codec, drivers::klog::ImageCodec::kRaw);
  auto error = [](const std::string& text) {
    try {
      kestrel::tools::live_config_from_yaml(config_with(text), "c.yaml");
    } catch (const std::runtime_error& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(error("record:\n  image_codec: png\n")
                .find("c.yaml: record.image_codec: expected one of zstd, lz4, none"),
            std::string::npos);
  EXPECT_NE(error("record:\n  zstd_level: 40\n").find("c.yaml: record.zstd_level"), std::string::npos)
      << error("record:\n  zstd_level: 40\n");
  EXPECT_NE(error("record:\n  level: 3\n").find("c.yaml: record.level: unknown key"), std::string::npos)
      << error("record:\n  level: 3\n");
}

}  // namespace
