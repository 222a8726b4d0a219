// `kestrel sim`: render an RGB-D + IMU log with ground truth (tools/sim).
#include <cstdio>
#include <memory>
#include <string>

#include "kestrel/commands.hpp"
#include "kestrel/drivers/log_export.hpp"
#include "kestrel/drivers/log_source.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/recording.hpp"
#include "kestrel/tools/simulator.hpp"

namespace kestrel::cli {
namespace {

struct SimArgs {
  tools::SimOptions o;
  int width = 640, height = 480;
  double fps = 30.0, imu_rate = 400.0;
  double duration = -1.0;
  bool fixed_yaw = false, no_noise = false;
  std::string export_eth3d;
  CLI::Option *width_opt = nullptr, *height_opt = nullptr, *fps_opt = nullptr, *imu_rate_opt = nullptr,
              *duration_opt = nullptr, *rig_offset_opt = nullptr;
  double rig_time_offset_ms = 0;
  ImageCompressionArgs compression;
};

}  // namespace

Subcommand add_sim_command(CLI::App& parent) {
  auto args = std::make_shared<SimArgs>();
  tools::SimOptions& o = args->o;
  CLI::App* app =
      parent.add_subcommand("sim", "render a simulated RGB-D + IMU log (.klog) with ground truth");
  app->footer(
      "Examples:\n"
      "  kestrel sim --scenario hover --duration 60 --seed 1 --out hover.klog\n"
      "  kestrel sim --trajectory ../shared/data/euroc/V1_02_medium/gt_body_20hz.csv \\\n"
      "              --imu ../shared/data/euroc/V1_02_medium/imu0.csv --out v102.klog\n"
      "  kestrel sim --images ../shared/data/real-rgbd/7scenes_first500 --out 7scenes_imu.klog\n"
      "Models and numbers: docs/simulator.md");

  auto* scen =
      app->add_option("--scenario", o.scenario, "built-in motion: hover, figure8, aggressive, static, hard")
          ->capture_default_str();
  auto* traj = app->add_option("--trajectory", o.trajectory_path,
                               "fly a ground-truth file instead (EuRoC gt csv or TUM groundtruth.txt)");
  scen->excludes(traj);
  auto* images =
      app->add_option("--images", o.images_path,
                      "real images: a recording with ground truth and no IMU (any reader's folder); its "
                      "frames are written with an IMU synthesised along its ground truth");
  images->excludes(scen)->excludes(traj);
  app->add_option("--images-format", o.images_format,
                  std::string("--images: the recording's format: ") + drivers::log_format_names())
      ->needs(images)
      ->capture_default_str();
  app->add_option(
         "--position-smoothing", o.position_smoothing,
         "--images: second-difference weight of the spline's positions (0: least squares on the knots)")
      ->needs(images)
      ->capture_default_str();
  app->add_option("--imu", o.imu_path,
                  "hybrid mode: write this real IMU (EuRoC imu0.csv) instead of a synthetic one")
      ->needs(traj);
  app->add_option("--out", o.out_path, "output .klog")->required();
  app->add_option(
      "--export-eth3d", args->export_eth3d,
      "also write the flight as an ETH3D SLAM folder here (same as `kestrel convert OUT --to eth3d`)");
  args->duration_opt = app->add_option("--duration", args->duration,
                                       "seconds (default: hover 189, others 60, a file: all of it)");
  app->add_option("--start", o.start_s, "seconds into the ground-truth file to start at")->needs(traj);
  app->add_option("--seed", o.seed, "fixes every random choice: same seed, same bytes")
      ->capture_default_str();
  args->width_opt = app->add_option("--width", args->width, "image width [px] (intrinsics scale with it)")
                        ->capture_default_str();
  args->height_opt = app->add_option("--height", args->height, "image height [px]")->capture_default_str();
  args->fps_opt =
      app->add_option(
             "--fps", args->fps,
             "camera rate [Hz] (a GT file: default its own sample times; --images: 7-Scenes' frame rate)")
          ->capture_default_str();
  args->imu_rate_opt =
      app->add_option("--imu-rate", args->imu_rate, "synthetic IMU rate [Hz]")->capture_default_str();
  app->add_option("--time-offset-ms", o.time_offset_ms,
                  "camera-IMU offset: frame stamps = true time - offset")
      ->capture_default_str();
  args->rig_offset_opt = app->add_option(
      "--rig-time-offset-ms", args->rig_time_offset_ms,
      "the offset the log's rig states (default: --time-offset-ms); another value makes a miscalibrated "
      "log whose remaining offset `window.estimate_time_offset` can find");
  app->add_option("--timestamp-jitter-us", o.timestamp_jitter_us, "std of frame stamp noise [us]")
      ->capture_default_str();
  app->add_option("--frame-drop-rate", o.frame_drop_rate, "probability a frame is lost")
      ->capture_default_str();
  app->add_option("--texture", o.texture_path,
                  "image file for walls, floor and ceiling (default: procedural)");
  app->add_option(
      "--room-m", o.room_m,
      "a hall at least this long on each side, walls up to this far from the path (0: a room around "
      "the flight; scenario hard: 24)");
  app->add_option("--exposure-change", o.exposure_change,
                  "image gain swings by up to +- this share (hard: 0.45)");
  app->add_option("--motion-blur-ms", o.motion_blur_ms,
                  "exposure time rendered as averaged sub-frames (hard: 8)");
  app->add_flag("--bare-wall", o.bare_wall, "the +x wall is bare paint, a low-texture wall (hard: on)");
  app->add_option("--cover-at", o.cover_at_s, "cover the lens at this time [s] (with --cover-s: a kidnap)");
  app->add_option(
      "--cover-s", o.cover_s,
      "seconds the lens stays covered: near-black noise frames without depth while the flight goes on");
  app->add_flag("--no-noise", args->no_noise,
                "ideal sensors: no IMU noise or bias, exact depth, clean images");
  app->add_flag(
      "--stereo", o.stereo,
      "render a stereo pair (a right camera beside the left) instead of depth images (docs/stereo.md)");
  app->add_option("--stereo-baseline-m", o.stereo_baseline_m,
                  "stereo: right camera along the left camera's x [m]")
      ->capture_default_str();
  app->add_option("--depth-dropout", o.depth_dropout, "share of depth pixels lost in small blobs")
      ->capture_default_str();
  app->add_option("--image-noise", o.image_noise_sigma, "colour noise std [8-bit DN]")->capture_default_str();
  app->add_option("--acc-bias-tau", o.acc_bias_tau_s,
                  "accelerometer bias time constant [s] (paper 000 eq. 6)")
      ->capture_default_str();
  app->add_option(
      "--rig", o.rig_path,
      "rig YAML (camera, T_BC, depth, imu); default: built-in rig (--images: the recording's own, with "
      "this file's calibration where it lacks one and its IMU noise)");
  app->add_flag("--fixed-yaw", args->fixed_yaw, "figure8: keep the heading fixed instead of along the path");
  app->add_option("--gt-rate", o.gt_rate_hz, "ground-truth record rate [Hz]")->capture_default_str();
  app->add_option("--knot-spacing", o.knot_spacing_s,
                  "GT spline knot spacing [s] (default: the file's interval; --images: 0.1)");
  app->add_option("--threads", o.threads, "render threads")->capture_default_str();
  add_image_compression_options(app, args->compression);

  Subcommand cmd;
  cmd.app = app;
  cmd.run = [args]() -> int {
    tools::SimOptions opt = args->o;
    if (args->width_opt->count()) opt.width = args->width;
    if (args->height_opt->count()) opt.height = args->height;
    if (args->fps_opt->count()) opt.fps = args->fps;
    if (args->imu_rate_opt->count()) opt.imu_rate_hz = args->imu_rate;
    if (args->rig_offset_opt->count()) opt.rig_time_offset_ms = args->rig_time_offset_ms;
    if (args->duration_opt->count()) {
      if (!(args->duration > 0.0)) throw UsageError("--duration must be > 0");
      opt.duration_s = args->duration;
    }
    opt.noise = !args->no_noise;
    opt.image_compression = image_compression_from(args->compression);
    opt.yaw_follows_path = !args->fixed_yaw;
    tools::SimSummary s;
    try {
      s = tools::run_simulation(opt);
    } catch (const tools::SimOptionError& e) {
      throw UsageError(e.what());
    }
    std::printf("kestrel sim: wrote %s\n%s", opt.out_path.c_str(), tools::format_summary(s).c_str());
    for (size_t k = 0; k < s.problems.size() && k < 5; ++k) {
      std::printf("  %s: %s: %s\n", s.problems[k].where.c_str(), s.problems[k].kind.c_str(),
                  s.problems[k].detail.c_str());
    }
    if (s.problems.size() > 5) std::printf("  ... %zu more reader problems\n", s.problems.size() - 5);
    if (!args->export_eth3d.empty()) {
      auto src = drivers::open_log(opt.out_path);
      const drivers::ExportStats st = drivers::export_eth3d(*src, args->export_eth3d);
      std::printf("kestrel sim: ETH3D folder %s (%llu frames, %llu IMU samples)\n",
                  args->export_eth3d.c_str(), static_cast<unsigned long long>(st.rgb),
                  static_cast<unsigned long long>(st.imu));
    }
    return 0;
  };
  return cmd;
}

}  // namespace kestrel::cli
