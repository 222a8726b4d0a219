#include <cmath>

#include "kestrel/core/so3.hpp"
#include "kestrel/core/window_problem.hpp"

namespace kestrel::core {

double huber_rho(double s, double a, double* rho1) {
  if (a <= 0.0 || s <= a * a) {
    if (rho1) *rho1 = 1.0;
    return s;
  }
  const double r = std::sqrt(s);
  if (rho1) *rho1 = a / r;
  return 2.0 * a * r - a * a;
}

int visual_residual(const WindowProblem& P, const NavState& x, const Eigen::Vector3d& l_W, const WindowObs& o,
                    double td_s, Eigen::Vector3d* r, Matrix36d* J_pose, Eigen::Matrix3d* J_l,
                    Eigen::Vector3d* J_td) {
  const Eigen::Matrix3d R = x.q_WB.toRotationMatrix();
  const Eigen::Vector3d p_B = R.transpose() * (l_W - x.p_WB);
  const Eigen::Vector3d p_C = P.R_CB * p_B + P.p_CB;
  if (!(p_C.z() > 1e-3)) return 0;
  const double iz = 1.0 / p_C.z();
  const double isp = 1.0 / o.sigma_px;
  const int rows = o.depth_m > 0.0 ? 3 : 2;
  // The pixel where the feature was at the state's time (first order).
  const Eigen::Vector2d uv = o.uv - o.uv_vel_pxps * td_s;
  (*r)(0) = (P.K.fx * p_C.x() * iz + P.K.cx - uv.x()) * isp;
  (*r)(1) = (P.K.fy * p_C.y() * iz + P.K.cy - uv.y()) * isp;
  // The depth too was measured at t + t_d: moved back along its own rate.
  (*r)(2) = rows == 3 ? (p_C.z() - (o.depth_m - o.depth_vel_mps * td_s)) / o.sigma_depth_m : 0.0;
  if (J_td) {
    *J_td = Eigen::Vector3d(o.uv_vel_pxps.x() * isp, o.uv_vel_pxps.y() * isp,
                            rows == 3 ? o.depth_vel_mps / o.sigma_depth_m : 0.0);
  }
  if (J_pose == nullptr && J_l == nullptr) return rows;
  // d r / d p_C, whitened.
  Eigen::Matrix3d D = Eigen::Matrix3d::Zero();
  D(0, 0) = P.K.fx * iz * isp;
  D(0, 2) = -P.K.fx * p_C.x() * iz * iz * isp;
  D(1, 1) = P.K.fy * iz * isp;
  D(1, 2) = -P.K.fy * p_C.y() * iz * iz * isp;
  if (rows == 3) D(2, 2) = 1.0 / o.sigma_depth_m;
  const Eigen::Matrix3d DR = D * P.R_CB;  // d r / d p_B
  if (J_pose) {
    // p_B = R^T (l - p): d/dp = -R^T; with R <- R Exp(dphi): p_B <- Exp(-dphi) p_B, d/dphi = [p_B]x.
    J_pose->leftCols<3>() = -DR * R.transpose();
    J_pose->rightCols<3>() = DR * so3::hat(p_B);
  }
  if (J_l) *J_l = DR * R.transpose();
  return rows;
}

double time_offset_prior_residual(const WindowProblem& P, double td_s, double* J) {
  if (P.td_meas_sigma_s > 0.0) {
    const double w = 1.0 / P.td_meas_sigma_s;
    if (J) *J = w;
    return w * (td_s - P.td_meas_s);
  }
  const double w = 1.0 / (1e-3 * P.opt.time_offset_prior_sigma_ms);
  if (J) *J = w;
  return w * td_s;
}

Vector15d imu_bias_residual(const WindowProblem& P, const WindowState& sj, const NavState& x_i,
                            const NavState& x_j, Matrix15d* J_i, Matrix15d* J_j) {
  Vector15d r;
  ImuFactorJacobians Jimu;
  BiasFactorJacobians Jb;
  const bool want = J_i != nullptr || J_j != nullptr;
  r.head<9>() = sj.imu_sqrt_info * imu_residual(sj.pim, x_i, x_j, want ? &Jimu : nullptr);
  r.tail<6>() = sj.bias_sqrt_info.asDiagonal() *
                bias_residual(x_i, x_j, sj.pim.dt_total(), P.bias_noise, want ? &Jb : nullptr);
  if (!want) return r;
  if (J_i) {
    J_i->setZero();
    J_i->block<9, 3>(0, 0) = sj.imu_sqrt_info * Jimu.p_i;
    J_i->block<9, 3>(0, 3) = sj.imu_sqrt_info * Jimu.phi_i;
    J_i->block<9, 3>(0, 6) = sj.imu_sqrt_info * Jimu.v_i;
    J_i->block<9, 3>(0, 9) = sj.imu_sqrt_info * Jimu.bg_i;
    J_i->block<9, 3>(0, 12) = sj.imu_sqrt_info * Jimu.ba_i;
    J_i->block<6, 3>(9, 9) = sj.bias_sqrt_info.asDiagonal() * Jb.bg_i;
    J_i->block<6, 3>(9, 12) = sj.bias_sqrt_info.asDiagonal() * Jb.ba_i;
  }
  if (J_j) {
    J_j->setZero();
    J_j->block<9, 3>(0, 0) = sj.imu_sqrt_info * Jimu.p_j;
    J_j->block<9, 3>(0, 3) = sj.imu_sqrt_info * Jimu.phi_j;
    J_j->block<9, 3>(0, 6) = sj.imu_sqrt_info * Jimu.v_j;
    J_j->block<6, 3>(9, 9) = sj.bias_sqrt_info.asDiagonal() * Jb.bg_j;
    J_j->block<6, 3>(9, 12) = sj.bias_sqrt_info.asDiagonal() * Jb.ba_j;
  }
  return r;
}

double yaw_of(const Eigen::Quaterniond& q_WB) {
  const Eigen::Matrix3d R = q_WB.toRotationMatrix();
  return std::atan2(R(1, 0), R(0, 0));
}

Eigen::Vector4d gauge_residual(const WindowProblem& P, const NavState& x, Eigen::Matrix<double, 4, 6>* J) {
  const double w = 1.0 / P.opt.gauge_sigma;
  const Eigen::Matrix3d R = x.q_WB.toRotationMatrix();
  double dyaw = std::atan2(R(1, 0), R(0, 0)) - P.gauge_yaw;
  dyaw = std::remainder(dyaw, 2.0 * M_PI);
  Eigen::Vector4d r;
  r.head<3>() = w * (x.p_WB - P.gauge_p);
  r(3) = w * dyaw;
  if (J) {
    J->setZero();
    J->block<3, 3>(0, 0) = w * Eigen::Matrix3d::Identity();
    // Yaw under a left perturbation theta (R <- Exp(theta) R):
    // d yaw = theta_z - (R00 R20 theta_x + R10 R20 theta_y) / (R00^2 + R10^2);
    // the right perturbation is theta = R dphi.
    const double n = std::max(1e-12, R(0, 0) * R(0, 0) + R(1, 0) * R(1, 0));
    const Eigen::RowVector3d dyaw_dtheta(-R(0, 0) * R(2, 0) / n, -R(1, 0) * R(2, 0) / n, 1.0);
    J->block<1, 3>(3, 3) = w * dyaw_dtheta * R;
  }
  return r;
}

Eigen::Vector3d gauge_rotation_residual(const WindowProblem& P, const NavState& x,
                                        Eigen::Matrix<double, 3, 6>* J) {
  const Eigen::Vector3d phi = so3::Log(P.gauge_q.toRotationMatrix().transpose() * x.q_WB.toRotationMatrix());
  if (J) {
    J->setZero();
    J->rightCols<3>() = so3::right_jacobian_inv(phi) / P.opt.gauge_sigma;
  }
  return phi / P.opt.gauge_sigma;
}

Vector9d hold_weights(const WindowProblem& P) {
  Vector9d w;
  w.segment<3>(0).setConstant(1.0 / P.opt.hold_velocity_sigma_mps);
  w.segment<3>(3).setConstant(1.0 / P.opt.hold_gyro_bias_sigma_rps);
  w.segment<3>(6).setConstant(1.0 / P.opt.hold_acc_bias_sigma_mps2);
  return w;
}

Vector9d hold_residual(const WindowProblem& P, const WindowState& st, const NavState& x) {
  Vector9d d;
  d.segment<3>(0) = x.v_WB - st.hold_x.v_WB;
  d.segment<3>(3) = x.bg_rps - st.hold_x.bg_rps;
  d.segment<3>(6) = x.ba_mps2 - st.hold_x.ba_mps2;
  return d.cwiseProduct(hold_weights(P));
}

Vector6d pose_prior_residual(const WindowState& st, const NavState& x, Matrix6d* J) {
  Vector6d r;
  const Eigen::Vector3d phi =
      so3::Log(st.prior_q_WB.toRotationMatrix().transpose() * x.q_WB.toRotationMatrix());
  r.head<3>() = (x.p_WB - st.prior_p_WB) / st.prior_sigma_p_m;
  r.tail<3>() = phi / st.prior_sigma_rad;
  if (J) {
    J->setZero();
    J->topLeftCorner<3, 3>().diagonal().setConstant(1.0 / st.prior_sigma_p_m);
    J->bottomRightCorner<3, 3>() = so3::right_jacobian_inv(phi) / st.prior_sigma_rad;
  }
  return r;
}

Vector15d state_minus(const NavState& x, const NavState& x0, Eigen::Matrix3d* J_rot) {
  Vector15d d;
  d.segment<3>(0) = x.p_WB - x0.p_WB;
  const Eigen::Vector3d phi = so3::Log(x0.q_WB.toRotationMatrix().transpose() * x.q_WB.toRotationMatrix());
  d.segment<3>(3) = phi;
  d.segment<3>(6) = x.v_WB - x0.v_WB;
  d.segment<3>(9) = x.bg_rps - x0.bg_rps;
  d.segment<3>(12) = x.ba_mps2 - x0.ba_mps2;
  if (J_rot) *J_rot = so3::right_jacobian_inv(phi);
  return d;
}

NavState state_plus(const NavState& x, const Vector15d& d) {
  NavState y = x;
  y.p_WB += d.segment<3>(0);
  y.q_WB = (x.q_WB * so3::exp_quat(d.segment<3>(3))).normalized();
  y.v_WB += d.segment<3>(6);
  y.bg_rps += d.segment<3>(9);
  y.ba_mps2 += d.segment<3>(12);
  return y;
}

}  // namespace kestrel::core
