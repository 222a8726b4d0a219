// `kestrel run`: the live sensors as the input of the replay pipeline
// (run_replay, replay_runner.hpp's LiveInput): the drivers fill the sensor
// rings, and from there on a flight runs the very code a realtime replay of its
// recording runs (kst-propagate, the estimator, optimizer, map, output
// threads, their checks and outputs). The backend is the config's
// (`estimator: backend:`, or --estimator; default window, as in replay).
#include <atomic>
#include <csignal>
#include <cstdio>
#include <iostream>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "kestrel/commands.hpp"
#include "kestrel/core/estimator.hpp"
#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/dense/dense_config.hpp"
#include "kestrel/drivers/devices.hpp"
#include "kestrel/foxglove_out.hpp"
#include "kestrel/mavlink/odometry_stream.hpp"
#include "kestrel/mcap_out.hpp"
#include "kestrel/recording.hpp"
#include "kestrel/replay_runner.hpp"
#include "kestrel/rt/clock.hpp"
#include "kestrel/rt/thread_setup.hpp"
#include "kestrel/tools/config_file.hpp"
#include "kestrel/tools/estimator_config_yaml.hpp"
#include "kestrel/tools/map_files.hpp"
#include "kestrel/view_cli.hpp"
#include "kestrel/viewer/server.hpp"

