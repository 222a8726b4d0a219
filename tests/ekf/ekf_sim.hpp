// A small simulated world for the EKF tests: landmarks on the walls and floor
// of a room around the simulator's flights, a forward-looking camera (the
// simulator rig's T_BC), stereo (virtual-baseline) observations with pixel
// noise and known correspondences, and the sim's trajectories and IMU.
#pragma once

#include <Eigen/Geometry>
#include <cmath>
#include <vector>

#include "kestrel/core/ekf_slam.hpp"
#include "kestrel/tools/sim_imu.hpp"
#include "kestrel/tools/sim_random.hpp"
#include "kestrel/tools/sim_trajectory.hpp"

namespace kestrel::test {

using core::ekf::Pose;

struct EkfSimWorld {
  std::vector<Eigen::Vector3d> landmarks;
  core::ekf::StereoCamera cam;
  int width = 640, height = 480;
  double max_range_m = 8.0;  // an RGB-D camera's useful depth range
};

inline EkfSimWorld make_ekf_world(uint64_t seed, int per_wall = 250) {
  EkfSimWorld w;
  tools::SimRng rng(seed, tools::RngStream::kScene);
  const double X = 7.0, Y = 6.0, Z = 3.5;
  for (int i = 0; i < per_wall; ++i) {
    w.landmarks.emplace_back(X, rng.uniform(-Y, Y), rng.uniform(0, Z));
    w.landmarks.emplace_back(-X, rng.uniform(-Y, Y), rng.uniform(0, Z));
    w.landmarks.emplace_back(rng.uniform(-X, X), Y, rng.uniform(0, Z));
    w.landmarks.emplace_back(rng.uniform(-X, X), -Y, rng.uniform(0, Z));
    w.landmarks.emplace_back(rng.uniform(-X, X), rng.uniform(-Y, Y), 0.0);
  }
  w.cam.fsu = w.cam.fsv = 460.0;
  w.cam.cu = 320.0;
  w.cam.cv = 240.0;
  w.cam.baseline_m = 0.25;  // virtual baseline: depth noise ~ z^2 / (f b) * sigma_px
  Eigen::Matrix3d R_BC;
  R_BC << 0, 0, 1, -1, 0, 0, 0, -1, 0;  // the simulator rig: optical axis along body +x
  w.cam.T_CB = Pose(R_BC, Eigen::Vector3d(0.06, 0.015, 0.02)).inverse();
  return w;
}

inline Pose pose_of(const tools::TrajectoryState& s) { return Pose(s.q_WB.toRotationMatrix(), s.p_WB); }

// Noisy observations of every landmark in view; ids are landmark indices.
inline void observe(const EkfSimWorld& w, const Pose& T_WB, double sigma_px, tools::SimRng& rng,
                    std::vector<core::StereoObservation>& out, int max_obs = 120) {
  out.clear();
  for (size_t i = 0; i < w.landmarks.size() && static_cast<int>(out.size()) < max_obs; ++i) {
    core::ekf::StereoMeas z;
    if (!core::ekf::stereo_project(w.cam, T_WB, w.landmarks[i], 0.3, z)) continue;
    const Eigen::Vector3d p_C = w.cam.T_CB * (T_WB.inverse() * w.landmarks[i]);
    if (p_C.z() > w.max_range_m) continue;
    if (z(0) < 0 || z(0) >= w.width || z(1) < 0 || z(1) >= w.height || z(2) < 0) continue;
    core::StereoObservation o;
    o.id = static_cast<uint32_t>(i);
    o.uL = z(0) + sigma_px * rng.normal();
    o.vL = z(1) + sigma_px * rng.normal();
    o.uR = z(2) + sigma_px * rng.normal();
    o.vR = z(1) + sigma_px * rng.normal();
    out.push_back(o);
  }
}

// RGB-D observations: pixel noise on u and v, depth noise sigma_z = k z^2,
// turned into virtual stereo with the camera's (virtual) baseline.
inline void observe_rgbd(const EkfSimWorld& w, const Pose& T_WB, double sigma_px, double k_per_m,
                         tools::SimRng& rng, std::vector<core::StereoObservation>& out, int max_obs = 120) {
  out.clear();
  for (size_t i = 0; i < w.landmarks.size() && static_cast<int>(out.size()) < max_obs; ++i) {
    const Eigen::Vector3d p_C = w.cam.T_CB * (T_WB.inverse() * w.landmarks[i]);
    if (p_C.z() < 0.3 || p_C.z() > w.max_range_m) continue;
    const double u = w.cam.fsu * p_C.x() / p_C.z() + w.cam.cu;
    const double v = w.cam.fsv * p_C.y() / p_C.z() + w.cam.cv;
    if (u < 0 || u >= w.width || v < 0 || v >= w.height) continue;
    const double z = p_C.z() + k_per_m * p_C.z() * p_C.z() * rng.normal();
    out.push_back(core::virtual_stereo(static_cast<uint32_t>(i), u + sigma_px * rng.normal(),
                                       v + sigma_px * rng.normal(), z, w.cam.fsu, w.cam.baseline_m));
  }
}

// Right-perturbation pose error e with T_true = T_est exp(e^).
inline core::ekf::Vec6 pose_error(const Pose& T_est, const Pose& T_true) {
  return core::ekf::se3_log(T_est.inverse() * T_true);
}

struct SimRunResult {
  double mean_nees = 0.0;      // pose, 6 dof
  double mean_pose_nis = 0.0;  // EkfUpdateStats::pose_nis over the updates (6 dof)
  double ate_rmse_m = 0.0;     // position, no alignment (the start is known)
  double rot_rmse_deg = 0.0;
  int frames = 0;
  int mean_active = 0;
  uint64_t landmarks_mapped = 0;
};

struct SimRunConfig {
  core::EkfMotionModel motion = core::EkfMotionModel::kImu;
  std::string scenario = "figure8";
  double duration_s = 20.0;
  double sigma_px_true = 0.5;
  double sigma_px_filter = 0.5;
  double camera_rate_hz = 20.0;
  double input_rate_hz = 200.0;
  double vel_sigma = 0.05, gyro_vel_sigma = 0.01;  // velocity mode input noise (true)
  double filter_input_noise_scale = 1.0;           // the filter assumes this times the true input noise
  double imu_noise_scale = 1.0;                    // EkfSlam::set_imu_noise_scale on top of that
  double true_imu_noise_scale = 1.0;  // the simulated IMU's white noise is this times the BMX055's
  int capacity = 48;
  // > 0: RGB-D observations with depth noise k z^2 (observe_rgbd) and the
  // filter's exact RGB-D noise model (rgbd_disparity_sigma_px = fx b k).
  double rgbd_depth_coeff_per_m = 0.0;
  uint64_t seed = 1;
  double skip_s = 1.0;  // NEES / ATE from here on
};

// One simulated run of the filter against ground truth.
inline SimRunResult run_ekf_sim(const SimRunConfig& c) {
  const auto traj = tools::make_scenario(c.scenario, c.duration_s);
  const EkfSimWorld world = make_ekf_world(7);
  tools::SimRng cam_rng(c.seed, tools::RngStream::kCamera);
  tools::SimRng in_rng(c.seed, tools::RngStream::kImu);
  const tools::ImuModel model = tools::ImuModel::bmx055(0.0);
  tools::ImuModel true_model = model;
  true_model.gyro_noise_density_rad_s_sqrthz *= c.true_imu_noise_scale;
  true_model.acc_noise_density_mps2_sqrthz *= c.true_imu_noise_scale;
  tools::ImuSynth synth(true_model, c.input_rate_hz, 9.81, c.seed);

  core::EkfSlamOptions opt;
  opt.motion = c.motion;
  opt.landmark_capacity = c.capacity;
  opt.pixel_sigma_px = c.sigma_px_filter;
  opt.max_missed_frames = 2;
  opt.max_init_depth_m = world.max_range_m;
  opt.gyro_noise_density = model.gyro_noise_density_rad_s_sqrthz;
  opt.acc_noise_density = model.acc_noise_density_mps2_sqrthz;
  opt.gyro_random_walk = std::max(model.gyro_random_walk_rad_s2_sqrthz, 1e-6);
  opt.acc_random_walk = std::max(model.acc_random_walk_mps3_sqrthz, 1e-5);
  opt.vel_sigma_mps = c.vel_sigma * c.filter_input_noise_scale;
  opt.gyro_vel_sigma_rps = c.gyro_vel_sigma * c.filter_input_noise_scale;
  opt.gyro_noise_density *= c.filter_input_noise_scale;
  opt.acc_noise_density *= c.filter_input_noise_scale;
  opt.gravity_mps2 = 9.81;
  if (c.rgbd_depth_coeff_per_m > 0)
    opt.rgbd_disparity_sigma_px =
        world.cam.fsu * world.cam.baseline_m * c.rgbd_depth_coeff_per_m * c.sigma_px_filter / c.sigma_px_true;
  core::EkfSlam ekf(opt, world.cam);
  ekf.set_imu_noise_scale(c.imu_noise_scale);
  const tools::TrajectoryState s0 = traj->state(0.0);
  const core::ekf::Mat6 P0 = core::ekf::Mat6::Identity() * 1e-10;
  if (c.motion == core::EkfMotionModel::kImu) {
    ekf.reset_imu(pose_of(s0), s0.v_WB, Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero(), P0, 1e-3,
                  std::max(model.gyro_bias_init_sigma_rps, 1e-4),
                  std::max(model.acc_bias_init_sigma_mps2, 1e-3));
  } else {
    ekf.reset(pose_of(s0), P0);
  }

  const double dt = 1.0 / c.input_rate_hz;
  const int per_frame = static_cast<int>(std::lround(c.input_rate_hz / c.camera_rate_hz));
  const int n_steps = static_cast<int>(c.duration_s / dt) - 1;
  std::vector<core::StereoObservation> obs;
  SimRunResult r;
  double nees_sum = 0.0, pos2 = 0.0, rot2 = 0.0, nis_sum = 0.0;
  int nis_n = 0;
  long active_sum = 0;
  for (int k = 0; k < n_steps; ++k) {
    // The input at the middle of the step: the zero-order hold then errs by
    // O(dt^3) only, far below the noise.
    const tools::TrajectoryState mid = traj->state((k + 0.5) * dt);
    if (c.motion == core::EkfMotionModel::kImu) {
      const ImuSample imu = synth.sample(mid, static_cast<int64_t>(std::llround((k + 0.5) * dt * 1e9)));
      ekf.propagate_imu(Eigen::Vector3d(imu.gyro_rps.data()), Eigen::Vector3d(imu.acc_mps2.data()), dt);
    } else {
      const Eigen::Vector3d v_B = mid.q_WB.conjugate() * mid.v_WB;
      const Eigen::Vector3d nv(in_rng.normal(), in_rng.normal(), in_rng.normal());
      const Eigen::Vector3d nw(in_rng.normal(), in_rng.normal(), in_rng.normal());
      ekf.predict_velocity(v_B + c.vel_sigma * nv, mid.w_B + c.gyro_vel_sigma * nw, dt);
    }
    if ((k + 1) % per_frame != 0) continue;
    const double t = (k + 1) * dt;
    const Pose T_true = pose_of(traj->state(t));
    if (c.rgbd_depth_coeff_per_m > 0)
      observe_rgbd(world, T_true, c.sigma_px_true, c.rgbd_depth_coeff_per_m, cam_rng, obs);
    else
      observe(world, T_true, c.sigma_px_true, cam_rng, obs);
    const core::EkfUpdateStats st = ekf.update(obs.data(), static_cast<int>(obs.size()));
    r.landmarks_mapped += static_cast<uint64_t>(ekf.frozen_count());
    ekf.clear_frozen();
    if (t < c.skip_s) continue;
    if (st.pose_nis > 0) {
      nis_sum += st.pose_nis;
      ++nis_n;
    }
    const core::ekf::Vec6 e = pose_error(ekf.pose(), T_true);
    const core::ekf::Mat6 P = ekf.pose_covariance();
    nees_sum += e.dot(P.ldlt().solve(e));
    pos2 += (ekf.pose().p - T_true.p).squaredNorm();
    rot2 += e.tail<3>().squaredNorm();
    active_sum += ekf.num_active();
    ++r.frames;
  }
  if (r.frames > 0) {
    r.mean_nees = nees_sum / r.frames;
    r.mean_pose_nis = nis_n > 0 ? nis_sum / nis_n : 0.0;
    r.ate_rmse_m = std::sqrt(pos2 / r.frames);
    r.rot_rmse_deg = std::sqrt(rot2 / r.frames) * 180.0 / M_PI;
    r.mean_active = static_cast<int>(active_sum / r.frames);
  }
  return r;
}

}  // namespace kestrel::test
