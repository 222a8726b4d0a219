// What the .klog image compression costs and buys, per codec, level and
// pre-filter, on VGA RGB-D frames of two kinds: `kestrel sim` renders (the
// default hover scene with its pixel noise) and real Kinect frames (7-Scenes,
// ../shared/data). Label bench; docs/log-format.md quotes its table and the
// default chosen on it. KESTREL_BENCH_FRAMES overrides the 30 frame pairs.
//
// Times are the calling thread's CPU time (what the logger thread would
// spend), encode = pre-filter + codec, decode = codec + inverse filter.
#include <gtest/gtest.h>

#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/klog_image_codec.hpp"
#include "kestrel/tools/simulator.hpp"
#include "test_data.hpp"

namespace kestrel::test {
namespace {

namespace klog = drivers::klog;

double cpu_s() {
  timespec t{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) + t.tv_nsec * 1e-9;
}

struct Pairs {
  std::string name;
  std::vector<drivers::LogImage> rgb, depth;
};

int frames_wanted() {
  const char* env = std::getenv("KESTREL_BENCH_FRAMES");
  return env ? std::max(1, std::atoi(env)) : 30;
}

Pairs sim_pairs(int n, bool noise) {
  Pairs p;
  p.name = noise ? "sim (kestrel sim hover, VGA)" : "sim without noise (kestrel sim hover --no-noise, VGA)";
  const std::string dir = temp_dir("klogz_bench_sim");
  tools::SimOptions o;
  o.scenario = "hover";
  o.duration_s = (n + 2) / 30.0;
  o.seed = 1;
  o.out_path = dir + "/hover.klog";
  o.image_compression.codec = klog::ImageCodec::kRaw;
  o.noise = noise;
  tools::run_simulation(o);
  drivers::KlogReader r(o.out_path);
  drivers::LogRecord rec;
  while (r.next(rec) && static_cast<int>(p.depth.size()) < n) {
    if (rec.type == drivers::RecordType::kRgb) p.rgb.push_back(rec.image);
    if (rec.type == drivers::RecordType::kDepth && p.depth.size() < p.rgb.size())
      p.depth.push_back(rec.image);
  }
  p.rgb.resize(p.depth.size());
  return p;
}

Pairs real_pairs(int n) {
  Pairs p;
  p.name = "real (7-Scenes Kinect, VGA)";
  const std::string dir = shared_path("real-rgbd/7scenes_first500");
  const int step = std::max(1, 500 / n);
  for (int i = 0; i < 500 && static_cast<int>(p.rgb.size()) < n; i += step) {
    char name[64];
    std::snprintf(name, sizeof name, "/frame-%06d.color.jpg", i);
    cv::Mat bgr = cv::imread(dir + name, cv::IMREAD_COLOR), rgb;
    std::snprintf(name, sizeof name, "/frame-%06d.depth.png", i);
    cv::Mat depth = cv::imread(dir + name, cv::IMREAD_UNCHANGED);
    if (bgr.empty() || depth.type() != CV_16UC1) continue;
    cv::cvtColor(bgr, rgb, cv::COLOR_BGR2RGB);
    drivers::LogImage a;
    a.width = rgb.cols;
    a.height = rgb.rows;
    a.format = PixelFormat::kRgb8;
    a.pixels.assign(rgb.data, rgb.data + rgb.total() * 3);
    drivers::LogImage d;
    d.width = depth.cols;
    d.height = depth.rows;
    d.format = PixelFormat::kDepthU16;
    d.pixels.resize(depth.total() * 2);
    for (size_t k = 0; k < depth.total(); ++k) {
      uint16_t v = depth.at<uint16_t>(static_cast<int>(k));
      if (v == 65535) v = 0;  // as the 7-Scenes reader gives it
      d.pixels[2 * k] = static_cast<uint8_t>(v & 0xff);
      d.pixels[2 * k + 1] = static_cast<uint8_t>(v >> 8);
    }
    p.rgb.push_back(std::move(a));
    p.depth.push_back(std::move(d));
  }
  return p;
}

struct Cost {
  double raw = 0, stored = 0, enc_s = 0, dec_s = 0;
  bool identical = true;
};

Cost measure(const std::vector<drivers::LogImage>& images, const klog::ImageCompression& c) {
  Cost k;
  klog::ImageEncoder enc;
  klog::ImageDecoder dec;
  enc.set_compression(c);
  std::string out;
  std::vector<uint8_t> back;
  for (int rep = 0; rep < 2; ++rep)  // the first pass sizes buffers and contexts
    for (const auto& img : images) {
      out.clear();
      klog::ImageCodec codec{};
      klog::ImageFilter filter{};
      const double t0 = cpu_s();
      enc.encode(img.view(), out, codec, filter);
      const double t1 = cpu_s();
      back.assign(img.pixels.size(), 0);
      std::string why;
      const bool ok = dec.decode(codec, filter, img.format, img.width, img.height,
                                 reinterpret_cast<const uint8_t*>(out.data()), out.size(), back.data(), why);
      const double t2 = cpu_s();
      if (rep == 0) continue;
      k.identical = k.identical && ok && back == img.pixels;
      k.raw += static_cast<double>(img.pixels.size());
      k.stored += static_cast<double>(out.size());
      k.enc_s += t1 - t0;
      k.dec_s += t2 - t1;
    }
  return k;
}

TEST(KlogCompressionBench, CodecsLevelsAndPreFilterOnVgaRgbd) {
  KESTREL_REQUIRE_SHARED("real-rgbd/7scenes_first500");
  const int n = frames_wanted();
  std::vector<klog::ImageCompression> configs;
  auto add = [&](klog::ImageCodec codec, int level, bool prefilter) {
    klog::ImageCompression c;
    c.codec = codec;
    c.zstd_level = level;
    c.prefilter = prefilter;
    configs.push_back(c);
  };
  add(klog::ImageCodec::kLz4, 0, false);
  add(klog::ImageCodec::kLz4, 0, true);
  for (int level : {-3, 1, 3}) {
    add(klog::ImageCodec::kZstd, level, false);
    add(klog::ImageCodec::kZstd, level, true);
  }
  for (const Pairs& p : {sim_pairs(n, true), sim_pairs(n, false), real_pairs(n)}) {
    ASSERT_EQ(static_cast<int>(p.rgb.size()), n) << p.name;
    const double raw_pair = static_cast<double>(p.rgb[0].pixels.size() + p.depth[0].pixels.size());
    std::printf("[ figure ] %s, %d frame pairs; raw %.1f MB per 10 s at 30 Hz\n", p.name.c_str(), n,
                raw_pair * 300 / 1e6);
    std::printf("  %-32s %7s %7s %9s %8s %8s %8s %8s %10s\n", "codec", "rgb x", "depth x", "MB/10s", "share",
                "enc rgb", "enc dep", "dec pair", "enc MB/s");
    for (const auto& c : configs) {
      const Cost rgb = measure(p.rgb, c);
      const Cost depth = measure(p.depth, c);
      EXPECT_TRUE(rgb.identical && depth.identical) << klog::describe(c) << " did not round-trip " << p.name;
      const double stored_pair = (rgb.stored + depth.stored) / n;
      std::printf("  %-32s %7.2f %7.2f %9.1f %8.3f %6.2fms %6.2fms %6.2fms %10.0f\n",
                  klog::describe(c).c_str(), rgb.raw / rgb.stored, depth.raw / depth.stored,
                  stored_pair * 300 / 1e6, stored_pair / raw_pair, rgb.enc_s / n * 1e3, depth.enc_s / n * 1e3,
                  (rgb.dec_s + depth.dec_s) / n * 1e3,
                  (rgb.raw + depth.raw) / (rgb.enc_s + depth.enc_s) / 1e6);
    }
  }
}

}  // namespace
}  // namespace kestrel::test
