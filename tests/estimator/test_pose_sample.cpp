// The one pose type of the pipeline: its views and setters agree with the
// numbers it stores, and the map-frame pose composes T_map_odom on the left.
#include <gtest/gtest.h>

#include <cstring>

#include "kestrel/core/pose_sample.hpp"

namespace kestrel::core {
namespace {

TEST(PoseSample, ViewsAndSettersRoundTripExactly) {
  PoseSample s;
  const Eigen::Vector3d p(1.5, -2.25, 3.125), v(0.1, 0.2, -0.3), w(0.01, -0.02, 0.03);
  const Eigen::Quaterniond q(Eigen::AngleAxisd(0.7, Eigen::Vector3d(0.2, -0.3, 1.0).normalized()));
  s.set_p_WB(p);
  s.set_q_WB(q);
  s.set_v_WB(v);
  s.set_omega_B(w);
  EXPECT_EQ(s.p_WB(), p);
  EXPECT_EQ(s.q_WB().coeffs(), q.coeffs());
  EXPECT_EQ(s.v_WB(), v);
  EXPECT_EQ(s.omega_B(), w);
  EXPECT_EQ(s.q_WB_wxyz[0], q.w()) << "stored w first";

  PoseCovariance c;
  for (int i = 0; i < 36; ++i) c.cov.data()[i] = 0.5 * i;
  c.t_ns = 42;
  c.valid = true;
  s.set_covariance(c);
  const PoseCovariance back = s.covariance();
  EXPECT_EQ(back.cov, c.cov);
  EXPECT_EQ(back.t_ns, 42);
  EXPECT_TRUE(back.valid);

  // A raw copy (what a ring or mailbox does) is the same pose.
  PoseSample copy;
  std::memcpy(static_cast<void*>(&copy), &s, sizeof s);
  EXPECT_EQ(copy.p_WB(), p);
  EXPECT_EQ(copy.covariance().cov, c.cov);
}

TEST(PoseSample, MapPoseComposesTheMapCorrection) {
  PoseSample s;
  s.set_p_WB(Eigen::Vector3d(1, 0, 0));
  s.set_q_WB(Eigen::Quaterniond(Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ())));
  EXPECT_TRUE(s.T_map_body().isApprox(s.T_WB())) << "no map: the odometry";
  Eigen::Isometry3d T_map_odom = Eigen::Isometry3d::Identity();
  T_map_odom.translation() = Eigen::Vector3d(0, 2, 0);
  T_map_odom.linear() = Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  s.map.active = true;
  s.map.set_T_map_odom(T_map_odom);
  const Eigen::Isometry3d T = s.T_map_body();
  // The body at (1, 0, 0) in W is at (0, 1, 0) + (0, 2, 0) in the map.
  EXPECT_TRUE(T.translation().isApprox(Eigen::Vector3d(0, 3, 0), 1e-12));
  EXPECT_TRUE(
      T.linear().isApprox(Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitZ()).toRotationMatrix(), 1e-12));
}

TEST(PoseSample, OfANavStateTakesTheBiasOffTheGyro) {
  NavState x;
  x.t_ns = 123;
  x.p_WB = Eigen::Vector3d(1, 2, 3);
  x.v_WB = Eigen::Vector3d(4, 5, 6);
  x.bg_rps = Eigen::Vector3d(0.01, 0.02, 0.03);
  const PoseSample s = pose_sample_of(x, Vec3d{0.11, 0.22, 0.33});
  EXPECT_EQ(s.t_ns, 123);
  EXPECT_EQ(s.p_WB(), x.p_WB);
  EXPECT_EQ(s.v_WB(), x.v_WB);
  EXPECT_DOUBLE_EQ(s.omega_B_rps[0], 0.11 - 0.01);
  EXPECT_DOUBLE_EQ(s.omega_B_rps[2], 0.33 - 0.03);
  EXPECT_EQ(s.quality, TrackingQuality::kUninitialized);
  EXPECT_FALSE(s.pose_cov_valid);
}

}  // namespace
}  // namespace kestrel::core
