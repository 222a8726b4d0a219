// SE(3), the stereo observation model and the IMU step of the EKF backend:
// every analytic Jacobian against numerical differentiation.
#include <gtest/gtest.h>

#include <random>

#include "jacobian_check.hpp"
#include "kestrel/core/ekf_geometry.hpp"

namespace {

using namespace kestrel::core::ekf;
using kestrel::test::check_jacobian;

struct Rng {
  std::mt19937_64 g{42};
  double u(double a, double b) { return std::uniform_real_distribution<double>(a, b)(g); }
  Vec3 v3(double s) { return Vec3(u(-s, s), u(-s, s), u(-s, s)); }
};

Pose random_pose(Rng& r, double trans) { return Pose(so3_exp(r.v3(1.5)), r.v3(trans)); }

StereoCamera kitti_like_camera() {
  StereoCamera c;
  c.fsu = 707.09;
  c.fsv = 707.09;
  c.cu = 601.89;
  c.cv = 183.11;
  c.baseline_m = 0.537;
  // Camera looking along body +x (x right = -y_B, y down = -z_B), offset.
  Mat3 R_BC;
  R_BC << 0, 0, 1, -1, 0, 0, 0, -1, 0;
  c.T_CB = Pose(R_BC, Vec3(1.1, -0.3, 0.7)).inverse();
  return c;
}

TEST(EkfGeometry, ExpLogRoundTripAndAdjoint) {
  Rng r;
  for (int i = 0; i < 50; ++i) {
    Vec6 xi;
    xi << r.v3(3.0), r.v3(1.7);  // |theta| < pi: the log is unique there
    const Pose T = se3_exp(xi);
    EXPECT_LT((se3_log(T) - xi).norm(), 1e-9) << xi.transpose();
    // T exp(d^) T^-1 = exp((Ad(T) d)^)
    Vec6 d;
    d << r.v3(0.3), r.v3(0.3);
    const Pose lhs = T * se3_exp(d) * T.inverse();
    const Pose rhs = se3_exp(se3_adjoint(T) * d);
    EXPECT_LT((lhs.R - rhs.R).norm() + (lhs.p - rhs.p).norm(), 1e-9);
  }
}

TEST(EkfGeometry, StereoJacobiansMatchNumeric) {
  Rng r;
  const StereoCamera cam = kitti_like_camera();
  int checked = 0;
  for (int i = 0; i < 200 && checked < 30; ++i) {
    const Pose T_WB = random_pose(r, 20.0);
    // A point in front of the camera, 2..40 m away.
    const Vec3 p_C(r.u(-8, 8), r.u(-3, 3), r.u(2, 40));
    const Vec3 m_W = T_WB * (cam.T_CB.inverse() * p_C);
    StereoMeas z;
    Eigen::Matrix<double, 3, 6> Jp;
    Mat3 Jm;
    ASSERT_TRUE(stereo_project(cam, T_WB, m_W, 0.1, z, &Jp, &Jm));
    EXPECT_TRUE(check_jacobian(
        Jp,
        [&](const Eigen::VectorXd& d) {
          StereoMeas zz;
          stereo_project(cam, T_WB * se3_exp(d), m_W, 0.1, zz);
          return Eigen::VectorXd(zz);
        },
        1e-5, 1e-6));
    EXPECT_TRUE(check_jacobian(
        Jm,
        [&](const Eigen::VectorXd& d) {
          StereoMeas zz;
          stereo_project(cam, T_WB, m_W + d, 0.1, zz);
          return Eigen::VectorXd(zz);
        },
        1e-5, 1e-6));
    // Triangulation inverts the projection, and its Jacobian is right.
    Vec3 p_back;
    Mat3 Jz;
    ASSERT_TRUE(stereo_triangulate(cam, z, p_back, &Jz));
    EXPECT_LT((p_back - p_C).norm(), 1e-9 * p_C.norm());
    EXPECT_TRUE(check_jacobian(
        Jz,
        [&](const Eigen::VectorXd& d) {
          Vec3 p;
          stereo_triangulate(cam, z + d, p);
          return Eigen::VectorXd(p);
        },
        1e-5, 1e-6, 1e-4));
    ++checked;
  }
  EXPECT_EQ(checked, 30);
}

TEST(EkfGeometry, StereoRejectsPointsBehindAndZeroDisparity) {
  const StereoCamera cam = kitti_like_camera();
  StereoMeas z;
  const Vec3 behind_W = Pose().inverse() * (cam.T_CB.inverse() * Vec3(0, 0, -5));
  EXPECT_FALSE(stereo_project(cam, Pose(), behind_W, 0.1, z));
  Vec3 p;
  EXPECT_FALSE(stereo_triangulate(cam, StereoMeas(100, 50, 100), p));
  EXPECT_FALSE(stereo_triangulate(cam, StereoMeas(100, 50, 120), p));
}

// The IMU step's Phi is the exact Jacobian of the step (numerically, through
// the SE(3) retraction, which agrees with the filter's to first order).
TEST(EkfGeometry, ImuStepJacobianMatchesNumeric) {
  Rng r;
  for (int trial = 0; trial < 10; ++trial) {
    ImuNominal x0;
    x0.T_WB = random_pose(r, 5.0);
    x0.v_WB = r.v3(3.0);
    x0.bg = r.v3(0.05);
    x0.ba = r.v3(0.3);
    const Vec3 gyro = r.v3(2.0), acc = r.v3(5.0) + Vec3(0, 0, 9.81);
    const double dt = trial < 5 ? 0.005 : 0.1;
    Eigen::Matrix<double, 15, 15> Phi;
    Eigen::Matrix<double, 15, 12> G;
    ImuNominal x1 = x0;
    imu_step(x1, gyro, acc, dt, 9.81, &Phi, &G);
    auto retract = [](const ImuNominal& x, const Eigen::VectorXd& d) {
      ImuNominal y = x;
      y.T_WB = x.T_WB * se3_exp(d.head<6>());
      y.v_WB += d.segment<3>(6);
      y.bg += d.segment<3>(9);
      y.ba += d.segment<3>(12);
      return y;
    };
    auto local = [](const ImuNominal& ref, const ImuNominal& x) {
      Eigen::VectorXd e(15);
      e.head<6>() = se3_log(ref.T_WB.inverse() * x.T_WB);
      e.segment<3>(6) = x.v_WB - ref.v_WB;
      e.segment<3>(9) = x.bg - ref.bg;
      e.segment<3>(12) = x.ba - ref.ba;
      return e;
    };
    EXPECT_TRUE(check_jacobian(
        Phi,
        [&](const Eigen::VectorXd& d) {
          ImuNominal y = retract(x0, d);
          imu_step(y, gyro, acc, dt, 9.81, nullptr, nullptr);
          return local(x1, y);
        },
        1e-5, 1e-7))
        << "dt " << dt;
    // Noise input: a gyro / accel / bias-rate perturbation held over the step.
    EXPECT_TRUE(check_jacobian(
        G,
        [&](const Eigen::VectorXd& n) {
          ImuNominal y = x0;
          imu_step(y, gyro - n.head<3>(), acc - n.segment<3>(3), dt, 9.81, nullptr, nullptr);
          y.bg += n.segment<3>(6) * dt;
          y.ba += n.segment<3>(9) * dt;
          return local(x1, y);
        },
        1e-5, 1e-7))
        << "dt " << dt;
  }
}

}  // namespace
