// The one pose that crosses every stage of the pipeline: estimator thread ->
// output ring, the IMU-rate mailbox, the output thread's callbacks, the
// MAVLink adapter, the ROS and Python outputs. Plain numbers, trivially
// copyable, so a ring slot or a seqlock mailbox (rt::Mailbox copies raw
// words) is all the memory it needs; Eigen views for the arithmetic.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <type_traits>

#include "kestrel/core/estimator.hpp"

namespace kestrel::core {

struct PoseSample {
  int64_t t_ns = 0;
  double p_WB_m[3] = {0, 0, 0};
  double q_WB_wxyz[4] = {1, 0, 0, 0};
  double v_WB_mps[3] = {0, 0, 0};
  double omega_B_rps[3] = {0, 0, 0};  // newest gyro minus the estimated bias
  TrackingQuality quality = TrackingQuality::kUninitialized;
  uint32_t reset_counter = 0;
  // PoseCovariance's [dp_W; dtheta_B], column-major: the backend's (window,
  // ekf); invalid for the IMU-rate pose and for backends without one.
  double pose_cov[36] = {};
  int64_t pose_cov_t_ns = 0;
  bool pose_cov_valid = false;
  MapFrameState map;  // T_map_odom and the map's counters (backends with a map)

  Eigen::Vector3d p_WB() const { return Eigen::Vector3d(p_WB_m[0], p_WB_m[1], p_WB_m[2]); }
  Eigen::Quaterniond q_WB() const {
    return Eigen::Quaterniond(q_WB_wxyz[0], q_WB_wxyz[1], q_WB_wxyz[2], q_WB_wxyz[3]);
  }
  Eigen::Vector3d v_WB() const { return Eigen::Vector3d(v_WB_mps[0], v_WB_mps[1], v_WB_mps[2]); }
  Eigen::Vector3d omega_B() const { return Eigen::Vector3d(omega_B_rps[0], omega_B_rps[1], omega_B_rps[2]); }
  void set_p_WB(const Eigen::Vector3d& p);
  void set_q_WB(const Eigen::Quaterniond& q);
  void set_v_WB(const Eigen::Vector3d& v);
  void set_omega_B(const Eigen::Vector3d& w);
  PoseCovariance covariance() const;
  void set_covariance(const PoseCovariance& c);
  // The odometry pose, and the pose in the map frame: T_map_odom * T_WB (the
  // odometry when there is no map).
  Eigen::Isometry3d T_WB() const;
  Eigen::Isometry3d T_map_body() const;
};
static_assert(std::is_trivially_copyable_v<PoseSample>,
              "PoseSample crosses threads in rings and seqlock mailboxes as raw words");

// A state's time, pose and velocity, with the body rate from the newest gyro
// sample and the state's bias; quality, covariance and map are left for the
// caller.
PoseSample pose_sample_of(const NavState& x, const Vec3d& gyro_rps);

}  // namespace kestrel::core
