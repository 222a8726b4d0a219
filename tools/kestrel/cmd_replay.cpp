// `kestrel replay LOG`: the hardware-in-the-loop harness.
#include <cstdio>
#include <fstream>
#include <iostream>

#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/commands.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/drivers/devices.hpp"
#include "kestrel/mavlink/udp_sender.hpp"
#include "kestrel/replay_runner.hpp"
#include "kestrel/tools/estimator_config_yaml.hpp"

namespace kestrel::cli {

Subcommand add_replay_command(CLI::App& parent) {
  struct Args {
    std::string path;
    std::string format = "auto";
    drivers::LogOpenOptions open;
    std::string pace = "lockstep";
    std::string estimator = "auto";
    std::string config;
    std::string traj_out;
    std::string metrics_out;
    double warmup_s = 2.0;
    bool quiet = false;
    std::string mavlink_udp;
    std::string status = "auto";
    bool print_config = false;
  };
  auto args = std::make_shared<Args>();
  CLI::App* app = parent.add_subcommand("replay", "play a recorded log through the estimator (HIL harness)");
  app->add_option("log", args->path,
                  "a .klog file, a ROS 1 bag, or an EuRoC / TUM / ETH3D / OpenLORIS folder (docs/datasets.md); "
                  "required unless --print-config");
  app->add_option("--format", args->format, std::string("input format: ") + drivers::log_format_names())
      ->capture_default_str();
  app->add_option("--rig", args->open.rig_path, "rig YAML for calibration the dataset lacks (ETH3D, OpenLORIS, 7-Scenes, rosbag)");
  app->add_option("--fps", args->open.fps, "7-Scenes: the frame rate its time stamps are made from (frame i at i / fps)")
      ->capture_default_str();
  app->add_option("--rgb-topic", args->open.rgb_topic, "rosbag colour topic (default /camera/color/image_raw)");
  app->add_option("--depth-topic", args->open.depth_topic,
                  "rosbag depth topic (default /camera/aligned_depth_to_color/image_raw)");
  app->add_option("--imu-topic", args->open.imu_topic, "rosbag IMU topic (default /camera/imu)");
  app->add_option("--camera-info-topic", args->open.camera_info_topic,
                  "rosbag CameraInfo topic (default: beside the colour topic)");
  app->add_option("--gt-topic", args->open.ground_truth_topic,
                  "rosbag ground truth, geometry_msgs/PoseStamped (default /kestrel/ground_truth)");
  app->add_option("--pace", args->pace,
                  "realtime (sensor timing, drops like live), fast (as fast as it drains), "
                  "lockstep (deterministic, bit-identical output)")
      ->capture_default_str();
  app->add_option("--estimator", args->estimator,
                  std::string("backend: ") + core::estimator_names() +
                      " (auto, the default: window with an IMU, rgbd without; window = front end + sliding-window optimizer; vo = "
                      "tracking front end + IMU; ekf = EKF SLAM; imu = IMU dead reckoning; rgbd = RGB-D tracking "
                      "without an IMU)")
      ->capture_default_str();
  app->add_option("--config", args->config,
                  "a config whose estimator sections (estimator:, frontend:, window:, ekf:; docs/config.md) set every "
                  "tunable (--estimator overrides its backend) and whose `threads:` table schedules the threads in "
                  "realtime pace (configs/*.yaml, docs/threads.md)");
  app->add_flag("--print-config", args->print_config,
                "print the effective estimator settings as YAML and exit (with a log: after opening it)");
  app->add_option("--traj-out", args->traj_out, "write the trajectory here (TUM: t[s] x y z qx qy qz qw)");
  app->add_option("--metrics-out", args->metrics_out,
                  "write latency histograms, drops, counters, CPU, RSS, real-time factor as JSON");
  app->add_option("--warmup", args->warmup_s, "seconds of log before steady-state statistics start")
      ->capture_default_str();
  app->add_flag("-q,--quiet", args->quiet, "print nothing but errors");
  app->add_option("--mavlink-udp", args->mavlink_udp,
                  "stream MAVLink v2 ODOMETRY to HOST:PORT at the pose rate (flight controller; docs/px4.md)");
  app->add_option("--status", args->status,
                  "1 Hz status line (per second of log time): on, off, auto (= on in realtime pace)")
      ->capture_default_str();

  Subcommand cmd;
  cmd.app = app;
  cmd.run = [args, app]() -> int {
    ReplayOptions opt;
    opt.path = args->path;
    opt.open = args->open;
    opt.estimator = args->estimator;
    const std::string override_backend = app->count("--estimator") ? args->estimator : "";
    if (!override_backend.empty() && !core::estimator_known(override_backend))
      throw UsageError("unknown --estimator '" + override_backend + "' (expected one of: " + core::estimator_names() +
                       ")");
    opt.config = tools::load_estimator_config(args->config, override_backend);
    opt.estimator = opt.config->backend;
    if (!args->config.empty()) opt.threads = drivers::load_thread_table(args->config);
    try {
      opt.format = drivers::parse_log_format(args->format);
      opt.pace = drivers::parse_replay_pace(args->pace);
    } catch (const std::exception& e) {
      throw UsageError(e.what());
    }
    if (!(args->warmup_s >= 0)) throw UsageError("--warmup must be >= 0 seconds");
    opt.warmup_ns = static_cast<int64_t>(args->warmup_s * 1e9);
    opt.mavlink_udp = args->mavlink_udp;
    std::string host;
    uint16_t port = 0;
    if (!opt.mavlink_udp.empty() && !mavlink::parse_endpoint(opt.mavlink_udp, host, port))
      throw UsageError("--mavlink-udp '" + opt.mavlink_udp + "': expected HOST:PORT with PORT in 1..65535");
    if (args->status != "on" && args->status != "off" && args->status != "auto")
      throw UsageError("--status must be on, off or auto");
    opt.status_line = !args->quiet && (args->status == "on" ||
                                       (args->status == "auto" && opt.pace == drivers::ReplayPace::kRealtime));
    if (args->print_config) {
      // With a log, open it first: the settings printed are the ones a replay of it would run with.
      if (!args->path.empty()) {
        drivers::LogOpenOptions o = opt.open;
        o.format = opt.format;
        (void)drivers::open_log(opt.path, o);
      }
      std::cout << tools::estimator_config_to_yaml(*opt.config);
      return 0;
    }
    if (args->path.empty()) throw UsageError("replay: the log is required (unless --print-config)");
    ReplayReport r = run_replay(opt);
    r.config = tools::estimator_config_entries(*opt.config);
    if (!args->traj_out.empty()) tools::write_tum(args->traj_out, r.trajectory);
    if (!args->metrics_out.empty()) {
      std::ofstream f(args->metrics_out);
      if (!f) throw std::runtime_error("cannot write " + args->metrics_out);
      f << replay_metrics_json(r);
    }
    if (!args->quiet) {
      std::cout << replay_summary(r);
      for (const auto& p : r.problems) std::cerr << "problem: " << p.where << ": " << p.kind << ": " << p.detail << "\n";
      if (!args->traj_out.empty()) std::cout << "trajectory: " << args->traj_out << "\n";
      if (!args->metrics_out.empty()) std::cout << "metrics: " << args->metrics_out << "\n";
    }
    return 0;
  };
  return cmd;
}

}  // namespace kestrel::cli
