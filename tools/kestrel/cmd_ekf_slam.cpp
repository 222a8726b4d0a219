// `kestrel ekf-slam`: the EKF backend (core/ekf_slam.hpp) on paper 003's own
// data, a KITTI .npz of stereo feature tracks and IMU-frame velocities.
// Writes the trajectory (TUM), the landmark map (PLY) and a top view (SVG)
// like the paper's figure 3, and prints the run time.
#include <Eigen/Geometry>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "kestrel/commands.hpp"
#include "kestrel/core/ekf_slam.hpp"
#include "kestrel/drivers/npz_reader.hpp"
#include "kestrel/tools/trajectory_eval.hpp"

namespace kestrel::cli {
namespace {

struct EkfArgs {
  std::string npz;
  std::string traj_out, map_out, plot_out;
  std::string extrinsic = "auto";
  int capacity = 256;
  // Tuned on the innovations of 0027 (docs/ekf.md): the OXTS velocities in
  // these files carry ~0.5 m/s of noise across the car's axes.
  double pixel_sigma = 2.0;
  double vel_sigma = 1.0;
  double gyro_sigma = 0.1;
  double max_depth = 60.0;
  int steps = 0;
  bool no_update = false;
};

using Clock = std::chrono::steady_clock;
double seconds_since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

core::ekf::Pose pose_from_rowmajor(const double* T) {
  core::ekf::Pose P;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) P.R(r, c) = T[4 * r + c];
    P.p(r) = T[4 * r + 3];
  }
  return P;
}

// Which way the stored cam_T_imu maps (docs/ekf.md) is decided from the
// data, not assumed: the car drives forward, so the camera's optical axis must
// point along the mean velocity. (In these files it is camera-from-IMU, as named.)
core::ekf::Pose camera_from_imu(const drivers::KittiVislamSequence& seq, const std::string& mode) {
  core::ekf::Pose stored = pose_from_rowmajor(seq.cam_T_imu);  // not const: returned, so moved
  if (mode == "as-stored") return stored;
  if (mode == "inverse") return stored.inverse();
  Eigen::Vector3d v_mean = Eigen::Vector3d::Zero();
  for (size_t i = 0; i < seq.num_steps(); ++i) v_mean += Eigen::Vector3d(&seq.v_B_mps[3 * i]);
  if (v_mean.norm() < 1e-6) {
    throw std::runtime_error(seq.path +
                             ": cannot tell the extrinsic's direction (no motion); pass --extrinsic");
  }
  v_mean.normalize();
  // Optical axis in the IMU frame: R_BC e_z.
  const double as_stored = stored.R.row(2).dot(v_mean);  // stored = T_CB: R_BC = R^T
  const double inverse = stored.R.col(2).dot(v_mean);    // stored = T_BC
  std::printf(
      "extrinsic: optical axis . mean velocity = %.3f if cam_T_imu maps IMU->camera, %.3f if camera->IMU\n",
      as_stored, inverse);
  if (inverse > 0.7 && inverse > as_stored) return stored.inverse();
  if (as_stored > 0.7) return stored;
  throw std::runtime_error(seq.path +
                           ": cannot tell the extrinsic's direction from the data; pass --extrinsic");
}

void write_ply(const std::string& path, const std::vector<core::FrozenLandmark>& map) {
  std::ofstream f(path);
  if (!f) throw std::runtime_error(path + ": cannot write");
  f << "ply\nformat ascii 1.0\ncomment kestrel ekf-slam landmark map, world frame = IMU frame at the first "
       "step [m]\n"
    << "element vertex " << map.size() << "\nproperty float x\nproperty float y\nproperty float z\n"
    << "property float sigma\nproperty uint observations\nend_header\n";
  char buf[160];
  for (const auto& m : map) {
    std::snprintf(buf, sizeof buf, "%.4f %.4f %.4f %.4f %u\n", m.p_W.x(), m.p_W.y(), m.p_W.z(),
                  std::sqrt(std::max(0.0, m.cov.trace())), m.observations);
    f << buf;
  }
  if (!f) throw std::runtime_error(path + ": write failed");
}

