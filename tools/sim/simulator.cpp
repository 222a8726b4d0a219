// run_simulation: options -> rig, trajectory, IMU, scene, then one pass in
// time order that renders frames and streams every record to the sink.
#include "kestrel/tools/simulator.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <vector>

namespace kestrel::tools {
namespace {

namespace fs = std::filesystem;

void require(bool ok, const std::string& msg) {
  if (!ok) throw SimOptionError(msg);
}

void require_file(const std::string& path, const char* what) {
  require(fs::exists(path), std::string(what) + " '" + path + "': no such file");
}

void validate(const SimOptions& o) {
  const bool from_file = !o.trajectory_path.empty();
  if (!o.images_path.empty()) {
    require(fs::exists(o.images_path), "--images '" + o.images_path + "': no such file or folder");
    require(!from_file && o.imu_path.empty(),
            "--images takes its motion from the recording: no --trajectory or --imu");
    require(o.knot_spacing_s >= 0.0 && o.knot_spacing_s <= 2.0, "--knot-spacing must be in [0, 2] s");
    require(o.position_smoothing >= 0.0, "--position-smoothing must be >= 0");
    if (!o.rig_path.empty()) require_file(o.rig_path, "--rig");
    if (o.fps) require(*o.fps > 0.0 && *o.fps <= 1000.0, "--fps must be in (0, 1000]");
    if (o.imu_rate_hz)
      require(*o.imu_rate_hz > 0.0 && *o.imu_rate_hz <= 10000.0, "--imu-rate must be in (0, 10000]");
    return;
  }
  if (!from_file) {
    const auto names = scenario_names();
    require(std::find(names.begin(), names.end(), o.scenario) != names.end(),
            "--scenario '" + o.scenario + "' is not one of hover, figure8, aggressive, static, hard");
    require(o.start_s == 0.0, "--start applies to --trajectory files only");
    require(o.imu_path.empty(), "--imu (hybrid mode) needs --trajectory");
  } else {
    require_file(o.trajectory_path, "--trajectory");
    require(o.start_s >= 0.0, "--start must be >= 0");
  }
  if (!o.imu_path.empty()) require_file(o.imu_path, "--imu");
  if (!o.texture_path.empty()) require_file(o.texture_path, "--texture");
  if (!o.rig_path.empty()) require_file(o.rig_path, "--rig");
  if (o.width) require(*o.width >= 16 && *o.width <= 8192, "--width must be in [16, 8192]");
  if (o.height) require(*o.height >= 16 && *o.height <= 8192, "--height must be in [16, 8192]");
  if (o.fps) require(*o.fps > 0.0 && *o.fps <= 1000.0, "--fps must be in (0, 1000]");
  if (o.imu_rate_hz)
    require(*o.imu_rate_hz > 0.0 && *o.imu_rate_hz <= 10000.0, "--imu-rate must be in (0, 10000]");
  require(std::abs(o.time_offset_ms) <= 1000.0, "--time-offset-ms must be within +-1000");
  require(!o.rig_time_offset_ms || std::abs(*o.rig_time_offset_ms) <= 1000.0,
          "--rig-time-offset-ms must be within +-1000");
  require(o.timestamp_jitter_us >= 0.0 && o.timestamp_jitter_us <= 1e5,
          "--timestamp-jitter-us must be in [0, 1e5]");
  require(o.frame_drop_rate >= 0.0 && o.frame_drop_rate < 1.0, "--frame-drop-rate must be in [0, 1)");
  require(o.cover_s <= 0.0 || o.cover_at_s >= 0.0, "--cover-at must be >= 0 seconds");
  require(o.depth_dropout >= 0.0 && o.depth_dropout <= 0.5, "--depth-dropout must be in [0, 0.5]");
  require(o.image_noise_sigma >= 0.0 && o.image_noise_sigma <= 50.0, "image noise sigma must be in [0, 50]");
  require(o.acc_bias_tau_s >= 0.0, "accelerometer bias tau must be >= 0");
  require(o.room_m >= 0.0 && o.room_m <= 200.0, "--room-m must be in [0, 200]");
  require(o.exposure_change >= 0.0 && o.exposure_change <= 0.9, "--exposure-change must be in [0, 0.9]");
  require(o.motion_blur_ms >= 0.0 && o.motion_blur_ms <= 50.0, "--motion-blur-ms must be in [0, 50]");
  require(o.gt_rate_hz > 0.0 && o.gt_rate_hz <= 10000.0, "ground-truth rate must be in (0, 10000]");
  require(o.threads >= 1 && o.threads <= 64, "threads must be in [1, 64]");
}

GroundTruthPose gt_record(const TrajectoryState& s, int64_t t_ns) {
  GroundTruthPose g;
  g.t_ns = t_ns;
  g.p_WB = {s.p_WB.x(), s.p_WB.y(), s.p_WB.z()};
  g.q_WB = {s.q_WB.w(), s.q_WB.x(), s.q_WB.y(), s.q_WB.z()};
  g.has_velocity = true;
  g.v_WB = {s.v_WB.x(), s.v_WB.y(), s.v_WB.z()};
  return g;
}

std::string fmt(const char* f, double a, double b, double c) {
  char buf[128];
  std::snprintf(buf, sizeof buf, f, a, b, c);
  return buf;
}

int64_t to_ns(double s) { return static_cast<int64_t>(std::llround(s * 1e9)); }

struct FrameSlot {
  double t_true_s = 0.0;
  int64_t stamp_ns = 0;
  uint32_t seq = 0;
  bool dropped = false;
};

}  // namespace

SimSummary run_simulation(const SimOptions& o, SimSink& sink) {
  using Clock = std::chrono::steady_clock;
  const auto wall0 = Clock::now();
  validate(o);
  if (!o.images_path.empty()) {
    SimSummary s = run_image_simulation(o, sink);
    s.real_images = true;
    return s;
  }
  const bool from_file = !o.trajectory_path.empty();
  const bool hybrid = !o.imu_path.empty();

  // ---- rig and IMU model ----
  Rig rig = default_sim_rig(640, 480, 30.0, 400.0);
  ImuModel model = ImuModel::bmx055(o.acc_bias_tau_s);
  if (!o.rig_path.empty()) load_sim_rig_yaml(o.rig_path, rig, model);
  if (o.width || o.height) {
    // Keep the field of view: scale the intrinsics to the new size.
    const int w = o.width.value_or(rig.rgb.width), h = o.height.value_or(rig.rgb.height);
    const double sx = static_cast<double>(w) / rig.rgb.width, sy = static_cast<double>(h) / rig.rgb.height;
    rig.rgb.fx *= sx;
    rig.rgb.cx = (rig.rgb.cx + 0.5) * sx - 0.5;
    rig.rgb.fy *= sy;
    rig.rgb.cy = (rig.rgb.cy + 0.5) * sy - 0.5;
    rig.rgb.width = w;
    rig.rgb.height = h;
  }
  if (o.fps) rig.camera_rate_hz = *o.fps;
  if (o.imu_rate_hz) rig.imu_rate_hz = *o.imu_rate_hz;
  if (hybrid) {
    // The real IMU's own noise figures; EuRoC's ADIS16448 when the sensor file is missing.
    const fs::path dir = fs::path(o.imu_path).parent_path();
    double rate = 200.0;
    if (!read_euroc_imu_yaml((dir / "imu0_sensor.yaml").string(), model, rate)) {
      model = ImuModel{};
      model.gyro_noise_density_rad_s_sqrthz = 1.6968e-4;
      model.gyro_random_walk_rad_s2_sqrthz = 1.9393e-5;
      model.acc_noise_density_mps2_sqrthz = 2.0e-3;
      model.acc_random_walk_mps3_sqrthz = 3.0e-3;
    }
    rig.imu_rate_hz = rate;
    Eigen::Isometry3d T_BS;
    if (read_euroc_T_BS((dir / "cam0_sensor.yaml").string(), T_BS)) rig.T_BC = to_mat4(T_BS);
    rig.name = "kestrel-sim-hybrid";
  } else if (!o.noise) {
    model = model.ideal();
  }
  rig.imu = model.to_rig();
  // A rig file's own offset stands unless an offset is asked for.
  if (o.rig_path.empty() || o.time_offset_ms != 0.0)
    rig.time_offset_cam_imu_ns = to_ns(o.time_offset_ms * 1e-3);
  // The stamps carry the true offset; the log's rig may claim another (a
  // miscalibrated rig, for the online estimate to find the difference).
  const int64_t true_offset_ns = rig.time_offset_cam_imu_ns;
  if (o.rig_time_offset_ms) rig.time_offset_cam_imu_ns = to_ns(*o.rig_time_offset_ms * 1e-3);
  const Eigen::Isometry3d T_BC = to_isometry(rig.T_BC);
  // The right camera: the left one moved along its own x (an ideal, already rectified pair).
  const Eigen::Isometry3d T_BC1 = T_BC * Eigen::Translation3d(o.stereo_baseline_m, 0, 0);
  if (o.stereo) {
    if (!(o.stereo_baseline_m > 0)) throw std::invalid_argument("--stereo-baseline-m: must be > 0");
    rig.stereo.present = true;
    rig.stereo.intrinsics = rig.rgb;
    rig.stereo.T_BC1 = to_mat4(T_BC1);
  }

  // ---- trajectory ----
  std::unique_ptr<MotionModel> traj;
  if (from_file) {
    SplineTrajectory::FitOptions fo;
    fo.knot_spacing_s = o.knot_spacing_s;
    try {
      traj = std::make_unique<SplineTrajectory>(
          SplineTrajectory::from_file(o.trajectory_path, o.start_s, o.duration_s, fo));
    } catch (const SimOptionError&) {
      throw;
    } catch (const std::invalid_argument& e) {  // a --start/--duration span with too few samples
      throw SimOptionError(e.what());
    }
  } else {
    ScenarioOptions so;
    so.yaw_follows_path = o.yaw_follows_path;
    traj = make_scenario(o.scenario, o.duration_s, so);
  }
  const double T = traj->duration_s();
  const int64_t t0 = traj->t0_ns();

  // ---- camera frames: true times, stamps, drops ----
  std::vector<double> cam_times = traj->sample_times_s();
  bool at_samples = false;
  if (!o.fps && cam_times.size() >= 2) {
    const double rate = (cam_times.size() - 1) / std::max(1e-9, cam_times.back() - cam_times.front());
    at_samples = rate <= 60.0;
  }
  if (at_samples) {
    rig.camera_rate_hz = (cam_times.size() - 1) / std::max(1e-9, cam_times.back() - cam_times.front());
  } else {
    if (from_file && !o.fps) rig.camera_rate_hz = 30.0;
    cam_times.clear();
    for (int64_t k = 0;; ++k) {
      const double t = static_cast<double>(k) / rig.camera_rate_hz;
      if (t > T + 1e-9) break;
      cam_times.push_back(t);
    }
  }
  std::vector<FrameSlot> frames(cam_times.size());
  {
    SimRng rng(o.seed, RngStream::kCamera);
    const double period_ns = 1e9 / rig.camera_rate_hz;
    for (size_t k = 0; k < frames.size(); ++k) {
      const double jitter = rng.normal() * o.timestamp_jitter_us * 1e3;
      const bool drop = rng.uniform() < o.frame_drop_rate;
      FrameSlot& f = frames[k];
      f.t_true_s = cam_times[k];
      f.seq = static_cast<uint32_t>(k);
      f.dropped = drop;
      // Clipped so stamps keep their order.
      f.stamp_ns = t0 + to_ns(f.t_true_s) - true_offset_ns +
                   static_cast<int64_t>(std::llround(std::clamp(jitter, -0.4 * period_ns, 0.4 * period_ns)));
    }
  }

  // ---- ground-truth times: a regular grid plus every frame's true time ----
  std::vector<int64_t> gt_times;
  for (int64_t k = 0;; ++k) {
    const double t = static_cast<double>(k) / o.gt_rate_hz;
    if (t > T + 1e-9) break;
    gt_times.push_back(to_ns(t));
  }
  for (const FrameSlot& f : frames) gt_times.push_back(to_ns(f.t_true_s));
  std::sort(gt_times.begin(), gt_times.end());
  gt_times.erase(std::unique(gt_times.begin(), gt_times.end()), gt_times.end());

  // ---- IMU ----
  std::vector<ImuSample> real_imu;
  if (hybrid) {
    for (const ImuSample& s : load_euroc_imu_csv(o.imu_path))
      if (s.t_ns >= t0 && s.t_ns <= t0 + to_ns(T)) real_imu.push_back(s);
    for (size_t k = 0; k < real_imu.size(); ++k) real_imu[k].seq = static_cast<uint32_t>(k);
  }
  ImuSynth synth(model, rig.imu_rate_hz, rig.gravity_mps2, o.seed);
  const uint64_t n_synth = hybrid ? 0 : static_cast<uint64_t>(std::floor(T * rig.imu_rate_hz + 1e-9)) + 1;
  const uint64_t n_imu = hybrid ? real_imu.size() : n_synth;
  auto imu_time = [&](uint64_t k) {
    return hybrid ? real_imu[k].t_ns : t0 + to_ns(static_cast<double>(k) / rig.imu_rate_hz);
  };

  // ---- scene and renderer ----
  // The hard scenario is a large hall with every difficult condition on
  // (an explicit option still wins where it asks for more).
  const bool hard = !from_file && o.scenario == "hard";
  const double room_m = o.room_m > 0.0 ? o.room_m : (hard ? 24.0 : 0.0);
  const double exposure_change = std::max(o.exposure_change, hard ? 0.45 : 0.0);
  const double motion_blur_ms = std::max(o.motion_blur_ms, hard ? 8.0 : 0.0);
  SceneOptions scene_opt;
  if (room_m > 0.0) {
    scene_opt.min_room_m = room_m;
    scene_opt.max_wall_distance_m = room_m;
    scene_opt.margin_m = std::max(scene_opt.margin_m, 0.5 * room_m);
    scene_opt.min_height_m = std::max(scene_opt.min_height_m, 0.25 * room_m);
    // Clutter stays as dense as in a room; the cap keeps a hall's render time bounded.
    scene_opt.max_clutter = 250;
  }
  const Scene scene = Scene::build(*traj, T_BC, o.seed, scene_opt);
  RenderOptions ro;
  ro.bare_surface = (o.bare_wall || hard) ? 1 : -1;
  ro.threads = o.threads;
  ro.depth_noise = o.noise;
  ro.dropout_fraction = o.noise ? o.depth_dropout : 0.0;
  ro.image_noise_sigma = o.noise ? o.image_noise_sigma : 0.0;
  ro.texture_path = o.texture_path;
  ro.seed = o.seed;
  const Renderer renderer(scene, rig.rgb, rig.depth, ro);
  const int W = rig.rgb.width, H = rig.rgb.height;
  std::vector<uint8_t> rgb(static_cast<size_t>(W) * H * 3);
  std::vector<uint16_t> depth(static_cast<size_t>(W) * H);
  uint32_t cover_lcg = 12345;  // the covered lens's noise
  // Motion blur: sub-frames across the exposure, averaged; the depth is the
  // middle one's (a structured-light or ToF sensor integrates differently).
  const int blur_subframes = motion_blur_ms > 0.0 ? 4 : 1;
  std::vector<uint8_t> sub_rgb(blur_subframes > 1 ? rgb.size() : 0);
  std::vector<uint16_t> sub_depth(blur_subframes > 1 ? depth.size() : 0);
  std::vector<uint16_t> acc(blur_subframes > 1 ? rgb.size() : 0);
  // Auto-exposure as a camera does it: a slow drift and a step every few
  // seconds, the same for every run of a seed.
  auto gain_at = [&](double t) {
    if (exposure_change <= 0.0) return 1.0;
    const double drift = 0.6 * std::sin(2.0 * 3.14159265358979 * t / 7.0);
    const double step = (static_cast<int64_t>(std::floor(t / 3.0)) % 2 == 0) ? 0.4 : -0.4;
    return 1.0 + exposure_change * (drift + step);
  };

  // One camera's image of a frame: motion blur, exposure gain and a covered lens applied alike to both
  // cameras of a stereo pair. The right camera's noise is seeded apart (seq with the top bit set).
  std::vector<uint8_t> rgb_right(o.stereo ? rgb.size() : 0);
  std::vector<uint16_t> depth_right(o.stereo ? depth.size() : 0);
  auto render_view = [&](const FrameSlot& f, const Eigen::Isometry3d& T_BCx, uint32_t seq,
                         std::vector<uint8_t>& out, std::vector<uint16_t>& out_depth) {
    if (blur_subframes == 1) {
      const TrajectoryState s = traj->state(f.t_true_s);
      renderer.render(Eigen::Translation3d(s.p_WB) * s.q_WB * T_BCx, seq, out.data(), out_depth.data());
    } else {
      std::fill(acc.begin(), acc.end(), 0);
      for (int j = 0; j < blur_subframes; ++j) {
        const double dt = (static_cast<double>(j) / (blur_subframes - 1) - 0.5) * motion_blur_ms * 1e-3;
        const TrajectoryState s = traj->state(std::clamp(f.t_true_s + dt, 0.0, T));
        const bool middle = j == blur_subframes / 2;
        renderer.render(Eigen::Translation3d(s.p_WB) * s.q_WB * T_BCx, seq, sub_rgb.data(),
                        middle ? out_depth.data() : sub_depth.data());
        for (size_t i = 0; i < acc.size(); ++i) acc[i] = static_cast<uint16_t>(acc[i] + sub_rgb[i]);
      }
      for (size_t i = 0; i < acc.size(); ++i)
        out[i] = static_cast<uint8_t>((acc[i] + blur_subframes / 2) / blur_subframes);
    }
    if (exposure_change > 0.0) {
      const double g = gain_at(f.t_true_s);
      for (uint8_t& p : out) p = static_cast<uint8_t>(std::min(255.0, p * g + 0.5));
    }
    if (o.cover_s > 0.0 && f.t_true_s >= o.cover_at_s && f.t_true_s < o.cover_at_s + o.cover_s) {
      // Noise, not a constant: identical frames would be withheld as repeats.
      for (uint8_t& p : out) p = static_cast<uint8_t>((cover_lcg = cover_lcg * 1664525u + 1013904223u) >> 30);
      std::fill(out_depth.begin(), out_depth.end(), 0);
    }
  };

  SimSummary sum;
  sum.trajectory = traj->description();
  sum.hybrid = hybrid;
  sum.duration_s = T;
  sum.room_size_m = scene.room.sizes();
  sum.clutter_objects = scene.boxes.size() + scene.cylinders.size();
  sum.rig = rig;

  // ---- one pass in time order: IMU, then ground truth, then frames on ties ----
  sink.begin(rig);
  {
    Event e;
    e.t_ns = frames.empty() ? t0 : std::min(t0, frames.front().stamp_ns);  // first record, in time order
    e.code = EventCode::kInfo;
    e.text = "kestrel sim: " + traj->description() + (hybrid ? " + real IMU " + o.imu_path : "") + ", seed " +
             std::to_string(o.seed) + ", room " +
             fmt("%.2f x %.2f x %.2f m", sum.room_size_m.x(), sum.room_size_m.y(), sum.room_size_m.z()) +
             ", " + std::to_string(sum.clutter_objects) + " objects";
    sink.event(e);
    ++sum.events;
  }
  // True biases once a second, parseable: "true_bias gyro_rps=x,y,z acc_mps2=x,y,z".
  int64_t next_bias_event = t0;

  uint64_t ki = 0;
  size_t kg = 0, kf = 0;
  double render_s = 0.0;
  while (ki < n_imu || kg < gt_times.size() || kf < frames.size()) {
    const int64_t ti = ki < n_imu ? imu_time(ki) : INT64_MAX;
    const int64_t tg = kg < gt_times.size() ? t0 + gt_times[kg] : INT64_MAX;
    const int64_t tf = kf < frames.size() ? frames[kf].stamp_ns : INT64_MAX;
    if (ti <= tg && ti <= tf) {
      if (hybrid) {
        sink.imu(real_imu[ki]);
      } else {
        const TrajectoryState s = traj->state(1e-9 * static_cast<double>(ti - t0));
        const ImuSample m = synth.sample(s, ti);
        if (m.flags & (kImuGyroSaturated | kImuAccSaturated)) ++sum.imu_saturated;
        if (ti >= next_bias_event && o.noise) {
          Event e;
          e.t_ns = ti;
          e.code = EventCode::kInfo;
          const Eigen::Vector3d& bg = synth.gyro_bias_rps();
          const Eigen::Vector3d& ba = synth.acc_bias_mps2();
          e.text = "true_bias gyro_rps=" + fmt("%.9g,%.9g,%.9g", bg.x(), bg.y(), bg.z()) +
                   " acc_mps2=" + fmt("%.9g,%.9g,%.9g", ba.x(), ba.y(), ba.z());
          sink.event(e);
          ++sum.events;
          next_bias_event += 1'000'000'000;
        }
        sink.imu(m);
      }
      ++ki;
      ++sum.imu_samples;
    } else if (tg <= tf) {
      sink.ground_truth(gt_record(traj->state(1e-9 * static_cast<double>(gt_times[kg])), tg));
      ++kg;
      ++sum.gt_records;
    } else {
      const FrameSlot& f = frames[kf++];
      if (f.dropped) {
        ++sum.frames_dropped;
        continue;
      }
      const auto r0 = Clock::now();
      render_view(f, T_BC, f.seq, rgb, depth);
      if (o.stereo) render_view(f, T_BC1, f.seq ^ 0x80000000u, rgb_right, depth_right);
      render_s += std::chrono::duration<double>(Clock::now() - r0).count();
      sink.image(drivers::RecordType::kRgb, f.stamp_ns, f.seq,
                 ImageView{W, H, W * 3, PixelFormat::kRgb8, rgb.data()});
      if (o.stereo) {
        sink.image(drivers::RecordType::kRight, f.stamp_ns, f.seq,
                   ImageView{W, H, W * 3, PixelFormat::kRgb8, rgb_right.data()});
      } else {
        sink.image(
            drivers::RecordType::kDepth, f.stamp_ns, f.seq,
            ImageView{W, H, W * 2, PixelFormat::kDepthU16, reinterpret_cast<const uint8_t*>(depth.data())});
      }
      ++sum.frames;
    }
  }
  sink.end();
  sum.render_s = render_s;
  sum.render_fps = render_s > 0.0 ? static_cast<double>(sum.frames) / render_s : 0.0;
  sum.output_bytes = sink.bytes();
  sum.wall_s = std::chrono::duration<double>(Clock::now() - wall0).count();
  return sum;
}

std::string format_summary(const SimSummary& s) {
  char buf[1024];
  if (s.real_images) {
    std::snprintf(buf, sizeof buf,
                  "trajectory   %s, %.1f s\n"
                  "spline       %.1f mm RMS from the ground truth (max %.1f mm, %.2f deg)\n"
                  "frames       %llu real (%dx%d @ %.1f Hz)\n"
                  "imu          %llu samples @ %.0f Hz (synthesised), %llu saturated\n"
                  "ground truth %llu poses, %llu events, %zu reader problems\n"
                  "total        %.2f s, output %.1f MB\n",
                  s.trajectory.c_str(), s.duration_s, 1e3 * s.spline_rms_position_residual_m,
                  1e3 * s.spline_max_position_residual_m, s.spline_max_rotation_residual_rad * 180.0 / M_PI,
                  static_cast<unsigned long long>(s.frames), s.rig.rgb.width, s.rig.rgb.height,
                  s.rig.camera_rate_hz, static_cast<unsigned long long>(s.imu_samples), s.rig.imu_rate_hz,
                  static_cast<unsigned long long>(s.imu_saturated),
                  static_cast<unsigned long long>(s.gt_records), static_cast<unsigned long long>(s.events),
                  s.problems.size(), s.wall_s, static_cast<double>(s.output_bytes) / 1e6);
    return buf;
  }
  std::snprintf(buf, sizeof buf,
                "trajectory   %s%s, %.1f s\n"
                "scene        room %.1f x %.1f x %.1f m, %zu objects\n"
                "frames       %llu written (%dx%d @ %.1f Hz), %llu dropped\n"
                "imu          %llu samples @ %.0f Hz%s, %llu saturated\n"
                "ground truth %llu poses, %llu events\n"
                "render       %.1f frames/s (%.2f s)\n"
                "total        %.2f s, output %.1f MB\n",
                s.trajectory.c_str(), s.hybrid ? " (hybrid: real IMU)" : "", s.duration_s, s.room_size_m.x(),
                s.room_size_m.y(), s.room_size_m.z(), s.clutter_objects,
                static_cast<unsigned long long>(s.frames), s.rig.rgb.width, s.rig.rgb.height,
                s.rig.camera_rate_hz, static_cast<unsigned long long>(s.frames_dropped),
                static_cast<unsigned long long>(s.imu_samples), s.rig.imu_rate_hz, s.hybrid ? " (real)" : "",
                static_cast<unsigned long long>(s.imu_saturated),
                static_cast<unsigned long long>(s.gt_records), static_cast<unsigned long long>(s.events),
                s.render_fps, s.render_s, s.wall_s, static_cast<double>(s.output_bytes) / 1e6);
  return buf;
}

}  // namespace kestrel::tools
