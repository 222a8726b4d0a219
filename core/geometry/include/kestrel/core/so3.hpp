// SO(3) helpers in the convention of Forster et al., TRO 2017, Sec. III:
//   Exp(phi + dphi) ~= Exp(phi) Exp(Jr(phi) dphi)                    (eq. 7)
//   Log(Exp(phi) Exp(dphi)) ~= phi + Jr^-1(phi) dphi                  (eq. 9)
// Header-only, fixed-size, allocation-free: called per IMU sample.
// Small angles use series (truncation below 1e-16), so zero and tiny rotations
// are exact instead of 0/0 or cancellation noise.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>

namespace kestrel::core::so3 {

inline Eigen::Matrix3d hat(const Eigen::Vector3d& v) {
  Eigen::Matrix3d m;
  m << 0.0, -v.z(), v.y(), v.z(), 0.0, -v.x(), -v.y(), v.x(), 0.0;
  return m;
}

inline Eigen::Vector3d vee(const Eigen::Matrix3d& m) { return {m(2, 1), m(0, 2), m(1, 0)}; }

// Rodrigues' formula, I + A W + B W^2 with A = sin(t)/t, B = (1 - cos t)/t^2
// written as 2 sin^2(t/2)/t^2 (no cancellation).
inline Eigen::Matrix3d Exp(const Eigen::Vector3d& phi) {
  const double t2 = phi.squaredNorm();
  const Eigen::Matrix3d W = hat(phi);
  double A, B;
  if (t2 < 1e-8) {
    A = 1.0 - t2 / 6.0;
    B = 0.5 - t2 / 24.0;
  } else {
    const double t = std::sqrt(t2);
    const double s = std::sin(0.5 * t);
    A = std::sin(t) / t;
    B = 2.0 * s * s / t2;
  }
  return Eigen::Matrix3d::Identity() + A * W + B * W * W;
}

// Exp as a unit quaternion, for integrators that keep q_WB. The first-order
// branch keeps a zero rate exact.
inline Eigen::Quaterniond exp_quat(const Eigen::Vector3d& phi) {
  const double theta = phi.norm();
  if (theta < 1e-9) return Eigen::Quaterniond(1.0, 0.5 * phi.x(), 0.5 * phi.y(), 0.5 * phi.z()).normalized();
  return Eigen::Quaterniond(Eigen::AngleAxisd(theta, phi / theta));
}

// Inverse of Exp for a proper rotation; angle in [0, pi].
inline Eigen::Vector3d Log(const Eigen::Matrix3d& R) {
  const Eigen::Vector3d w(R(2, 1) - R(1, 2), R(0, 2) - R(2, 0), R(1, 0) - R(0, 1));  // 2 sin(t) axis
  const double c = 0.5 * (R.trace() - 1.0);
  const double s2 = w.norm();  // 2 sin(t)
  // atan2 keeps the angle accurate at both ends, where acos(c) does not.
  const double t = std::atan2(0.5 * s2, c);
  if (t < 1e-4) return (0.5 + t * t / 12.0) * w;  // t / (2 sin t) series
  if (c > -0.99) return (t / s2) * w;
  // Near pi the antisymmetric part vanishes, but the symmetric part
  // (R + R^T)/2 = c I + (1 - c) a a^T still holds the axis exactly; the
  // antisymmetric part only fixes its sign.
  const Eigen::Matrix3d B = (0.5 * (R + R.transpose()) - c * Eigen::Matrix3d::Identity()) / (1.0 - c);
  int k = 0;
  B.diagonal().maxCoeff(&k);
  Eigen::Vector3d a = B.col(k) / std::sqrt(std::max(1e-300, B(k, k)));
  a.normalize();
  if (a.dot(w) < 0.0) a = -a;
  return t * a;
}

// Right Jacobian of SO(3) (Forster eq. 8; Chirikjian):
// Jr = I - (1 - cos t)/t^2 W + (t - sin t)/t^3 W^2.
inline Eigen::Matrix3d right_jacobian(const Eigen::Vector3d& phi) {
  const double t2 = phi.squaredNorm();
  const Eigen::Matrix3d W = hat(phi);
  double B, C;
  if (t2 < 1e-4) {  // t < 1e-2: the series' next terms are below 1e-17
    B = 0.5 - t2 / 24.0 + t2 * t2 / 720.0;
    C = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0;
  } else {
    const double t = std::sqrt(t2);
    const double s = std::sin(0.5 * t);
    B = 2.0 * s * s / t2;
    C = (t - std::sin(t)) / (t2 * t);
  }
  return Eigen::Matrix3d::Identity() - B * W + C * W * W;
}

// Inverse right Jacobian (Forster eq. 8):
// Jr^-1 = I + W/2 + (1/t^2 - (1 + cos t)/(2 t sin t)) W^2.
inline Eigen::Matrix3d right_jacobian_inv(const Eigen::Vector3d& phi) {
  const double t2 = phi.squaredNorm();
  const Eigen::Matrix3d W = hat(phi);
  double D;
  if (t2 < 1e-4) {
    D = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0;
  } else {
    const double t = std::sqrt(t2);
    D = 1.0 / t2 - (1.0 + std::cos(t)) / (2.0 * t * std::sin(t));
  }
  return Eigen::Matrix3d::Identity() + 0.5 * W + D * W * W;
}

}  // namespace kestrel::core::so3