// Top view (x-y) of the landmarks and the trajectories, like paper 003's fig. 3.
void write_top_view(const std::string& path, const std::string& title,
                    const std::vector<Eigen::Vector3d>& ekf, const std::vector<Eigen::Vector3d>& dead,
                    const std::vector<core::FrozenLandmark>& map) {
  double x0 = 1e300, x1 = -1e300, y0 = 1e300, y1 = -1e300;
  for (const auto* tr : {&ekf, &dead}) {
    for (const auto& p : *tr) {
      x0 = std::min(x0, p.x()), x1 = std::max(x1, p.x());
      y0 = std::min(y0, p.y()), y1 = std::max(y1, p.y());
    }
  }
  const double pad = 0.15 * std::max({x1 - x0, y1 - y0, 10.0});
  x0 -= pad, x1 += pad, y0 -= pad, y1 += pad;
  const double W = 900.0, margin = 50.0;
  const double s = (W - 2 * margin) / std::max(x1 - x0, y1 - y0);
  const double H = 2 * margin + s * (y1 - y0) + 30.0;
  auto X = [&](double x) { return margin + s * (x - x0); };
  auto Y = [&](double y) { return H - margin - s * (y - y0); };
  std::ofstream f(path);
  if (!f) throw std::runtime_error(path + ": cannot write");
  char buf[256];
  std::snprintf(
      buf, sizeof buf,
      "<svg xmlns='http://www.w3.org/2000/svg' width='%.0f' height='%.0f' font-family='sans-serif' "
      "font-size='13'>\n"
      "<rect width='100%%' height='100%%' fill='white'/>\n<text x='%.0f' y='24' font-size='16'>%s</text>\n",
      W, H, margin, title.c_str());
  f << buf;
  f << "<g fill='#1f5fbf' fill-opacity='0.5'>\n";
  for (const auto& m : map) {
    const double x = m.p_W.x(), y = m.p_W.y();
    if (x < x0 || x > x1 || y < y0 || y > y1) continue;
    std::snprintf(buf, sizeof buf, "<circle cx='%.1f' cy='%.1f' r='1.3'/>\n", X(x), Y(y));
    f << buf;
  }
  f << "</g>\n";
  auto polyline = [&](const std::vector<Eigen::Vector3d>& tr, const char* style) {
    f << "<polyline fill='none' " << style << " points='";
    for (const auto& p : tr) {
      std::snprintf(buf, sizeof buf, "%.1f,%.1f ", X(p.x()), Y(p.y()));
      f << buf;
    }
    f << "'/>\n";
  };
  polyline(dead, "stroke='#888' stroke-width='1.5' stroke-dasharray='6,4'");
  polyline(ekf, "stroke='#8b1fa9' stroke-width='2.5'");
  // Scale bar and legend.
  double bar = 1.0;
  while (bar * s < 80.0) bar *= (bar * 2 * s < 80.0 ? 10.0 : 2.0);
  std::snprintf(buf, sizeof buf,
                "<line x1='%.0f' y1='%.0f' x2='%.0f' y2='%.0f' stroke='black' stroke-width='2'/>"
                "<text x='%.0f' y='%.0f'>%g m</text>\n",
                margin, H - 20, margin + bar * s, H - 20, margin + bar * s + 6, H - 16, bar);
  f << buf;
  std::snprintf(buf, sizeof buf,
                "<text x='%.0f' y='%.0f' fill='#8b1fa9'>EKF trajectory</text>"
                "<text x='%.0f' y='%.0f' fill='#888'>velocity dead reckoning</text>"
                "<text x='%.0f' y='%.0f' fill='#1f5fbf'>landmarks (%zu)</text>\n",
                W - 380, H - 16, W - 260, H - 16, W - 380, H - 34, map.size());
  f << buf << "</svg>\n";
  if (!f) throw std::runtime_error(path + ": write failed");
}

