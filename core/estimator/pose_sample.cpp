#include "kestrel/core/pose_sample.hpp"

namespace kestrel::core {

void PoseSample::set_p_WB(const Eigen::Vector3d& p) {
  for (int i = 0; i < 3; ++i) p_WB_m[i] = p[i];
}

void PoseSample::set_q_WB(const Eigen::Quaterniond& q) {
  q_WB_wxyz[0] = q.w();
  q_WB_wxyz[1] = q.x();
  q_WB_wxyz[2] = q.y();
  q_WB_wxyz[3] = q.z();
}

void PoseSample::set_v_WB(const Eigen::Vector3d& v) {
  for (int i = 0; i < 3; ++i) v_WB_mps[i] = v[i];
}

void PoseSample::set_omega_B(const Eigen::Vector3d& w) {
  for (int i = 0; i < 3; ++i) omega_B_rps[i] = w[i];
}

PoseCovariance PoseSample::covariance() const {
  PoseCovariance c;
  c.cov = Eigen::Map<const Eigen::Matrix<double, 6, 6>>(pose_cov);
  c.t_ns = pose_cov_t_ns;
  c.valid = pose_cov_valid;
  return c;
}

void PoseSample::set_covariance(const PoseCovariance& c) {
  Eigen::Map<Eigen::Matrix<double, 6, 6>> m(pose_cov);
  m = c.cov;
  pose_cov_t_ns = c.t_ns;
  pose_cov_valid = c.valid;
}

Eigen::Isometry3d PoseSample::T_WB() const {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = q_WB().normalized().toRotationMatrix();
  T.translation() = p_WB();
  return T;
}

Eigen::Isometry3d PoseSample::T_map_body() const { return map.active ? map.T_map_odom() * T_WB() : T_WB(); }

PoseSample pose_sample_of(const NavState& x, const Vec3d& gyro_rps) {
  PoseSample s;
  s.t_ns = x.t_ns;
  s.set_p_WB(x.p_WB);
  s.set_q_WB(x.q_WB);
  s.set_v_WB(x.v_WB);
  for (int i = 0; i < 3; ++i) s.omega_B_rps[i] = gyro_rps[i] - x.bg_rps[i];
  return s;
}

}  // namespace kestrel::core
