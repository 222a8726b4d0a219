// Kestrel state -> MAVLink ODOMETRY for a flight controller's external-vision
// input (PX4 EKF2, ArduPilot VISO). The only place where Kestrel's frames meet
// the flight controller's (docs/frames.md, docs/px4.md):
//   W (z up, gravity along -z, yaw fixed at start)  ->  MAV_FRAME_LOCAL_FRD (z down)
//   B (IMU body, x forward, y left, z up on our rigs) ->  MAV_FRAME_BODY_FRD
// Both are a rotation by pi about x unless the options say otherwise.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>

#include "kestrel/core/estimator.hpp"
#include "kestrel/core/pose_sample.hpp"
#include "kestrel/drivers/mavlink/mavlink_v2.hpp"

namespace kestrel::mavlink {

struct OdometryAdapterOptions {
  // Vehicle FRD body axes in B. Default: B is forward-left-up.
  Eigen::Matrix3d R_FB = Eigen::Vector3d(1, -1, -1).asDiagonal();
  // Local FRD axes in W. Default: W's x stays forward, z flips to down.
  Eigen::Matrix3d R_LW = Eigen::Vector3d(1, -1, -1).asDiagonal();
  uint8_t estimator_type = kMavEstimatorVio;
  // Sent when the estimator has no covariance of its own (vo, imu; window
  // and ekf have a pose covariance, none for the twist), or it is coasting
  // (a covariance from the last camera update would be over-confident).
  // 1-sigma, per axis; documented in docs/px4.md.
  double tracking_pos_sigma_m = 0.03;
  double tracking_att_sigma_rad = 0.02;
  double tracking_vel_sigma_mps = 0.1;
  double tracking_rate_sigma_rps = 0.01;
  // Coasting on the IMU: honest about the drift of ~1 s of dead reckoning.
  double coasting_pos_sigma_m = 0.5;
  double coasting_att_sigma_rad = 0.05;
  double coasting_vel_sigma_mps = 0.5;
  // MAVLink quality per tracking state (-1 = failed, 1..100).
  int8_t quality_tracking = 100;
  int8_t quality_coasting = 20;
};

// False (nothing to send) before the estimator is initialised.
// The pose's own covariance goes out while tracking when it has one
// (PoseSample::pose_cov_valid); otherwise, and for the twist (no backend
// estimates its covariance), the fixed values above.
bool to_odometry(const core::PoseSample& in, const OdometryAdapterOptions& opt, OdometryMsg& out);

// Quality of a tracking state on MAVLink's scale.
int8_t mavlink_quality(core::TrackingQuality q, const OdometryAdapterOptions& opt);

// 6x6 symmetric -> 21 floats, row-major upper triangle.
void upper_triangle(const Eigen::Matrix<double, 6, 6>& m, float* out21);

}  // namespace kestrel::mavlink
