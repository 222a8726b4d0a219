// `kestrel run`: live drivers into the sensor rings, consumed by an
// estimator thread running the backend the config names (`estimator:
// backend:`, or --estimator; default vo). The estimator sees IMU and frames
// merged in time order, as in replay.
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
  std::string estimator;
  double duration_s = 0;
};

// A frame waits for the IMU up to its time at most this long (wall clock):
// an IMU that stopped must not stall the camera.
constexpr int64_t kFrameWaitForImuNs = 50'000'000;

}  // namespace

Subcommand add_run_command(CLI::App& parent) {
  auto a = std::make_shared<RunArgs>();
  CLI::App* app = parent.add_subcommand("run", "start the live drivers and the estimator");
  app->add_option("--config", a->config, "rig + drivers config (configs/*.yaml)")->required();
  app->add_option("--estimator", a->estimator,
                  std::string("backend: ") + core::estimator_names() +
                      " (default: the config's estimator.backend, else vo)");
  app->add_option("--duration", a->duration_s, "seconds to run (0 = until Ctrl-C)")->capture_default_str();
  app->footer("Runs: live drivers -> sensor rings -> estimator thread (IMU and frames in time order).\n"
              "Without the sensors it exits with 1 naming what is missing.");
  Subcommand s;
  s.app = app;
  s.run = [a] {
    const drivers::LiveConfig cfg = drivers::load_live_config(a->config);
    std::string backend = "vo";
    if (!a->estimator.empty()) {
      if (!core::estimator_known(a->estimator))
        throw UsageError("unknown --estimator '" + a->estimator + "' (expected one of: " + core::estimator_names() +
                         ")");
      backend = a->estimator;
    } else if (!cfg.estimator.backend.empty()) {
      if (!core::estimator_known(cfg.estimator.backend))
        throw std::runtime_error(a->config + ": estimator.backend: unknown backend '" + cfg.estimator.backend +
                                 "' (expected one of: " + core::estimator_names() + ")");
      backend = cfg.estimator.backend;
    }
    drivers::LiveSensors sensors(cfg);
    const size_t max_image = static_cast<size_t>(cfg.drivers.camera.width_px) * cfg.drivers.camera.height_px * 3;
    auto rings = std::make_unique<drivers::SensorRings>(max_image);
    drivers::RingImuSink<decltype(rings->imu)> imu(rings->imu);
    RingFrameSink frames(*rings);
    std::unique_ptr<core::Estimator> est = core::make_estimator(backend, cfg.rig);
    std::printf("running %s -> estimator '%s' (%s)\n", sensors.description().c_str(), est->name(),
                a->estimator.empty() && !cfg.estimator.backend.empty() ? "from the config" : "");
    g_run_stop.store(false);
    std::signal(SIGINT, run_on_signal);
    std::signal(SIGTERM, run_on_signal);
    std::atomic<bool> consumer_stop{false};
    std::atomic<uint64_t> frames_seen{0}, imu_seen{0};
    std::thread consumer([&] {
      int64_t last_imu_t_ns = -1;
      int64_t frame_waiting_since_ns = -1;
      while (!consumer_stop.load(std::memory_order_relaxed)) {
        bool any = false;
        for (;;) {
          ImuSample* s = rings->imu.front();
          RgbdFrameMsg* m = rings->frames.front();
          if (s != nullptr && (m == nullptr || s->t_ns <= m->t_ns)) {
            est->add_imu(*s);
            imu_seen.fetch_add(1, std::memory_order_relaxed);
            last_imu_t_ns = s->t_ns;
            rings->imu.pop();
            any = true;
            continue;
          }
          if (m == nullptr) break;
          // The frame goes once the IMU has passed its time (the estimator
          // propagates to the exposure), or after a bounded wait.
          const int64_t now = rt::now_ns();
          if (frame_waiting_since_ns < 0) frame_waiting_since_ns = now;
          if (s == nullptr && last_imu_t_ns < m->t_ns && now - frame_waiting_since_ns < kFrameWaitForImuNs) break;
          frame_waiting_since_ns = -1;
          core::RgbdFrame f;
          f.t_ns = m->t_ns;
          f.seq = m->seq;
          if (const auto* b = rings->images.get(m->rgb_handle)) f.rgb = b->view();
          if (const auto* b = rings->images.get(m->depth_handle)) f.depth = b->view();
          est->add_frame(f);
          rings->images.release(m->rgb_handle);
          if (m->depth_handle != rt::kInvalidHandle) rings->images.release(m->depth_handle);
          rings->frames.pop();
          frames_seen.fetch_add(1, std::memory_order_relaxed);
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
        std::printf("t=%5.1f s  imu %llu  frames %llu  ring drops imu %llu frames %llu\n", (rt::now_ns() - t0) * 1e-9,
                    (unsigned long long)imu_seen.load(), (unsigned long long)frames_seen.load(),
                    (unsigned long long)rings->imu.drops(), (unsigned long long)(rings->frames.drops() + frames.drops));
      }
    }
    sensors.stop();
    consumer_stop.store(true);
    consumer.join();
    std::signal(SIGINT, SIG_DFL);
    std::signal(SIGTERM, SIG_DFL);
    std::printf("%s", sensors.report().c_str());
    const auto& c = est->counters();
    const auto& o = est->output();
    std::printf("estimator %s: imu %llu used of %llu, frames %llu used of %llu, resets %llu; last pose t=%.3f s "
                "p_WB (%.3f, %.3f, %.3f) m\n",
                est->name(), (unsigned long long)c.imu_used, (unsigned long long)c.imu_in,
                (unsigned long long)c.frames_used, (unsigned long long)c.frames_in, (unsigned long long)c.resets,
                o.state.t_ns * 1e-9, o.state.p_WB.x(), o.state.p_WB.y(), o.state.p_WB.z());
    return 0;
  };
  return s;
}

}  // namespace kestrel::cli
