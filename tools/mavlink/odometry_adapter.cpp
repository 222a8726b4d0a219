#include "kestrel/mavlink/odometry_adapter.hpp"

#include <cmath>
#include <limits>

namespace kestrel::mavlink {
namespace {

using Mat6 = Eigen::Matrix<double, 6, 6>;

Mat6 diagonal(double a, double b) {
  Mat6 m = Mat6::Zero();
  m.diagonal() << a * a, a * a, a * a, b * b, b * b, b * b;
  return m;
}

void unknown(float* out21) {
  // MAVLink: "If unknown, assign NaN value to first element in the array."
  out21[0] = std::numeric_limits<float>::quiet_NaN();
  for (int i = 1; i < 21; ++i) out21[i] = 0.0f;
}

}  // namespace

int8_t mavlink_quality(core::TrackingQuality q, const OdometryAdapterOptions& opt) {
  switch (q) {
    case core::TrackingQuality::kTracking:
    case core::TrackingQuality::kVisionOnly:
      return opt.quality_tracking;
    case core::TrackingQuality::kImuOnly:
      return opt.quality_coasting;
    case core::TrackingQuality::kLost:
      return -1;
    case core::TrackingQuality::kUninitialized:
      return 0;
  }
  return 0;
}

void upper_triangle(const Mat6& m, float* out21) {
  int k = 0;
  for (int r = 0; r < 6; ++r)
    for (int c = r; c < 6; ++c) out21[k++] = static_cast<float>(m(r, c));
}

bool to_odometry(const core::PoseSample& in, const OdometryAdapterOptions& opt, OdometryMsg& out) {
  if (in.quality == core::TrackingQuality::kUninitialized) return false;
  const Eigen::Matrix3d R_WB = in.q_WB().normalized().toRotationMatrix();
  const Eigen::Matrix3d R_LF = opt.R_LW * R_WB * opt.R_FB.transpose();
  const Eigen::Vector3d p_L = opt.R_LW * in.p_WB();
  const Eigen::Matrix3d R_FW = opt.R_FB * R_WB.transpose();
  // REP 147 / MAVLink: the twist is in the child frame (body FRD).
  const Eigen::Vector3d v_F = R_FW * in.v_WB();
  const Eigen::Vector3d w_F = opt.R_FB * in.omega_B();
  Eigen::Quaterniond q_LF(R_LF);
  q_LF.normalize();
  if (q_LF.w() < 0) q_LF.coeffs() = -q_LF.coeffs();  // one sign on the wire, easier to read in logs

  out = OdometryMsg{};
  out.time_usec = in.t_ns > 0 ? static_cast<uint64_t>(in.t_ns / 1000) : 0;
  out.frame_id = kMavFrameLocalFrd;
  out.child_frame_id = kMavFrameBodyFrd;
  out.x = static_cast<float>(p_L.x());
  out.y = static_cast<float>(p_L.y());
  out.z = static_cast<float>(p_L.z());
  out.q[0] = static_cast<float>(q_LF.w());
  out.q[1] = static_cast<float>(q_LF.x());
  out.q[2] = static_cast<float>(q_LF.y());
  out.q[3] = static_cast<float>(q_LF.z());
  out.vx = static_cast<float>(v_F.x());
  out.vy = static_cast<float>(v_F.y());
  out.vz = static_cast<float>(v_F.z());
  out.rollspeed = static_cast<float>(w_F.x());
  out.pitchspeed = static_cast<float>(w_F.y());
  out.yawspeed = static_cast<float>(w_F.z());

  const bool tracking =
      in.quality == core::TrackingQuality::kTracking || in.quality == core::TrackingQuality::kVisionOnly;
  if (in.quality == core::TrackingQuality::kLost) {
    unknown(out.pose_covariance);
    unknown(out.velocity_covariance);
  } else {
    const Mat6 pose_cov = Eigen::Map<const Mat6>(in.pose_cov);
    if (tracking && in.pose_cov_valid && pose_cov.allFinite()) {
      // [dp_W; dtheta_B] -> [dp_L; dtheta_F]: p_L = R_LW p_W, and R_LF = R_LW R_WB R_FB' with
      // R_WB = R_hat Exp(dtheta_B) gives R_LF = R_LF_hat Exp(R_FB dtheta_B). Small body-frame
      // angles are what MAVLink's roll, pitch, yaw rows mean for a near-level vehicle.
      Mat6 J = Mat6::Zero();
      J.topLeftCorner<3, 3>() = opt.R_LW;
      J.bottomRightCorner<3, 3>() = opt.R_FB;
      upper_triangle(J * pose_cov * J.transpose(), out.pose_covariance);
    } else if (tracking) {
      upper_triangle(diagonal(opt.tracking_pos_sigma_m, opt.tracking_att_sigma_rad), out.pose_covariance);
    } else {
      upper_triangle(diagonal(opt.coasting_pos_sigma_m, opt.coasting_att_sigma_rad), out.pose_covariance);
    }
    upper_triangle(diagonal(tracking ? opt.tracking_vel_sigma_mps : opt.coasting_vel_sigma_mps,
                            opt.tracking_rate_sigma_rps),
                   out.velocity_covariance);
  }
  // The counter wraps at 256 on the wire; receivers only compare for change.
  out.reset_counter = static_cast<uint8_t>(in.reset_counter & 0xFF);
  out.estimator_type = opt.estimator_type;
  out.quality = mavlink_quality(in.quality, opt);
  return true;
}

}  // namespace kestrel::mavlink
