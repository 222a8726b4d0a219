// `kestrel replay LOG`: the hardware-in-the-loop harness.
#include <cstdio>
#include <fstream>
#include <iostream>

#include "kestrel/commands.hpp"
#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/dense/dense_config.hpp"
#include "kestrel/drivers/devices.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/foxglove_out.hpp"
#include "kestrel/mcap_out.hpp"
#include "kestrel/replay_runner.hpp"
#include "kestrel/tools/config_file.hpp"
#include "kestrel/tools/estimator_config_yaml.hpp"
#include "kestrel/tools/map_files.hpp"
#include "kestrel/view_cli.hpp"

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
    std::string mavlink_serial;
    std::string status = "auto";
    ViewArgs view;
    bool print_config = false;
    std::string mapping, loop;
    std::string map_traj_out, map_final_traj_out;
    std::string map_in, map_out;
    std::string dense_out, dense_octomap_out, dense_map_out;  // the dense map (docs/dense.md)
    std::string mcap_out;
    std::string foxglove;  // [ADDR:]PORT
    double foxglove_wait_s = 0;
    std::string loop_log;
  };
  auto args = std::make_shared<Args>();
  CLI::App* app = parent.add_subcommand("replay", "play a recorded log through the estimator (HIL harness)");
  app->add_option(
      "log", args->path,
      "a .klog file, a ROS 1 bag, or an EuRoC / TUM / ETH3D / OpenLORIS folder (docs/datasets.md); "
      "required unless --print-config");
  app->add_option("--format", args->format, std::string("input format: ") + drivers::log_format_names())
      ->capture_default_str();
  app->add_option("--rig", args->open.rig_path,
                  "rig YAML for calibration the dataset lacks (ETH3D, OpenLORIS, 7-Scenes, rosbag)");
  app->add_option("--fps", args->open.fps,
                  "7-Scenes: the frame rate its time stamps are made from (frame i at i / fps)")
      ->capture_default_str();
  app->add_option("--rgb-topic", args->open.rgb_topic,
                  "rosbag colour topic (default /camera/color/image_raw)");
  app->add_option("--depth-topic", args->open.depth_topic,
                  "rosbag depth topic (default /camera/aligned_depth_to_color/image_raw)");
  app->add_option("--imu-topic", args->open.imu_topic, "rosbag IMU topic (default /camera/imu)");
  app->add_option(
      "--right-topic", args->open.right_topic,
      "rosbag / rosbag2: a stereo pair's right image topic, e.g. /camera/infra2/image_rect_raw with "
      "--rgb-topic "
      "/camera/infra1/image_rect_raw (default /camera/right/image_raw when present; docs/stereo.md)");
  app->add_option("--camera-info-topic", args->open.camera_info_topic,
                  "rosbag CameraInfo topic (default: beside the colour topic)");
  app->add_option(
         "--topics", args->open.topics,
         "rosbag2: read only these topics (comma-separated), detected by type among them; tf_static and "
         "CameraInfo are still read for the rig (docs/ros2.md)")
      ->delimiter(',');
  app->add_option("--gt-topic", args->open.ground_truth_topic,
                  "rosbag ground truth, geometry_msgs/PoseStamped (default /kestrel/ground_truth)");
  app->add_option("--pace", args->pace,
                  "realtime (sensor timing, drops like live), fast (as fast as it drains), "
                  "lockstep (deterministic, bit-identical output)")
      ->capture_default_str();
  app->add_option(
         "--estimator", args->estimator,
         std::string("backend: ") + core::estimator_names() +
             " (auto, the default: window with an IMU, rgbd without; window = front end + sliding-window "
             "optimizer; vo = "
             "tracking front end + IMU; ekf = EKF SLAM; imu = IMU dead reckoning; rgbd = RGB-D tracking "
             "without an IMU)")
      ->capture_default_str();
  app->add_option(
      "--config", args->config,
      "a config whose estimator sections (estimator:, frontend:, window:, ekf:; docs/config.md) set every "
      "tunable (--estimator overrides its backend) and whose `threads:` table schedules the threads in "
      "realtime pace (configs/*.yaml, docs/threads.md)");
  app->add_flag("--print-config", args->print_config,
                "print the effective estimator settings as YAML and exit (with a log: after opening it)");
  app->add_option("--traj-out", args->traj_out, "write the trajectory here (TUM: t[s] x y z qx qy qz qw)");
  app->add_option("--mapping", args->mapping,
                  "on|off: the map beside the backend (local mapping thread, tracking against the refined "
                  "map; default on for window, off for ekf; docs/map.md)");
  app->add_option("--loop", args->loop, "on|off: loop closing and relocalisation on the map (default on)");
  app->add_option(
      "--map-traj-out", args->map_traj_out,
      "write the trajectory in the map frame here, T_map_odom(t) * pose(t) (TUM); --traj-out keeps the "
      "continuous odometry");
  app->add_option(
      "--map-final-traj-out", args->map_final_traj_out,
      "write the trajectory through the map's keyframes as they ended the flight (TUM; after every "
      "bundle adjustment and loop correction: what SLAM benchmarks score, not what flew; docs/map.md)");
  app->add_option(
      "--map-in", args->map_in,
      "start from this map file (a flight's --map-out): the flight maps nothing until it relocalises in "
      "it, then goes on in its frame (docs/map.md)");
  app->add_option(
      "--mcap-out", args->mcap_out,
      "write the poses (nav_msgs/msg/Odometry, /tf, /diagnostics), the map points (PointCloud2) and "
      "keyframe and loop markers here in MCAP (ROS 2, Foxglove; docs/ros2.md)");
  app->add_option(
      "--foxglove", args->foxglove,
      "serve the --mcap-out topics live over the Foxglove WebSocket protocol on [ADDR:]PORT (docs/ros2.md)");
  app->add_option("--foxglove-wait", args->foxglove_wait_s,
                  "with --foxglove: wait up to this long [s] for a client first");
  app->add_option(
      "--loop-log", args->loop_log,
      "write every loop candidate here (CSV: BoW score, matches, inliers, the verdict, and with the "
      "log's ground truth its view overlap and the correction's error); with ground truth the "
      "summary and --metrics-out also count the revisits the flight made (docs/map.md)");
  app->add_option("--map-out", args->map_out,
                  "write the map here at the end (versioned, CRC-checked; docs/map.md)");
  app->add_option(
      "--dense-out", args->dense_out,
      "build the dense map (the config's dense: section) and write its surface here as PLY, in the "
      "frame of --traj-out (docs/dense.md)");
  app->add_option("--dense-octomap-out", args->dense_octomap_out,
                  "build the dense map and write its occupancy here as an OctoMap .bt (docs/dense.md)");
  app->add_option("--dense-map-out", args->dense_map_out,
                  "build the dense map and write its surface here as PLY re-integrated along the map's final "
                  "trajectory (the frame of --map-final-traj-out: surfaces follow loops; docs/dense.md)");
  app->add_option("--metrics-out", args->metrics_out,
                  "write latency histograms, drops, counters, CPU, RSS, real-time factor as JSON");
  app->add_option("--warmup", args->warmup_s, "seconds of log before steady-state statistics start")
      ->capture_default_str();
  app->add_flag("-q,--quiet", args->quiet, "print nothing but errors");
  app->add_option(
      "--mavlink-udp", args->mavlink_udp,
      "MAVLink v2 to a flight controller at HOST:PORT: ODOMETRY per pose, HEARTBEAT 1 Hz, TIMESYNC "
      "(the config's mavlink: section sets ids, R_FB, rates; docs/px4.md)");
  app->add_option("--mavlink-serial", args->mavlink_serial,
                  "the same over a serial port, DEVICE[:BAUD] (baud default: the config's, else 921600)");
  app->add_option("--status", args->status,
                  "1 Hz status line (per second of log time): on, off, auto (= on in realtime pace)")
      ->capture_default_str();
  add_view_options(app, args->view, true);

  Subcommand cmd;
  cmd.app = app;
  cmd.run = [args, app]() -> int {
    ReplayOptions opt;
    opt.path = args->path;
    opt.open = args->open;
    opt.estimator = args->estimator;
    const std::string override_backend = app->count("--estimator") ? args->estimator : "";
    if (!override_backend.empty() && !core::estimator_known(override_backend)) {
      throw UsageError("unknown --estimator '" + override_backend +
                       "' (expected one of: " + core::estimator_names() + ")");
    }
    // The file is read once, every section checked, before any work starts.
    const tools::Config file = tools::load_config(args->config, override_backend);
    opt.config = file.estimator;
    try {
      tools::apply_map_switches(*opt.config, args->mapping, args->loop);
      if (!args->map_in.empty()) tools::set_map_in(*opt.config, args->map_in);
      if (!args->map_out.empty() && !tools::may_have_map(*opt.config)) {
        throw std::invalid_argument(
            "--map-out needs a backend with the map (window, or ekf with --mapping on)");
      }
    } catch (const std::invalid_argument& e) {
      throw UsageError(e.what());
    }
    opt.estimator = opt.config->backend;
    opt.map_out = args->map_out;
    opt.dense = file.dense;
    opt.dense_view = file.dense_view;
    opt.dense_out = args->dense_out;
    opt.dense_octomap_out = args->dense_octomap_out;
    opt.dense_map_out = args->dense_map_out;
    opt.threads = file.threads;
    try {
      opt.format = drivers::parse_log_format(args->format);
      opt.pace = drivers::parse_replay_pace(args->pace);
    } catch (const std::exception& e) {
      throw UsageError(e.what());
    }
    if (!(args->warmup_s >= 0)) throw UsageError("--warmup must be >= 0 seconds");
    opt.warmup_ns = static_cast<int64_t>(args->warmup_s * 1e9);
    try {
      opt.mavlink = mavlink_options(file.mavlink, args->mavlink_udp, args->mavlink_serial);
    } catch (const std::invalid_argument& e) {
      throw UsageError(e.what());
    }
    if (args->status != "on" && args->status != "off" && args->status != "auto")
      throw UsageError("--status must be on, off or auto");
    opt.status_line =
        !args->quiet &&
        (args->status == "on" || (args->status == "auto" && opt.pace == drivers::ReplayPace::kRealtime));
    if (!args->view.endpoint.empty()) {
      opt.view = true;
      opt.view_options = view_server_options(args->view, "replay " + args->path);
      opt.view_wait_s = args->view.wait_s;
      opt.on_view_ready = [args](const viewer::Server& s) { print_view_ready(s, args->view); };
    } else if (app->count("--view-wait") + app->count("--view-clients") + app->count("--view-bandwidth") >
               0) {
      throw UsageError("--view-wait, --view-clients and --view-bandwidth need --view [ADDR:]PORT");
    }
    if (args->print_config) {
      // With a log, open it first: the settings printed are the ones a replay of it would run with.
      if (!args->path.empty()) {
        drivers::LogOpenOptions o = opt.open;
        o.format = opt.format;
        (void)drivers::open_log(opt.path, o);
      }
      std::cout << tools::estimator_config_to_yaml(*opt.config)
                << dense::dense_sections_yaml(opt.dense, opt.dense_view);
      return 0;
    }
    if (args->path.empty()) throw UsageError("replay: the log is required (unless --print-config)");
    // The map's outputs need a backend with a map: said before the replay, not after it.
    opt.check_before_start = [args](const core::Estimator& est) {
      if (est.has_map()) return;
      const std::string flag = !args->map_in.empty()               ? "--map-in"
                               : !args->loop_log.empty()           ? "--loop-log"
                               : !args->map_traj_out.empty()       ? "--map-traj-out"
                               : !args->map_final_traj_out.empty() ? "--map-final-traj-out"
                                                                   : "";
      if (!flag.empty()) throw UsageError(flag + ": the backend '" + est.name() + "' runs without a map");
    };
    const auto mcap = add_mcap_out(opt, args->mcap_out, file.ros2.map_points_rate_hz);
    const auto fox = add_foxglove(opt, args->foxglove, file.ros2.map_points_rate_hz, args->foxglove_wait_s);
    // The revisits need the log's ground truth and a second pass over its
    // depth: only when asked for.
    const bool loop_truth = !args->loop_log.empty() || !args->metrics_out.empty();
    opt.loop_log = loop_truth;
    ReplayReport r = run_replay(opt);
    if (mcap) mcap->close();
    if (fox) fox->server().stop();
    if (opt.loop_log && r.has_map) {
      drivers::LogOpenOptions o = opt.open;
      o.format = opt.format;
      const auto log = drivers::open_log(opt.path, o);
      r.loop_truth = evaluate_loops(*log, r.loop_log);
      if (!args->loop_log.empty()) write_loop_log(args->loop_log, r.loop_log, *r.loop_truth);
    }
    r.config = tools::estimator_config_entries(*opt.config);
    if (!args->traj_out.empty()) tools::write_tum(args->traj_out, r.trajectory);
    if (!args->map_traj_out.empty()) {
      tools::write_tum(args->map_traj_out, r.map_trajectory);
    }
    if (!args->metrics_out.empty()) {
      std::ofstream f(args->metrics_out);
      if (!f) throw std::runtime_error("cannot write " + args->metrics_out);
      f << replay_metrics_json(r);
    }
    if (!args->map_final_traj_out.empty()) {
      if (r.map_final_trajectory.empty()) {
        throw std::runtime_error(
            "--map-final-traj-out: the map holds no keyframe of this flight; nothing written to " +
            args->map_final_traj_out);
      }
      tools::write_tum(args->map_final_traj_out, r.map_final_trajectory);
    }
    if (!args->quiet) {
      std::cout << replay_summary(r);
      for (const auto& p : r.problems)
        std::cerr << "problem: " << p.where << ": " << p.kind << ": " << p.detail << "\n";
      if (!args->traj_out.empty()) std::cout << "trajectory: " << args->traj_out << "\n";
      if (!args->metrics_out.empty()) std::cout << "metrics: " << args->metrics_out << "\n";
      if (!args->map_out.empty()) std::cout << "map: " << args->map_out << "\n";
      if (!args->dense_out.empty()) std::cout << "dense map: " << args->dense_out << "\n";
      if (!args->dense_octomap_out.empty())
        std::cout << "dense occupancy: " << args->dense_octomap_out << "\n";
      if (!args->dense_map_out.empty()) std::cout << "dense map (map frame): " << args->dense_map_out << "\n";
      if (mcap) std::cout << "mcap: " << args->mcap_out << " (" << mcap->count() << " odometry messages)\n";
      if (fox) std::cout << foxglove::stats_summary(fox->server().stats());
    }
    return 0;
  };
  return cmd;
}

}  // namespace kestrel::cli
