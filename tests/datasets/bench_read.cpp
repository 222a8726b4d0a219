// Replay speed of each dataset reader against the .klog reader on the same
// content (label bench). KESTREL_BENCH_SECONDS sets the length (default 10 s
// of 640x480 RGB + depth at 30 Hz, IMU at 400 Hz, ground truth at 100 Hz).
#include <gtest/gtest.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>

#include "dataset_fixtures.hpp"
#include "kestrel/drivers/dataset_logs.hpp"
#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/log_export.hpp"

namespace kestrel::test {
namespace {

using drivers::RecordType;

// A textured image that moves a little each frame: PNG compresses it like a real scene, not like noise or a
// flat wall.
drivers::LogImage frame(int64_t t_ns, uint32_t i, PixelFormat f) {
  drivers::LogImage img;
  img.t_ns = img.t_recv_ns = t_ns;
  img.seq = i;
  img.width = 640;
  img.height = 480;
  img.format = f;
  img.pixels.resize(640 * 480 * static_cast<size_t>(bytes_per_pixel(f)));
  uint32_t h = 2166136261u ^ i;
  for (int y = 0; y < 480; ++y)
    for (int x = 0; x < 640; ++x) {
      h = h * 16777619u ^ static_cast<uint32_t>(x);
      const int v = ((x + static_cast<int>(i) * 3) / 16 + y / 16) % 2 * 120 + static_cast<int>(h % 24);
      const size_t k = static_cast<size_t>(y) * 640 + x;
      if (f == PixelFormat::kDepthU16) {
        const uint16_t d = static_cast<uint16_t>(1000 + 4 * y + v);
        std::memcpy(img.pixels.data() + 2 * k, &d, 2);
      } else {
        for (int c = 0; c < 3; ++c) img.pixels[3 * k + c] = static_cast<uint8_t>(v + 40 * c);
      }
    }
  return img;
}

struct Speed {
  double seconds = 0;
  size_t frames = 0, records = 0;
};

Speed time_read(drivers::LogSource& s) {
  Speed sp;
  drivers::LogRecord r;
  s.rewind();
  const auto t0 = std::chrono::steady_clock::now();
  while (s.next(r)) {
    ++sp.records;
    if (r.type == RecordType::kRgb) ++sp.frames;
  }
  sp.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return sp;
}

TEST(BenchDatasets, ReplaySpeedPerReaderAgainstKlog) {
  const char* env = std::getenv("KESTREL_BENCH_SECONDS");
  const double seconds = env ? std::atof(env) : 10.0;
  const int frames = static_cast<int>(seconds * 30);
  const std::string dir = temp_dir("bench_datasets");
  Rig rig = small_rig();
  rig.rgb.width = 640, rig.rgb.height = 480, rig.rgb.fx = rig.rgb.fy = 525, rig.rgb.cx = 319.5,
  rig.rgb.cy = 239.5;
  rig.camera_rate_hz = 30;
  {
    drivers::KlogWriter w;
    w.open(dir + "/a.klog", rig);
    const int n_imu = frames * 40 / 3;
    for (int i = 0; i < n_imu; ++i) {
      const ImuSample s = imu_at(static_cast<uint32_t>(i));
      w.write_imu(s);
      if (i % 4 == 0) w.write_ground_truth(gt_at(s.t_ns, static_cast<uint32_t>(i / 4)));
      if ((i * 3) % 40 < 3) {  // 30 Hz against 400 Hz
        const uint32_t f = static_cast<uint32_t>(i * 3 / 40);
        w.write_image(RecordType::kRgb, frame(s.t_ns, f, PixelFormat::kRgb8));
        w.write_image(RecordType::kDepth, frame(s.t_ns, f, PixelFormat::kDepthU16));
      }
    }
  }
  drivers::KlogReader klog(dir + "/a.klog");
  drivers::export_eth3d(klog, dir + "/eth3d");
  drivers::export_openloris(klog, dir + "/openloris");
  drivers::export_euroc(klog, dir + "/euroc");
  const bool bag = drivers::rosbag_built();
  if (bag) drivers::export_rosbag(klog, dir + "/a.bag");

  struct Case {
    const char* name;
    std::function<std::unique_ptr<drivers::LogSource>()> open;
  };
  const std::vector<Case> cases = {
      {"klog", [&] { return std::make_unique<drivers::KlogReader>(dir + "/a.klog"); }},
      {"eth3d", [&] { return std::make_unique<drivers::Eth3dReader>(dir + "/eth3d", &rig); }},
      {"openloris", [&] { return std::make_unique<drivers::OpenLorisReader>(dir + "/openloris"); }},
      {"euroc", [&] { return std::make_unique<drivers::EurocReader>(dir + "/euroc"); }},
      {"rosbag",
       [&]() -> std::unique_ptr<drivers::LogSource> {
         if (!bag) return nullptr;
         return std::make_unique<drivers::RosbagReader>(dir + "/a.bag", drivers::RosbagTopics{}, &rig);
       }},
  };
  std::printf(
      "replay read speed, %d frames 640x480 RGB + depth, IMU 400 Hz (files in the page cache, second pass)\n",
      frames);
  std::printf("%-10s %10s %12s %12s %10s\n", "reader", "open s", "read s", "frames/s", "vs klog");
  double klog_fps = 0;
  for (const auto& c : cases) {
    const auto t0 = std::chrono::steady_clock::now();
    auto src = c.open();
    const double open_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (!src) {
      std::printf("%-10s not built\n", c.name);
      continue;
    }
    time_read(*src);  // first pass warms the page cache
    const Speed sp = time_read(*src);
    EXPECT_EQ(sp.frames, static_cast<size_t>(frames)) << c.name;
    const double fps = sp.frames / sp.seconds;
    if (std::string(c.name) == "klog") klog_fps = fps;
    std::printf("%-10s %10.3f %12.3f %12.1f %9.2fx\n", c.name, open_s, sp.seconds, fps,
                klog_fps > 0 ? fps / klog_fps : 0);
  }
}

}  // namespace
}  // namespace kestrel::test
