// `kestrel record`: live sensors into a .klog. Driver threads copy into the
// logger's preallocated rings; the logger thread alone touches the disk.
#include <atomic>
#include <csignal>
#include <cstdio>
#include <memory>
#include <string>

#include "kestrel/commands.hpp"
#include "kestrel/drivers/devices.hpp"
#include "kestrel/drivers/klog_logger.hpp"
#include "kestrel/recording.hpp"
#include "kestrel/replay_runner.hpp"
#include "kestrel/rt/clock.hpp"
#include "kestrel/tools/config_file.hpp"

namespace kestrel::cli {
namespace {

std::atomic<bool> g_record_stop{false};
extern "C" void record_on_signal(int) { g_record_stop.store(true); }

struct RecordArgs {
  std::string config;
  std::string out;
  double duration_s = 0;
  uint32_t fsync_every = 0;
  double buffer_s = 4.0;
};

}  // namespace

Subcommand add_record_command(CLI::App& parent) {
  auto a = std::make_shared<RecordArgs>();
  CLI::App* app = parent.add_subcommand("record", "record live camera + IMU into a .klog");
  app->add_option("--config", a->config, "rig + drivers config (configs/*.yaml)")->required();
  app->add_option("--out", a->out, "output .klog")->required();
  app->add_option("--duration", a->duration_s, "seconds to record (0 = until Ctrl-C)")->capture_default_str();
  app->add_option("--fsync-every", a->fsync_every, "fsync every N records (0 = flush only)")
      ->capture_default_str();
  app->add_option("--buffer-s", a->buffer_s,
                  "seconds of camera frames held in memory while the disk stalls (sizes the staging buffer)")
      ->capture_default_str();
  app->footer(
      "Example:\n  kestrel record --config configs/openni2_bmx055_i2c.yaml --out FLIGHT.klog\n"
      "Without the sensors it exits with 1 and names what is missing. Drivers: docs/drivers/README.md");
  Subcommand s;
  s.app = app;
  s.run = [a] {
    const drivers::LiveConfig cfg = tools::load_live_config(a->config);
    if (!(a->buffer_s > 0 && a->buffer_s <= 60)) throw UsageError("--buffer-s must be in (0, 60] seconds");
    drivers::LiveSensors sensors(cfg);  // throws, naming each missing device
    const std::unique_ptr<drivers::KlogLogger> log =
        make_recording_logger(cfg, a->out, a->buffer_s, a->fsync_every);
    drivers::KlogLogger& logger = *log;
    LoggerImuSink imu(logger);
    LoggerFrameSink frames(logger);
    g_record_stop.store(false);
    std::signal(SIGINT, record_on_signal);
    std::signal(SIGTERM, record_on_signal);
    std::printf("recording %s to %s (%s)\n", sensors.description().c_str(), a->out.c_str(),
                a->duration_s > 0 ? (std::to_string(a->duration_s) + " s").c_str() : "Ctrl-C to stop");
    const int64_t t0 = rt::now_ns();
    sensors.start(imu, frames);
    while (!g_record_stop.load() &&
           (a->duration_s <= 0 || rt::now_ns() - t0 < static_cast<int64_t>(a->duration_s * 1e9)))
      rt::sleep_for_ns(100'000'000);
    sensors.stop();
    logger.stop();
    std::signal(SIGINT, SIG_DFL);
    std::signal(SIGTERM, SIG_DFL);
    std::printf("%s", sensors.report().c_str());
    std::vector<AppliedThread> applied;
    for (const auto& [spec, rep] : sensors.thread_reports()) applied.push_back(applied_thread(spec, rep));
    applied.push_back(applied_thread(logger.thread_spec(), logger.thread_report()));
    std::printf("%s", threads_summary(applied).c_str());
    std::printf("%s", recording_summary(logger).c_str());
    if (!logger.error().empty()) {
      std::fprintf(stderr, "kestrel record: write error: %s\n", logger.error().c_str());
      return 1;
    }
    return 0;
  };
  return s;
}

}  // namespace kestrel::cli
