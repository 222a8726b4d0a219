// `kestrel run`: live drivers into the sensor rings, consumed by an
// estimator thread. Until the full pipeline is wired here, the consumer runs
// the IMU dead-reckoning backend and says so.
#include <atomic>
#include <csignal>
#include <cstdio>
#include <memory>
#include <string>
#include <thread>

#include "kestrel/commands.hpp"
#include "kestrel/core/estimator.hpp"
#include "kestrel/drivers/devices.hpp"
#include "kestrel/drivers/sensor_rings.hpp"
#include "kestrel/rt/clock.hpp"

namespace kestrel::cli {
namespace {

std::atomic<bool> g_run_stop{false};
extern "C" void run_on_signal(int) { g_run_stop.store(true); }

class RingFrameSink final : public drivers::FrameSink {
 public:
  explicit RingFrameSink(drivers::SensorRings& r) : rings_(r) {}
  bool push_frame(const drivers::CameraFrame& f) noexcept override {
    RgbdFrameMsg m;
    m.t_ns = f.t_ns;
    m.t_recv_ns = f.t_recv_ns;
    m.seq = f.seq;
    m.exposure_us = f.exposure_us;
    if (!copy(*f.rgb, m.rgb_handle)) return drop();
    if (f.depth != nullptr && !copy(*f.depth, m.depth_handle)) {
      rings_.images.release(m.rgb_handle);
      return drop();
    }
    if (rings_.frames.try_push(m)) return true;
    rings_.images.release(m.rgb_handle);
    if (m.depth_handle != rt::kInvalidHandle) rings_.images.release(m.depth_handle);
    return false;
  }
  uint64_t drops = 0;

 private:
  bool drop() {
    ++drops;
    return false;
  }
  bool copy(const drivers::ImageBuffer& src, uint32_t& handle) {
    handle = rings_.images.acquire();
    if (handle == rt::kInvalidHandle) return false;
    drivers::ImageBuffer* dst = rings_.images.get(handle);
    if (dst == nullptr || src.pixels.size() > dst->pixels.capacity()) {
      rings_.images.release(handle);
      handle = rt::kInvalidHandle;
      return false;
    }
    dst->t_ns = src.t_ns;
    dst->width = src.width;
    dst->height = src.height;
    dst->format = src.format;
    dst->pixels.assign(src.pixels.begin(), src.pixels.end());   // within capacity: no allocation
    return true;
  }
  drivers::SensorRings& rings_;
};

struct RunArgs {
  std::string config;
  double duration_s = 0;
};

}  // namespace

Subcommand add_run_command(CLI::App& parent) {
  auto a = std::make_shared<RunArgs>();
  CLI::App* app = parent.add_subcommand("run", "start the live drivers and the estimator");
  app->add_option("--config", a->config, "rig + drivers config (configs/*.yaml)")->required();
  app->add_option("--duration", a->duration_s, "seconds to run (0 = until Ctrl-C)")->capture_default_str();
  app->footer("Runs: live drivers -> sensor rings -> estimator thread (currently the IMU dead-reckoning backend;\n"
              "the visual pipeline is wired by the lead). Without the sensors it exits with 1 naming what is missing.");
  Subcommand s;
  s.app = app;
  s.run = [a] {
    const drivers::LiveConfig cfg = drivers::load_live_config(a->config);
    drivers::LiveSensors sensors(cfg);
    const size_t max_image = static_cast<size_t>(cfg.drivers.camera.width_px) * cfg.drivers.camera.height_px * 3;
    auto rings = std::make_unique<drivers::SensorRings>(max_image);
    drivers::RingImuSink<decltype(rings->imu)> imu(rings->imu);
    RingFrameSink frames(*rings);
    std::unique_ptr<core::Estimator> est = core::make_estimator("imu", cfg.rig);
    std::printf("running %s -> estimator '%s' (IMU dead reckoning only: the visual pipeline is not wired into "
                "`kestrel run` yet)\n", sensors.description().c_str(), est->name());
    g_run_stop.store(false);
    std::signal(SIGINT, run_on_signal);
    std::signal(SIGTERM, run_on_signal);
    std::atomic<bool> consumer_stop{false};
    uint64_t frames_seen = 0;
    std::thread consumer([&] {
      while (!consumer_stop.load(std::memory_order_relaxed)) {
        bool any = false;
        ImuSample s;
        while (rings->imu.try_pop(s)) {
          est->add_imu(s);
          any = true;
        }
        RgbdFrameMsg m;
        while (rings->frames.try_pop(m)) {
          core::RgbdFrame f;
          f.t_ns = m.t_ns;
          f.seq = m.seq;
          if (const auto* b = rings->images.get(m.rgb_handle)) f.rgb = b->view();
          if (const auto* b = rings->images.get(m.depth_handle)) f.depth = b->view();
          est->add_frame(f);
          rings->images.release(m.rgb_handle);
          if (m.depth_handle != rt::kInvalidHandle) rings->images.release(m.depth_handle);
          ++frames_seen;
          any = true;
        }
        if (!any) rt::sleep_for_ns(1'000'000);
      }
    });
    const int64_t t0 = rt::now_ns();
    sensors.start(imu, frames);
    int64_t next_print = t0 + 1'000'000'000;
    while (!g_run_stop.load() && (a->duration_s <= 0 || rt::now_ns() - t0 < static_cast<int64_t>(a->duration_s * 1e9))) {
      rt::sleep_for_ns(100'000'000);
      if (rt::now_ns() >= next_print) {
        next_print += 1'000'000'000;
        const auto& c = est->counters();
        std::printf("t=%5.1f s  imu %llu  frames %llu  ring drops imu %llu frames %llu\n", (rt::now_ns() - t0) * 1e-9,
                    (unsigned long long)c.imu_in, (unsigned long long)frames_seen,
                    (unsigned long long)rings->imu.drops(), (unsigned long long)(rings->frames.drops() + frames.drops));
      }
    }
    sensors.stop();
    consumer_stop.store(true);
    consumer.join();
    std::signal(SIGINT, SIG_DFL);
    std::signal(SIGTERM, SIG_DFL);
    std::printf("%s", sensors.report().c_str());
    return 0;
  };
  return s;
}

}  // namespace kestrel::cli
