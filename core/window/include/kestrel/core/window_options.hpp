// Configuration and inputs of the sliding-window optimiser (window_optimizer.hpp).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <string>

#include "kestrel/core/imu_propagator.hpp"
#include "kestrel/core/observation.hpp"
#include "kestrel/core/preintegration.hpp"

namespace kestrel::core {

// Compile-time capacity of the window (S + N); the dense reduced camera
// system is at most 15 * kWindowMaxStates square.
constexpr int kWindowMaxStates = 10;

struct WindowOptions {
  int S = 3;                    // most recent frames (temporal window), >= 1
  int N = 5;                    // keyframes outside the temporal window, >= 1; S + N <= kWindowMaxStates
  int max_landmarks = 600;      // landmark budget, fixed at construction
  int max_obs_per_frame = 300;  // observations kept per frame (the rest are skipped and counted)
  enum class Solver { kOurs, kCeres } solver = Solver::kOurs;
  int max_iterations = 8;
  double time_budget_ms = 35.0;  // wall-clock bound of one optimize() (checked after each iteration)
  double huber_px = 2.0;         // Huber threshold on the whitened residual norm; <= 0: plain least squares
  bool use_depth = true;         // RGB-D depth as a third row of the visual residual
  double depth_sigma_coeff_per_m = 0.0025;  // sigma_depth(z) = k z^2 [m]
  bool marginalize = true;                  // false: dropped states and their factors are simply discarded
  double pixel_sigma = 1.0;                 // [px] used when an observation's sigma_px <= 0
  ImuNoiseParams imu;  // noise densities for the bias factor (preintegrations carry their own)
  // Accelerometer bias model of the bias factor: Forster's random walk, or
  // paper 000 eq. 6 bounded random walk db/dt = -b/tau + w (tau below).
  enum class AccBiasModel { kRandomWalk, kBoundedRandomWalk } acc_bias_model = AccBiasModel::kRandomWalk;
  double acc_bias_tau_s = 300.0;
  // Prior on the very first state's biases (OKVIS adds the same speed/bias
  // prior at start-up); it is part of the marginalisation prior afterwards.
  double prior_gyro_bias_sigma_rps = 0.01;
  double prior_acc_bias_sigma_mps2 = 0.1;
  // Gauge: the oldest state's position and yaw are held by a stiff prior of this sigma [m, rad].
  double gauge_sigma = 1e-5;
  // Zero-velocity factor on states the front end flags as stationary:
  // r = v_WB / sigma. Soft, so a hovering vehicle (a few cm/s) is not pinned.
  double zero_velocity_sigma_mps = 0.02;
  // A state that enters without an IMU factor (WindowFrameInput::vision_only)
  // has nothing to observe its velocity and biases: a soft prior holds them
  // at the guess (the biases at the last estimate, so when the IMU returns
  // they are re-estimated from there rather than from nothing).
  double hold_velocity_sigma_mps = 1.0;
  double hold_gyro_bias_sigma_rps = 0.01;
  double hold_acc_bias_sigma_mps2 = 0.1;
  // Convergence (ours): stop when the relative cost decrease of an accepted step or the step's
  // max-norm falls below these.
  double function_tolerance = 1e-10;
  double step_tolerance = 1e-10;
  // Online camera-IMU time offset t_d (VINS-Mono's estimate_td): what is left
  // of the offset after the rig's time_offset_cam_imu_ns was applied to the
  // stamps. A frame stamped t was taken at t + t_d; each observation is moved
  // back to its state's time along its pixel and depth rates, and t_d is one
  // more variable of the window, held near 0 by a prior of this sigma until
  // a measurement (WindowFrameInput::td_meas_s: the rotation correlation of
  // WindowEstimator) replaces it. Off by default: it lands within 1 ms over
  // 30 s but recovers only half the accuracy (docs/optimizer.md).
  bool estimate_time_offset = false;
  double time_offset_prior_sigma_ms = 50.0;
  // Map points (observations with WindowObservation::map_sigma_m > 0) hold
  // their landmarks by a prior; with at least this many such landmarks in
  // the problem the map fixes the gauge and the oldest state is let go.
  bool use_map_points = true;
  int map_anchor_min_landmarks = 10;

  // The embedded profile: S = 2, N = 3.
  static WindowOptions embedded();
  // Empty when usable, else what is wrong (names the field).
  std::string validate() const;
};

struct WindowFrameInput {
  int64_t t_ns = 0;
  NavState guess;  // pose/vel/bias initial guess (from the front end)
  const Preintegrated* imu_from_prev =
      nullptr;  // previous added frame -> this one (null for the first); copied
  const WindowObservation* obs = nullptr;
  int n_obs = 0;
  bool keyframe = false;
  bool stationary = false;  // the IMU says the vehicle is still: add the zero-velocity factor
  // Image velocity of each observation [px/s] (estimate_time_offset; null: none known).
  const Eigen::Vector2d* uv_vel_pxps = nullptr;
  // Rate of change of each observation's depth [m/s] (estimate_time_offset; null: none known).
  const double* depth_vel_mps = nullptr;
  // A measurement of the time offset t_d [s] and its 1-sigma (<= 0: none):
  // replaces the prior around 0 (WindowEstimator: the rotation-correlation calibrator).
  double td_meas_s = 0.0;
  double td_meas_sigma_s = 0.0;
  // No IMU factor from the previous frame (there is no IMU, or it is silent):
  // imu_from_prev may be null; velocity and biases get the hold prior, and
  // while no state of the window has an IMU factor the gauge also pins the
  // oldest state's roll and pitch (nothing ties them to gravity then).
  bool vision_only = false;
  // A pose measured against landmarks of earlier keyframes (the tracker's
  // local map): a unary factor r = [p - p_prior; Log(R_prior^T R)] / sigma.
  // It ties the window to the map instead of only to its own oldest state, so
  // drift stops growing where the vehicle sees old landmarks again; while a
  // state in the window carries one, the gauge prior is off (the map fixes
  // position and yaw).
  bool has_pose_prior = false;
  Eigen::Vector3d prior_p_WB = Eigen::Vector3d::Zero();
  Eigen::Quaterniond prior_q_WB = Eigen::Quaterniond::Identity();
  double prior_sigma_p_m = 0.02;
  double prior_sigma_rad = 0.01;
};

}  // namespace kestrel::core