namespace kestrel::cli {
namespace {

std::atomic<bool> g_run_stop{false};
extern "C" void run_on_signal(int) { g_run_stop.store(true); }

struct RunArgs {
  std::string config;
  std::string estimator;
  double duration_s = 0;
  std::string mavlink_udp;
  ViewArgs view;
  std::string mavlink_serial;
  std::string record;
  std::string traj_out;
  double record_buffer_s = 4.0;
  bool print_config = false;
  std::string mapping, loop;
  std::string map_in, map_out;
  std::string dense_out, dense_octomap_out;  // the dense map (docs/dense.md)
  std::string mcap_out;
  std::string foxglove;  // [ADDR:]PORT
  double foxglove_wait_s = 0;
};

// Latency statistics start after this much sample time (start-up is not steady state).
constexpr int64_t kWarmupNs = 2'000'000'000;

// What both kinds of input share: the backend, the thread table, the outputs.
ReplayOptions pipeline_options(const RunArgs& a, const tools::Config& file, const drivers::LiveConfig& cfg,
                               const core::EstimatorConfig& est_cfg,
                               const std::optional<mavlink::OdometryStreamOptions>& mavlink,
                               const viewer::ServerOptions& view_options) {
  ReplayOptions opt;
  opt.config = est_cfg;
  opt.estimator = est_cfg.backend;
  opt.threads = cfg.threads;
  opt.mavlink = mavlink;
  opt.map_out = a.map_out;
  opt.dense = file.dense;
  opt.dense_view = file.dense_view;
  opt.dense_out = a.dense_out;
  opt.dense_octomap_out = a.dense_octomap_out;
  if (!a.view.endpoint.empty()) {
    opt.view = true;
    opt.view_options = view_options;
    opt.view_wait_s = a.view.wait_s;
    const ViewArgs view = a.view;
    opt.on_view_ready = [view](const viewer::Server& s) { print_view_ready(s, view); };
  }
  return opt;
}

// `drivers.log.pace: fast|lockstep`: the log is read by replay's source
// instead of the live log driver, so `kestrel run` writes byte for byte what
// `kestrel replay LOG --pace P` writes. Realtime pace plays it through the
// live sensor threads, as a flight.
int run_log_through_replay(const RunArgs& a, const tools::Config& file, const drivers::LiveConfig& cfg,
                           const core::EstimatorConfig& est_cfg,
                           const std::optional<mavlink::OdometryStreamOptions>& mavlink,
                           const viewer::ServerOptions& view_options) {
  if (!a.record.empty()) {
    throw UsageError(std::string("--record: the sensors are a log played at ") +
                     drivers::to_string(cfg.drivers.log_pace) + " pace, already a recording (" +
                     cfg.drivers.log_path + ")");
  }
  if (a.duration_s > 0) {
    throw UsageError(std::string("--duration: a log at ") + drivers::to_string(cfg.drivers.log_pace) +
                     " pace runs to its end");
  }
  ReplayOptions opt = pipeline_options(a, file, cfg, est_cfg, mavlink, view_options);
  opt.path = cfg.drivers.log_path;
  opt.format = drivers::LogFormat::kKlog;
  opt.pace = cfg.drivers.log_pace;
  std::printf("running %s at %s pace through the replay pipeline -> estimator '%s'\n",
              cfg.drivers.log_path.c_str(), drivers::to_string(cfg.drivers.log_pace),
              est_cfg.backend.c_str());
  const auto mcap = add_mcap_out(opt, a.mcap_out, cfg.ros2.map_points_rate_hz);
  const auto fox = add_foxglove(opt, a.foxglove, cfg.ros2.map_points_rate_hz, a.foxglove_wait_s);
  ReplayReport r;
  try {
    r = run_replay(opt);
  } catch (const std::invalid_argument& e) {
    throw UsageError(e.what());
  }
  if (mcap) mcap->close();
  if (fox) fox->server().stop();
  r.config = tools::estimator_config_entries(est_cfg);
  std::printf("%s", replay_summary(r).c_str());
  for (const auto& p : r.problems)
    std::fprintf(stderr, "problem: %s: %s: %s\n", p.where.c_str(), p.kind.c_str(), p.detail.c_str());
  if (!a.traj_out.empty()) {
    tools::write_tum(a.traj_out, r.trajectory);
    std::printf("trajectory: %s (%zu poses)\n", a.traj_out.c_str(), r.trajectory.size());
  }
  if (!a.map_out.empty()) std::printf("map: %s\n", a.map_out.c_str());
  if (mcap) {
    std::printf("mcap: %s (%llu odometry messages)\n", a.mcap_out.c_str(),
                static_cast<unsigned long long>(mcap->count()));
  }
  if (fox) std::printf("%s", foxglove::stats_summary(fox->server().stats()).c_str());
  return 0;
}

}  // namespace

Subcommand add_run_command(CLI::App& parent) {
  auto a = std::make_shared<RunArgs>();
  CLI::App* app = parent.add_subcommand("run", "start the live drivers and the estimator");
  app->add_option("--config", a->config, "rig + drivers config (configs/*.yaml)")->required();
  app->add_option("--estimator", a->estimator,
                  std::string("backend: ") + core::estimator_names() +
                      " (default: the config's estimator.backend, else window)");
  app->add_flag(
      "--print-config", a->print_config,
      "print the effective estimator settings as YAML (the config's estimator sections on the backend's "
      "defaults, docs/config.md) and exit");
  app->add_option("--duration", a->duration_s, "seconds to run (0 = until Ctrl-C)")->capture_default_str();
  app->add_option("--mapping", a->mapping,
                  "on|off: the map beside the backend (default on for window, off for ekf; docs/map.md)");
  app->add_option("--loop", a->loop, "on|off: loop closing and relocalisation (default on)");
  app->add_option(
      "--map-in", a->map_in,
      "start from this map file: nothing is mapped until the camera relocalises in it (docs/map.md)");
  app->add_option(
      "--mcap-out", a->mcap_out,
      "write the poses (nav_msgs/msg/Odometry, /tf, /diagnostics), the map points (PointCloud2) and "
      "keyframe and loop markers here in MCAP (ROS 2, Foxglove; docs/ros2.md)");
  app->add_option(
      "--foxglove", a->foxglove,
      "serve the --mcap-out topics live over the Foxglove WebSocket protocol on [ADDR:]PORT (docs/ros2.md)");
  app->add_option("--foxglove-wait", a->foxglove_wait_s,
                  "with --foxglove: wait up to this long [s] for a client first");
  app->add_option("--map-out", a->map_out, "write the map here when the run stops (docs/map.md)");
  app->add_option(
      "--dense-out", a->dense_out,
      "build the dense map (the config's dense: section) and write its surface here as PLY when the "
      "run stops, in the frame of --traj-out (docs/dense.md)");
  app->add_option("--dense-octomap-out", a->dense_octomap_out,
                  "build the dense map and write its occupancy here as an OctoMap .bt when the run stops");
  app->add_option(
      "--mavlink-udp", a->mavlink_udp,
      "MAVLink v2 to the flight controller at HOST:PORT: ODOMETRY per pose, HEARTBEAT 1 Hz, TIMESYNC "
      "(over the config's mavlink: link; docs/px4.md)");
  app->add_option(
      "--mavlink-serial", a->mavlink_serial,
      "the same over a serial port, DEVICE[:BAUD] (baud default: the config's mavlink.serial_baud)");
  app->add_option(
      "--record", a->record,
      "also record the sensors into this .klog while estimating (replay it afterwards with kestrel replay)");
  app->add_option("--record-buffer-s", a->record_buffer_s,
                  "seconds of camera frames the recorder holds while the disk stalls")
      ->capture_default_str();
  app->add_option("--traj-out", a->traj_out,
                  "write the estimated trajectory here (TUM: t[s] x y z qx qy qz qw)");
  add_view_options(app, a->view, false);
  app->footer(
      "Runs: live drivers -> sensor rings -> kst-propagate (IMU-rate pose at once) -> estimator thread (IMU "
      "and\n"
      "frames in time order) -> kst-optimizer; thread scheduling from the config's threads: table.\n"
      "Without the sensors it exits with 1 naming what is missing.");
  Subcommand s;
  s.app = app;
  s.run = [a] {
    if (!a->estimator.empty() && !core::estimator_known(a->estimator)) {
      throw UsageError("unknown --estimator '" + a->estimator +
                       "' (expected one of: " + core::estimator_names() + ")");
    }
    // The file is read once, every section checked, before any device opens.
    // The default backend is replay's unless the config or --estimator names one.
    const tools::Config file = tools::load_config(a->config, a->estimator);
    const drivers::LiveConfig cfg = tools::live_config(file);
    core::EstimatorConfig est_cfg = file.estimator;
    try {
      tools::apply_map_switches(est_cfg, a->mapping, a->loop);
      if (!a->map_in.empty()) tools::set_map_in(est_cfg, a->map_in);
      if (!a->map_out.empty() && !tools::may_have_map(est_cfg)) {
        throw std::invalid_argument(
            "--map-out needs a backend with the map (window, or ekf with --mapping on)");
      }
    } catch (const std::invalid_argument& e) {
      throw UsageError(e.what());
    }
    if (a->print_config) {
      std::cout << tools::estimator_config_to_yaml(est_cfg)
                << dense::dense_sections_yaml(file.dense, file.dense_view);
      return 0;
    }
    std::optional<mavlink::OdometryStreamOptions> mo;
    try {
      mo = mavlink_options(cfg.mavlink, a->mavlink_udp, a->mavlink_serial);
    } catch (const std::invalid_argument& e) {
      throw UsageError(e.what());
    }
    viewer::ServerOptions view_options;
    if (!a->view.endpoint.empty()) view_options = view_server_options(a->view, "run " + a->config);
    if (!a->record.empty() && !(a->record_buffer_s > 0 && a->record_buffer_s <= 60))
      throw UsageError("--record-buffer-s must be in (0, 60] seconds");
    if (cfg.drivers.camera.type == drivers::CameraType::kLog &&
        cfg.drivers.log_pace != drivers::ReplayPace::kRealtime)
      return run_log_through_replay(*a, file, cfg, est_cfg, mo, view_options);
    drivers::LiveSensors sensors(cfg);  // missing sensors are named first
    // The flight runs the replay pipeline (run_replay) with the sensors as its
    // input: the same stages, threads, wake-ups, checks and outputs a replay
    // of the recording would run (issue 45).
    ReplayOptions opt = pipeline_options(*a, file, cfg, est_cfg, mo, view_options);
    opt.pace = drivers::ReplayPace::kRealtime;
    opt.warmup_ns = kWarmupNs;
    opt.status_line = true;
    opt.camera_silent_after_ns = 150'000'000;
    // --record: every sample also goes to the recorder (its own rings and disk
    // thread), with the stamps the drivers gave it, so the flight replays.
    std::unique_ptr<drivers::KlogLogger> recorder;
    std::unique_ptr<LoggerImuSink> rec_imu;
    std::unique_ptr<LoggerFrameSink> rec_frames;
    std::unique_ptr<TeeImuSink> tee_imu;
    std::unique_ptr<TeeFrameSink> tee_frames;
    if (!a->record.empty()) {
      recorder = make_recording_logger(cfg, a->record, a->record_buffer_s, 0);
      rec_imu = std::make_unique<LoggerImuSink>(*recorder);
      rec_frames = std::make_unique<LoggerFrameSink>(*recorder);
      std::printf("recording the sensors to %s\n", a->record.c_str());
    }
    int64_t t0 = 0;
    auto live = std::make_shared<LiveInput>();
    live->rig = cfg.rig;
    live->description = sensors.description();
    live->stereo_problem = drivers::stereo_capability(cfg.drivers.camera);
    live->max_image_bytes =
        static_cast<size_t>(cfg.drivers.camera.width_px) * cfg.drivers.camera.height_px * 3;
    live->start = [&](drivers::ImuSink& imu, drivers::FrameSink& frames,
                      std::vector<AppliedThread>& applied) {
      drivers::ImuSink* imu_sink = &imu;
      drivers::FrameSink* frame_sink = &frames;
      if (recorder) {
        tee_imu = std::make_unique<TeeImuSink>(imu, *rec_imu);
        tee_frames = std::make_unique<TeeFrameSink>(frames, *rec_frames);
        imu_sink = tee_imu.get();
        frame_sink = tee_frames.get();
      }
      t0 = rt::now_ns();
      sensors.start(*imu_sink, *frame_sink);
      for (const auto& [spec, rep] : sensors.thread_reports()) applied.push_back(applied_thread(spec, rep));
    };
    live->stop = [&] {
      sensors.stop();
      if (recorder) recorder->stop();
    };
    const int64_t duration_ns = static_cast<int64_t>(a->duration_s * 1e9);
    live->should_stop = [&] {
      return g_run_stop.load() || (duration_ns > 0 && rt::now_ns() - t0 >= duration_ns);
    };
    opt.live = live;
    std::printf("running %s -> estimator '%s' (%s)\n", sensors.description().c_str(), est_cfg.backend.c_str(),
                file.backend_from_file ? "from the config" : "");
    // Memory locked and the stack prefaulted before any pipeline thread starts
    // (docs/threads.md); refused without CAP_IPC_LOCK, and the line says so.
    std::printf("process: %s\n", rt::to_string(rt::setup_process()).c_str());
    g_run_stop.store(false);
    std::signal(SIGINT, run_on_signal);
    std::signal(SIGTERM, run_on_signal);
    const auto mcap = add_mcap_out(opt, a->mcap_out, cfg.ros2.map_points_rate_hz);
    const auto fox = add_foxglove(opt, a->foxglove, cfg.ros2.map_points_rate_hz, a->foxglove_wait_s);
    ReplayReport r;
    try {
      r = run_replay(opt);
    } catch (const std::invalid_argument& e) {
      throw UsageError(e.what());
    }
    if (mcap) mcap->close();
    if (fox) fox->server().stop();
    std::signal(SIGINT, SIG_DFL);
    std::signal(SIGTERM, SIG_DFL);
    r.config = tools::estimator_config_entries(est_cfg);
    std::printf("%s", replay_summary(r).c_str());
    std::printf("%s", sensors.report().c_str());
    if (recorder) {
      std::printf(
          "%s",
          threads_summary({applied_thread(recorder->thread_spec(), recorder->thread_report())}).c_str());
      std::printf("%s", recording_summary(*recorder).c_str());
      if (!recorder->error().empty())
        std::fprintf(stderr, "kestrel run: recording: %s\n", recorder->error().c_str());
    }
    if (!a->traj_out.empty()) {
      tools::write_tum(a->traj_out, r.trajectory);
      std::printf("trajectory: %s (%zu poses)\n", a->traj_out.c_str(), r.trajectory.size());
    }
    if (!a->map_out.empty()) std::printf("map: %s\n", a->map_out.c_str());
    if (mcap) {
      std::printf("mcap: %s (%llu odometry messages)\n", a->mcap_out.c_str(),
                  static_cast<unsigned long long>(mcap->count()));
    }
    if (fox) std::printf("%s", foxglove::stats_summary(fox->server().stats()).c_str());
    return 0;
  };
  return s;
}

}  // namespace kestrel::cli