int run_ekf_slam(const EkfArgs& a) {
  if (a.capacity < 1) throw UsageError("--capacity must be >= 1");
  if (a.extrinsic != "auto" && a.extrinsic != "as-stored" && a.extrinsic != "inverse")
    throw UsageError("--extrinsic must be auto, as-stored or inverse, got '" + a.extrinsic + "'");
  const auto t_load = Clock::now();
  const drivers::KittiVislamSequence seq = drivers::load_kitti_vislam_npz(a.npz);
  const double load_s = seconds_since(t_load);
  const size_t N = seq.num_steps();
  std::printf("%s: %zu steps over %.1f s, %zu landmark tracks, %zu stereo observations (loaded in %.2f s)\n",
              a.npz.c_str(), N, seq.t_s.back() - seq.t_s.front(), seq.num_landmarks, seq.features.size(),
              load_s);
  if (seq.missing_partial > 0) {
    std::printf("warning: %zu feature entries with some but not all of uL,vL,uR,vR (or non-finite) skipped\n",
                seq.missing_partial);
  }

  core::ekf::StereoCamera cam;
  cam.fsu = seq.K[0];
  cam.fsv = seq.K[4];
  cam.cu = seq.K[2];
  cam.cv = seq.K[5];
  cam.baseline_m = seq.baseline_m;
  cam.T_CB = camera_from_imu(seq, a.extrinsic);

  core::EkfSlamOptions opt;
  opt.motion = core::EkfMotionModel::kVelocity;
  opt.landmark_capacity = a.capacity;
  opt.pixel_sigma_px = a.pixel_sigma;
  opt.vel_sigma_mps = a.vel_sigma;
  opt.gyro_vel_sigma_rps = a.gyro_sigma;
  opt.max_init_depth_m = a.max_depth;
  opt.max_missed_frames = 0;  // the KITTI tracks have no gaps: an unseen track has ended
  core::EkfSlam ekf(opt, cam);
  ekf.reset(core::ekf::Pose(), core::ekf::Mat6::Identity() * 1e-10);

  const size_t steps = a.steps > 0 ? std::min<size_t>(N, static_cast<size_t>(a.steps)) : N;
  std::vector<core::StereoObservation> obs;
  obs.reserve(1024);
  std::vector<core::FrozenLandmark> map;
  std::vector<Eigen::Vector3d> ekf_path, dead_path;
  tools::Trajectory traj;
  core::ekf::Pose dead;
  core::EkfUpdateStats total;
  double max_step_ms = 0.0;
  const auto drain = [&] {
    for (int i = 0; i < ekf.frozen_count(); ++i) map.push_back(ekf.frozen(i));
    ekf.clear_frozen();
  };
  const auto t_run = Clock::now();
  for (size_t t = 0; t < steps; ++t) {
    const auto t_step = Clock::now();
    if (t > 0) {
      // Paper 003: T_{t+1} = T_t exp(tau zeta_t^), the input of step t-1 held over tau.
      const double tau = seq.t_s[t] - seq.t_s[t - 1];
      const Eigen::Vector3d v(&seq.v_B_mps[3 * (t - 1)]), w(&seq.w_B_rps[3 * (t - 1)]);
      ekf.predict_velocity(v, w, tau);
      core::ekf::Vec6 xi;
      xi << v * tau, w * tau;
      dead = dead * core::ekf::se3_exp(xi);
    }
    if (!a.no_update) {
      obs.clear();
      for (size_t k = seq.step_begin[t]; k < seq.step_begin[t + 1]; ++k) {
        const auto& f = seq.features[k];
        obs.push_back({f.id, f.uL, f.vL, f.uR, f.vR});
      }
      const core::EkfUpdateStats st = ekf.update(obs.data(), static_cast<int>(obs.size()));
      total.observations += st.observations;
      total.used += st.used;
      total.gated += st.gated;
      total.initialised += st.initialised;
      total.not_initialised += st.not_initialised;
      total.dropped += st.dropped;
      drain();
    }
    max_step_ms = std::max(max_step_ms, 1e3 * seconds_since(t_step));
    const auto& T = ekf.pose();
    ekf_path.push_back(T.p);
    dead_path.push_back(dead.p);
    tools::TimedPose tp;
    tp.t_ns = static_cast<int64_t>(std::llround(seq.t_s[t] * 1e9));
    tp.p = T.p;
    tp.q = Eigen::Quaterniond(T.R).normalized();
    traj.push_back(tp);
  }
  ekf.freeze_all();
  drain();
  const double run_s = seconds_since(t_run);

  const double path_len = [&] {
    double L = 0.0;
    for (size_t i = 1; i < ekf_path.size(); ++i) L += (ekf_path[i] - ekf_path[i - 1]).norm();
    return L;
  }();
  const auto& c = ekf.counters();
  std::printf("filter: %zu steps in %.3f s (%.3f ms/step mean, %.2f ms max), load + filter %.2f s\n", steps,
              run_s, 1e3 * run_s / static_cast<double>(std::max<size_t>(steps, 1)), max_step_ms,
              load_s + run_s);
  std::printf("speed-up vs paper 003's 50 min: %.0fx (filter), %.0fx (load + filter)\n", 3000.0 / run_s,
              3000.0 / (load_s + run_s));
  std::printf(
      "observations: %d given, %d in the update, %d gated; landmarks: %llu initialised, %zu mapped, %llu "
      "dropped "
      "as outliers, %llu tracks refused for a full active set; %llu Cholesky failures\n",
      total.observations, total.used, total.gated, static_cast<unsigned long long>(c.landmarks_initialised),
      map.size(), static_cast<unsigned long long>(c.landmarks_dropped),
      static_cast<unsigned long long>(c.capacity_full), static_cast<unsigned long long>(c.cholesky_failures));
  std::printf("trajectory: %.1f m travelled; end %.1f %.1f %.1f m (dead reckoning %.1f %.1f %.1f m)\n",
              path_len, ekf_path.back().x(), ekf_path.back().y(), ekf_path.back().z(), dead_path.back().x(),
              dead_path.back().y(), dead_path.back().z());

  if (!a.traj_out.empty()) {
    tools::write_tum(a.traj_out, traj);
    std::printf("wrote %s (TUM, T_W-IMU, W = IMU frame at the first step)\n", a.traj_out.c_str());
  }
  if (!a.map_out.empty()) {
    write_ply(a.map_out, map);
    std::printf("wrote %s (%zu landmarks)\n", a.map_out.c_str(), map.size());
  }
  if (!a.plot_out.empty()) {
    const std::string name = a.npz.substr(a.npz.find_last_of('/') + 1);
    write_top_view(a.plot_out, "kestrel ekf-slam " + name + ": top view", ekf_path, dead_path, map);
    std::printf("wrote %s\n", a.plot_out.c_str());
  }
  return 0;
}

}  // namespace

