// The sliding-window problem both solvers work on (ours in
// window_optimizer.cpp, Ceres in ceres_window.cpp): states, landmarks,
// observations, factors and priors, plus the residual functions with their
// analytic Jacobians. One definition of every residual, so the two solvers
// minimise the identical cost.
//
// Tangent of a state (15): [dp (W), dphi (B, right: q <- q Exp(dphi)), dv (W), dbg, dba]
// (preintegration.hpp's perturbation convention). Landmarks: points in W, dl in W.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <vector>

#include "kestrel/core/imu_propagator.hpp"
#include "kestrel/core/motion_estimation.hpp"
#include "kestrel/core/preintegration.hpp"
#include "kestrel/core/window_options.hpp"

namespace kestrel::core {

constexpr int kWindowStateDim = 15;
// The states, plus one for the camera-IMU time offset t_d (last).
constexpr int kWindowMaxDim = kWindowStateDim * kWindowMaxStates + 1;
using Vector15d = Eigen::Matrix<double, 15, 1>;
using Matrix15d = Eigen::Matrix<double, 15, 15>;
using Matrix36d = Eigen::Matrix<double, 3, 6>;

struct WindowObs {
  int32_t lm = -1;  // landmark index, -1: unused (dropped, or its landmark is gone)
  Eigen::Vector2d uv = Eigen::Vector2d::Zero();
  double depth_m = 0.0;  // 0: none (or use_depth off)
  double sigma_px = 1.0;
  double sigma_depth_m = 0.0;
  Eigen::Vector2d uv_vel_pxps = Eigen::Vector2d::Zero();  // image velocity (time offset)
  double depth_vel_mps = 0.0;                             // rate of change of the depth (time offset)
};

struct WindowLandmark {
  bool used = false;
  bool initialised = false;
  uint32_t id = 0;
  Eigen::Vector3d p_W = Eigen::Vector3d::Zero();
  int n_obs = 0;
  int n_depth = 0;  // observations carrying depth
  // Where it is observed: (state slot, index into that slot's observations).
  int8_t obs_slot[kWindowMaxStates] = {};
  int16_t obs_idx[kWindowMaxStates] = {};
  // A map point: its position from the map's bundle adjustment, held by a
  // prior (l - prior_p_W) / prior_sigma_m (Huber like the visual terms).
  bool has_prior = false;
  Eigen::Vector3d prior_p_W = Eigen::Vector3d::Zero();
  double prior_sigma_m = 1.0;
  // Only landmarks whose 3x3 block is invertible take part: two views, or one with depth or a map prior.
  bool active() const { return initialised && (n_obs >= 2 || (n_obs >= 1 && (n_depth >= 1 || has_prior))); }
};

struct WindowState {
  bool used = false;
  bool keyframe = false;
  bool zero_velocity = false;  // carries the zero-velocity factor
  // Map pose factor (WindowFrameInput::has_pose_prior).
  bool has_pose_prior = false;
  Eigen::Vector3d prior_p_WB = Eigen::Vector3d::Zero();
  Eigen::Quaterniond prior_q_WB = Eigen::Quaterniond::Identity();
  double prior_sigma_p_m = 1.0, prior_sigma_rad = 1.0;
  NavState x;
  // Hold prior on velocity and biases (WindowFrameInput::vision_only), at hold_x's.
  bool hold = false;
  NavState hold_x;
  // IMU + bias factor from the previous state in the chain (imu_prev) to this one.
  bool has_imu = false;
  int imu_prev = -1;
  Preintegrated pim;
  Matrix9d imu_sqrt_info = Matrix9d::Zero();
  Vector6d bias_sqrt_info = Vector6d::Zero();  // diagonal
  int n_obs = 0;
  // Marginalisation prior: linearisation point of this state (first estimate).
  bool in_prior = false;
  NavState x0;
};

struct WindowProblem {
  WindowOptions opt;
  ImuNoiseParams bias_noise;  // opt.imu with the accelerometer bias model applied
  PinholeK K;
  Eigen::Matrix3d R_CB = Eigen::Matrix3d::Identity();
  Eigen::Vector3d p_CB = Eigen::Vector3d::Zero();
  int max_states = 0;  // S + N

  std::vector<WindowState> states;   // slots [max_states]
  int order[kWindowMaxStates] = {};  // slots in time order, oldest first
  int n_states = 0;
  std::vector<WindowObs> obs;       // [max_states * opt.max_obs_per_frame]
  std::vector<WindowLandmark> lms;  // [opt.max_landmarks]

  // Camera-IMU time offset t_d [s] (opt.estimate_time_offset): a frame
  // stamped t was taken at t + td_s. Kept across resets (a calibration);
  // in the marginalisation prior at index td_index() with its first estimate td0_s.
  double td_s = 0.0;
  double td0_s = 0.0;
  bool td_in_prior = false;
  // A measurement of t_d from outside the window (the rotation-correlation
  // calibrator, time_offset_calibrator.hpp); sigma 0: none, the prior holds t_d near 0.
  double td_meas_s = 0.0;
  double td_meas_sigma_s = 0.0;
  bool estimate_td() const { return opt.estimate_time_offset; }
  int td_index() const { return kWindowStateDim * max_states; }

  // Gauge: position and yaw of the oldest state held at these values.
  int gauge_slot = -1;
  // Enough landmarks carry map priors (WindowOptions::map_anchor_min_landmarks):
  // the map fixes position and yaw, like a map pose factor. Set by optimize().
  bool map_anchored = false;
  Eigen::Vector3d gauge_p = Eigen::Vector3d::Zero();
  double gauge_yaw = 0.0;
  Eigen::Quaterniond gauge_q = Eigen::Quaterniond::Identity();  // the whole attitude, for vision-only windows

