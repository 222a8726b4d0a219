#include "kestrel/core/ekf_geometry.hpp"

#include <cmath>

namespace kestrel::core::ekf {

Mat3 skew(const Vec3& v) {
  Mat3 S;
  S << 0.0, -v.z(), v.y(), v.z(), 0.0, -v.x(), -v.y(), v.x(), 0.0;
  return S;
}

Mat3 so3_exp(const Vec3& phi) {
  const double th2 = phi.squaredNorm();
  const Mat3 K = skew(phi);
  if (th2 < 1e-16) return Mat3::Identity() + K + 0.5 * K * K;
  const double th = std::sqrt(th2);
  return Mat3::Identity() + (std::sin(th) / th) * K + ((1.0 - std::cos(th)) / th2) * K * K;
}

Vec3 so3_log(const Mat3& R) {
  // Through the quaternion: well conditioned up to and including pi.
  Eigen::Quaterniond q(R);
  q.normalize();
  if (q.w() < 0.0) q.coeffs() = -q.coeffs();
  const double n = q.vec().norm();
  if (n < 1e-12) return 2.0 * q.vec() / q.w();
  return (2.0 * std::atan2(n, q.w()) / n) * q.vec();
}

Mat3 so3_left_jacobian(const Vec3& phi) {
  const double th2 = phi.squaredNorm();
  const Mat3 K = skew(phi);
  if (th2 < 1e-12) return Mat3::Identity() + 0.5 * K + (1.0 / 6.0) * K * K;
  const double th = std::sqrt(th2);
  return Mat3::Identity() + ((1.0 - std::cos(th)) / th2) * K + ((th - std::sin(th)) / (th2 * th)) * K * K;
}

Pose se3_exp(const Vec6& xi) {
  const Vec3 rho = xi.head<3>(), theta = xi.tail<3>();
  return {so3_exp(theta), so3_left_jacobian(theta) * rho};
}

Vec6 se3_log(const Pose& T) {
  Vec6 xi;
  xi.tail<3>() = so3_log(T.R);
  xi.head<3>() = so3_left_jacobian(xi.tail<3>()).partialPivLu().solve(T.p);
  return xi;
}

Mat6 se3_adjoint(const Pose& T) {
  Mat6 A = Mat6::Zero();
  A.topLeftCorner<3, 3>() = T.R;
  A.topRightCorner<3, 3>() = skew(T.p) * T.R;
  A.bottomRightCorner<3, 3>() = T.R;
  return A;
}

bool stereo_project(const StereoCamera& cam, const Pose& T_WB, const Vec3& m_W, double min_depth_m,
                    StereoMeas& z, Eigen::Matrix<double, 3, 6>* J_pose, Mat3* J_m) {
  const Vec3 p_B = T_WB.R.transpose() * (m_W - T_WB.p);
  const Vec3 q = cam.T_CB.R * p_B + cam.T_CB.p;
  if (!(q.z() >= min_depth_m)) return false;
  const double iz = 1.0 / q.z();
  z << cam.fsu * q.x() * iz + cam.cu, cam.fsv * q.y() * iz + cam.cv,
      cam.fsu * (q.x() - cam.baseline_m) * iz + cam.cu;
  if (J_pose == nullptr && J_m == nullptr) return true;
  Mat3 J_q;
  J_q << cam.fsu * iz, 0.0, -cam.fsu * q.x() * iz * iz,  //
      0.0, cam.fsv * iz, -cam.fsv * q.y() * iz * iz,     //
      cam.fsu * iz, 0.0, -cam.fsu * (q.x() - cam.baseline_m) * iz * iz;
  const Mat3 J_qB = J_q * cam.T_CB.R;
  // Right perturbation: p_B(xi) = exp(-xi^) p_B = p_B - rho + p_B^ theta.
  if (J_pose != nullptr) {
    J_pose->leftCols<3>() = -J_qB;
    J_pose->rightCols<3>() = J_qB * skew(p_B);
  }
  if (J_m != nullptr) *J_m = J_qB * T_WB.R.transpose();
  return true;
}

bool stereo_triangulate(const StereoCamera& cam, const StereoMeas& z, Vec3& p_C, Mat3* J_z) {
  const double d = z(0) - z(2);
  if (!(d > 0.0)) return false;
  const double b = cam.baseline_m;
  const double du = z(0) - cam.cu, dv = z(1) - cam.cv;
  const double k = cam.fsu / cam.fsv;
  p_C << du * b / d, dv * k * b / d, cam.fsu * b / d;
  if (J_z != nullptr) {
    const double id2 = 1.0 / (d * d);
    // Columns: d/duL, d/dv, d/duR, with d = uL - uR.
    *J_z << b / d - du * b * id2, 0.0, du * b * id2,     //
        -dv * k * b * id2, k * b / d, dv * k * b * id2,  //
        -cam.fsu * b * id2, 0.0, cam.fsu * b * id2;
  }
  return true;
}

void imu_step(ImuNominal& x, const Vec3& gyro_rps, const Vec3& acc_mps2, double dt_s, double gravity_mps2,
              Eigen::Matrix<double, 15, 15>* Phi, Eigen::Matrix<double, 15, 12>* G) {
  const Vec3 w = gyro_rps - x.bg;
  const Vec3 a = acc_mps2 - x.ba;
  const Vec3 g(0.0, 0.0, -gravity_mps2);
  const Mat3 R = x.T_WB.R;
  const Mat3 dR = so3_exp(w * dt_s);
  const Vec3 acc_W = R * a + g;
  x.T_WB.p += x.v_WB * dt_s + 0.5 * acc_W * dt_s * dt_s;
  x.v_WB += acc_W * dt_s;
  // Re-orthonormalised through the quaternion so R stays a rotation over long runs.
  x.T_WB.R = Eigen::Quaterniond(R * dR).normalized().toRotationMatrix();
  const Mat3 dRt = dR.transpose();
  const Mat3 Rn_t = (R * dR).transpose();
  const Mat3 Jr = so3_left_jacobian(-w * dt_s);  // J_r(phi) = J_l(-phi)
  const Mat3 ax = skew(a);
  const double dt2 = dt_s * dt_s;
  if (Phi != nullptr) {
    Phi->setIdentity();
    Phi->block<3, 3>(0, 0) = dRt;
    Phi->block<3, 3>(0, 3) = -0.5 * dt2 * dRt * ax;
    Phi->block<3, 3>(0, 6) = Rn_t * dt_s;
    Phi->block<3, 3>(0, 12) = -0.5 * dt2 * dRt;
    Phi->block<3, 3>(3, 3) = dRt;
    Phi->block<3, 3>(3, 9) = -Jr * dt_s;
    Phi->block<3, 3>(6, 3) = -R * ax * dt_s;
    Phi->block<3, 3>(6, 12) = -R * dt_s;
  }
  if (G != nullptr) {
    G->setZero();
    G->block<3, 3>(0, 3) = -0.5 * dt2 * dRt;
    G->block<3, 3>(3, 0) = -Jr * dt_s;
    G->block<3, 3>(6, 3) = -R * dt_s;
    G->block<3, 3>(9, 6) = Mat3::Identity() * dt_s;
    G->block<3, 3>(12, 9) = Mat3::Identity() * dt_s;
  }
}

}  // namespace kestrel::core::ekf