Subcommand add_ekf_slam_command(CLI::App& parent) {
  auto args = std::make_shared<EkfArgs>();
  CLI::App* app =
      parent.add_subcommand("ekf-slam", "EKF visual-inertial SLAM on a KITTI features .npz (paper 003)");
  app->add_option("npz", args->npz, "kitti-vislam-features .npz")->required()->check(CLI::ExistingFile);
  app->add_option("--traj-out", args->traj_out, "trajectory T_W-IMU, TUM text");
  app->add_option("--map-out", args->map_out, "landmark map, PLY point cloud");
  app->add_option("--plot", args->plot_out, "top-view SVG (trajectory + landmarks)");
  app->add_option("--extrinsic", args->extrinsic,
                  "direction of the stored cam_T_imu: auto, as-stored, inverse")
      ->capture_default_str();
  app->add_option("--capacity", args->capacity, "active landmarks in the filter")->capture_default_str();
  app->add_option("--pixel-sigma", args->pixel_sigma, "pixel noise std [px]")->capture_default_str();
  app->add_option("--vel-sigma", args->vel_sigma, "linear velocity noise std [m/s]")->capture_default_str();
  app->add_option("--gyro-sigma", args->gyro_sigma, "angular velocity noise std [rad/s]")
      ->capture_default_str();
  app->add_option("--max-depth", args->max_depth, "farthest landmark initialised [m]")->capture_default_str();
  app->add_option("--steps", args->steps, "stop after this many steps (0: all)");
  app->add_flag("--no-update", args->no_update, "prediction only (velocity dead reckoning)");
  return {app, [args] { return run_ekf_slam(*args); }};
}

}  // namespace kestrel::cli