  // Marginalisation prior in slot space (15 * max_states + 1 square, t_d last):
  //   cost = prior_c + prior_g' dx + 1/2 dx' prior_H dx,  dx = x [-] x0 per state (td - td0 for t_d),
  // which equals 1/2 |e + J dx|^2 with J'J = prior_H, J'e = prior_g, 1/2 e'e = prior_c.
  Eigen::MatrixXd prior_H;
  Eigen::VectorXd prior_g;
  double prior_c = 0.0;
  bool prior_active = false;

  WindowObs* obs_of(int slot) { return obs.data() + static_cast<std::size_t>(slot) * opt.max_obs_per_frame; }
  const WindowObs* obs_of(int slot) const {
    return obs.data() + static_cast<std::size_t>(slot) * opt.max_obs_per_frame;
  }
  int newest_slot() const { return n_states > 0 ? order[n_states - 1] : -1; }
  // The gauge prior holds only while no state carries a map pose factor.
  bool gauge_active() const {
    if (gauge_slot < 0 || map_anchored) return false;
    for (int k = 0; k < n_states; ++k)
      if (states[order[k]].has_pose_prior) return false;
    return true;
  }
  // Without any IMU factor in the window roll and pitch are unobservable:
  // the gauge then holds the oldest state's whole attitude.
  bool gauge_rotation_active() const {
    if (!gauge_active()) return false;
    for (int k = 0; k < n_states; ++k)
      if (states[order[k]].has_imu) return false;
    return true;
  }
};

// ---- residuals ---------------------------------------------------------------

// Huber on a squared whitened norm s (Ceres' HuberLoss): rho(s) = s for
// s <= a^2, 2 a sqrt(s) - a^2 above; rho1 = rho'(s). a <= 0: rho(s) = s.
double huber_rho(double s, double a, double* rho1);

// Visual residual of one observation, whitened: rows 0-1
// (pi(K p_C) - (uv - uv_vel td_s)) / sigma_px, row 2 (z_C - (depth - depth_vel td_s)) / sigma_depth
// when the observation has depth. p_C = R_CB R_WB^T (l_W - p_WB) + p_CB;
// td_s: the time offset (0 when not estimated): the pixel is moved back along
// its image velocity to the state's time. Returns the number of rows (2 or 3),
// 0 when the point is not in front of the camera (z_C < 1e-3 m).
// J_pose: d r / d[dp, dphi]; J_l: d r / d l_W; J_td: d r / d td_s.
int visual_residual(const WindowProblem& P, const NavState& x, const Eigen::Vector3d& l_W, const WindowObs& o,
                    double td_s, Eigen::Vector3d* r, Matrix36d* J_pose = nullptr,
                    Eigen::Matrix3d* J_l = nullptr, Eigen::Vector3d* J_td = nullptr);
// The time offset's prior (td_s - td_meas) / sigma_meas when a measurement is
// known, else td_s / time_offset_prior_sigma_ms; and its derivative.
double time_offset_prior_residual(const WindowProblem& P, double td_s, double* J = nullptr);

// IMU (9, whitened by the preintegration's covariance) and bias (6, whitened
// by bias_covariance) residuals stacked: [r_R, r_v, r_p, r_bg, r_ba].
// J_i, J_j: d r / d (15-tangent of x_i, x_j).
Vector15d imu_bias_residual(const WindowProblem& P, const WindowState& sj, const NavState& x_i,
                            const NavState& x_j, Matrix15d* J_i = nullptr, Matrix15d* J_j = nullptr);

// Map pose factor of a state carrying one: [(p - p_prior) / sigma_p;
// Log(R_prior^T R) / sigma_r], J = d r / d[dp, dphi].
Vector6d pose_prior_residual(const WindowState& st, const NavState& x, Matrix6d* J = nullptr);

// Map prior of a landmark carrying one: (l_W - prior_p_W) / prior_sigma_m; d r / d l = I / sigma.
inline Eigen::Vector3d landmark_prior_residual(const WindowLandmark& L, const Eigen::Vector3d& l_W) {
  return (l_W - L.prior_p_W) / L.prior_sigma_m;
}

// Yaw of R_WB: heading of the body x axis in W, atan2(R10, R00).
double yaw_of(const Eigen::Quaterniond& q_WB);
// Gauge residual [p - gauge_p; wrap(yaw - gauge_yaw)] / gauge_sigma and its
// Jacobian w.r.t. [dp, dphi].
Eigen::Vector4d gauge_residual(const WindowProblem& P, const NavState& x,
                               Eigen::Matrix<double, 4, 6>* J = nullptr);

// Attitude gauge of a window without IMU factors: Log(R_gauge^T R) / gauge_sigma,
// J = d r / d[dp, dphi].
Eigen::Vector3d gauge_rotation_residual(const WindowProblem& P, const NavState& x,
                                        Eigen::Matrix<double, 3, 6>* J = nullptr);

// Hold prior of a vision-only state: [(v - v0) / s_v; (bg - bg0) / s_g; (ba - ba0) / s_a]
// at st.hold_x; d r / d[dv, dbg, dba] is the diagonal of the inverse sigmas (hold_weights).
Vector9d hold_residual(const WindowProblem& P, const WindowState& st, const NavState& x);
Vector9d hold_weights(const WindowProblem& P);

// x [-] x0 in the state tangent: [p - p0, Log(R0^T R), v - v0, bg - bg0, ba - ba0],
// and d(delta)/d(tangent of x) as the 3x3 block of the rotation part (Jr^-1);
// the other blocks are identity.
Vector15d state_minus(const NavState& x, const NavState& x0, Eigen::Matrix3d* J_rot = nullptr);
// x [+] d in the same tangent.
NavState state_plus(const NavState& x, const Vector15d& d);

}  // namespace kestrel::core
