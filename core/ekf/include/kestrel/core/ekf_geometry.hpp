// SE(3) and stereo-camera geometry for the EKF backend (docs/ekf.md).
//
// Twist / error ordering follows paper 003 (and Barfoot's "State Estimation
// for Robotics"): xi = [rho; theta], translation first. Pose errors are right
// perturbations, T = T_hat * exp(xi^), so they live in the body (IMU) frame.
// Every Jacobian here is checked numerically in tests/ekf.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace kestrel::core::ekf {

using Mat3 = Eigen::Matrix3d;
using Vec3 = Eigen::Vector3d;
using Vec6 = Eigen::Matrix<double, 6, 1>;
using Mat6 = Eigen::Matrix<double, 6, 6>;

Mat3 skew(const Vec3& v);
// SO(3) exponential (Rodrigues), exact for any angle.
Mat3 so3_exp(const Vec3& phi);
Vec3 so3_log(const Mat3& R);
// Left Jacobian of SO(3): the V matrix of the SE(3) exponential.
Mat3 so3_left_jacobian(const Vec3& phi);

// A rigid transform T_AB as (R_AB, p_AB): p_A = R_AB p_B + p_AB.
struct Pose {
  Mat3 R = Mat3::Identity();
  Vec3 p = Vec3::Zero();
  Pose() = default;
  Pose(const Mat3& R_, const Vec3& p_) : R(R_), p(p_) {}
  Pose operator*(const Pose& o) const { return {R * o.R, R * o.p + p}; }
  Vec3 operator*(const Vec3& x) const { return R * x + p; }
  Pose inverse() const { return {R.transpose(), -(R.transpose() * p)}; }
};

// exp(xi^) for xi = [rho; theta].
Pose se3_exp(const Vec6& xi);
Vec6 se3_log(const Pose& T);
// Ad(T) in [rho; theta] ordering: [[R, p^ R], [0, R]], so that
// T exp(xi^) T^-1 = exp((Ad(T) xi)^).
Mat6 se3_adjoint(const Pose& T);

// Rectified stereo pair: left camera C with intrinsics (fsu, fsv, cu, cv), the
// right camera displaced by baseline_m along C's +x. T_CB maps body (IMU)
// coordinates into the left camera. For an RGB-D camera the "right" image is
// virtual: uR = uL - fsu * baseline_m / depth (docs/ekf.md, "RGB-D").
struct StereoCamera {
  double fsu = 0.0, fsv = 0.0, cu = 0.0, cv = 0.0;
  double baseline_m = 0.0;
  Pose T_CB;
};

// The compressed stereo measurement [uL, v, uR]. Paper 003's four rows
// [uL, vL, uR, vR] have two identical rows for a rectified pair (vL and vR
// predict the same number), so the state only sees their mean, with half the
// variance; the difference vL - vR is pure noise and only enters the outlier
// gate. The compression loses nothing (docs/ekf.md).
using StereoMeas = Eigen::Vector3d;

// Predicted measurement of world point m_W seen from body pose T_WB. Returns
// false (and leaves the outputs unspecified) when the point is not in front of
// the camera by at least min_depth_m. J_pose: d z / d xi for the right
// perturbation T_WB exp(xi^); J_m: d z / d m_W.
bool stereo_project(const StereoCamera& cam, const Pose& T_WB, const Vec3& m_W, double min_depth_m,
                    StereoMeas& z, Eigen::Matrix<double, 3, 6>* J_pose = nullptr, Mat3* J_m = nullptr);

// Triangulates a measurement into the left-camera frame: depth from the
// disparity, z = fsu * b / (uL - uR). Returns false when the disparity is not
// positive. J_z: d p_C / d [uL, v, uR].
bool stereo_triangulate(const StereoCamera& cam, const StereoMeas& z, Vec3& p_C, Mat3* J_z = nullptr);

// The nominal (mean) state of the IMU motion model.
struct ImuNominal {
  Pose T_WB;
  Vec3 v_WB = Vec3::Zero();
  Vec3 bg = Vec3::Zero();  // gyro bias [rad/s]
  Vec3 ba = Vec3::Zero();  // accelerometer bias [m/s^2]
};

// One Euler strapdown step with the sample held over dt (W has gravity along
// -z). Phi: the exact Jacobian of this step for the error state
// [rho, theta, dv, dbg, dba] with R = R_hat Exp(theta), p = p_hat + R_hat rho
// (to first order the same as the SE(3) right perturbation); G: how the white
// noises [n_g, n_a, n_bg, n_ba] enter over the step.
void imu_step(ImuNominal& x, const Vec3& gyro_rps, const Vec3& acc_mps2, double dt_s, double gravity_mps2,
              Eigen::Matrix<double, 15, 15>* Phi, Eigen::Matrix<double, 15, 12>* G);

}  // namespace kestrel::core::ekf
