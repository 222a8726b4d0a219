#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <sstream>
#include <vector>

#include "kestrel/core/estimator.hpp"
#include "kestrel/core/imu_propagator.hpp"
#include "test_data.hpp"

using kestrel::ImuSample;
using namespace kestrel::core;

namespace {

ImuSample sample(int64_t t_ns, Eigen::Vector3d gyro, Eigen::Vector3d acc) {
  ImuSample s;
  s.t_ns = t_ns;
  for (int i = 0; i < 3; ++i) {
    s.gyro_rps[i] = gyro[i];
    s.acc_mps2[i] = acc[i];
  }
  return s;
}

}  // namespace

TEST(ImuPropagator, ConstantRateRotatesExactly) {
  ImuPropagator p;
  p.reset(NavState{});
  const Eigen::Vector3d w(0.3, -0.2, 0.5);
  // Level, at rest in gravity: the specific force is +g along z_B while the
  // body rotates, so supply it rotated into B at each step.
  const int n = 1000;
  const int64_t dt_ns = 1'000'000;
  for (int k = 0; k <= n; ++k) {
    const double t = k * 1e-3;
    const Eigen::Quaterniond q_WB(Eigen::AngleAxisd(w.norm() * t, w.normalized()));
    const Eigen::Vector3d f_B = q_WB.conjugate() * Eigen::Vector3d(0, 0, 9.81);
    ASSERT_TRUE(p.propagate(sample(k * dt_ns, w, f_B)));
  }
  const Eigen::Quaterniond expected(Eigen::AngleAxisd(w.norm() * 1.0, w.normalized()));
  EXPECT_LT(p.state().q_WB.angularDistance(expected), 1e-9);
  // Midpoint integration of a rotating specific force leaves a small residual.
  EXPECT_LT(p.state().p_WB.norm(), 2e-3);
  EXPECT_LT(p.state().v_WB.norm(), 5e-3);
}

TEST(ImuPropagator, ConstantAccelerationMatchesKinematics) {
  ImuPropagator p;
  p.reset(NavState{});
  const Eigen::Vector3d a_W(0.5, -0.25, 0.1);
  for (int k = 0; k <= 2000; ++k) {
    ASSERT_TRUE(
        p.propagate(sample(k * 1'000'000LL, Eigen::Vector3d::Zero(), a_W + Eigen::Vector3d(0, 0, 9.81))));
  }
  const double t = 2.0;
  EXPECT_LT((p.state().p_WB - 0.5 * a_W * t * t).norm(), 1e-9);
  EXPECT_LT((p.state().v_WB - a_W * t).norm(), 1e-9);
}

TEST(ImuPropagator, BadSamplesAreCountedNotUsed) {
  ImuPropagator p;
  p.reset(NavState{});
  const Eigen::Vector3d f(0, 0, 9.81);
  ASSERT_TRUE(p.propagate(sample(0, Eigen::Vector3d::Zero(), f)));
  ASSERT_TRUE(p.propagate(sample(2'500'000, Eigen::Vector3d::Zero(), f)));
  auto nan = sample(5'000'000, Eigen::Vector3d(NAN, 0, 0), f);
  EXPECT_FALSE(p.propagate(nan));
  auto sat = sample(5'000'000, Eigen::Vector3d::Zero(), f);
  sat.flags = kestrel::kImuAccSaturated;
  EXPECT_FALSE(p.propagate(sat));
  EXPECT_FALSE(p.propagate(sample(2'500'000, Eigen::Vector3d::Zero(), f)));   // duplicate time
  EXPECT_FALSE(p.propagate(sample(1'000'000, Eigen::Vector3d::Zero(), f)));   // out of order
  EXPECT_TRUE(p.propagate(sample(400'000'000, Eigen::Vector3d::Zero(), f)));  // long gap: held
  EXPECT_EQ(p.counts().non_finite, 1u);
  EXPECT_EQ(p.counts().saturated, 1u);
  EXPECT_EQ(p.counts().out_of_order, 2u);
  EXPECT_EQ(p.counts().gaps, 1u);
  EXPECT_LT(p.state().v_WB.norm(), 1e-12);
}

TEST(StaticInitializer, RecoversTiltAndGyroBias) {
  StaticInitializer init;
  const Eigen::Quaterniond q_WB_true(Eigen::AngleAxisd(0.2, Eigen::Vector3d::UnitX()) *
                                     Eigen::AngleAxisd(-0.1, Eigen::Vector3d::UnitY()));
  const Eigen::Vector3d bg(0.01, -0.02, 0.005);
  const Eigen::Vector3d f_B = q_WB_true.conjugate() * Eigen::Vector3d(0, 0, 9.81);
  NavState s0;
  bool done = false;
  for (int k = 0; k < 400 && !done; ++k) done = init.add(sample(k * 2'500'000LL, bg, f_B), s0);
  ASSERT_TRUE(done);
  EXPECT_LT((s0.bg_rps - bg).norm(), 1e-12);
  // Roll and pitch are observable, yaw is not: compare the gravity direction in B.
  const Eigen::Vector3d up_B_est = s0.q_WB.conjugate() * Eigen::Vector3d::UnitZ();
  const Eigen::Vector3d up_B_true = q_WB_true.conjugate() * Eigen::Vector3d::UnitZ();
  EXPECT_LT((up_B_est - up_B_true).norm(), 1e-9);
}

TEST(StaticInitializer, RefusesAMovingWindow) {
  StaticInitializer init;
  NavState s0;
  for (int k = 0; k < 400; ++k) {
    const double w = 0.5 * std::sin(k * 0.05);
    ASSERT_FALSE(
        init.add(sample(k * 2'500'000LL, Eigen::Vector3d(w, 0, 0), Eigen::Vector3d(0, 0, 9.81)), s0));
  }
}

// Real data: EuRoC V1_02 official ground truth carries velocity and biases.
// Starting from the true state with the true biases, 1 s of the real ADIS16448
// IMU must reproduce the true motion to within a few centimetres.
TEST(ImuPropagator, EurocV102OneSecondWindowsFollowGroundTruth) {
  KESTREL_REQUIRE_SHARED("euroc/V1_02_medium/gt_official_200hz.csv");
  struct Gt {
    int64_t t;
    Eigen::Vector3d p, v, bg, ba;
    Eigen::Quaterniond q;
  };
  std::vector<Gt> gt;
  {
    std::ifstream f(kestrel::test::shared_path("euroc/V1_02_medium/gt_official_200hz.csv"));
    std::string line;
    while (std::getline(f, line)) {
      if (line.empty() || line[0] == '#') continue;
      std::replace(line.begin(), line.end(), ',', ' ');
      std::istringstream ss(line);
      Gt g;
      double qw, qx, qy, qz;
      ss >> g.t >> g.p.x() >> g.p.y() >> g.p.z() >> qw >> qx >> qy >> qz >> g.v.x() >> g.v.y() >> g.v.z() >>
          g.bg.x() >> g.bg.y() >> g.bg.z() >> g.ba.x() >> g.ba.y() >> g.ba.z();
      g.q = Eigen::Quaterniond(qw, qx, qy, qz).normalized();
      gt.push_back(g);
    }
  }
  std::vector<ImuSample> imu;
  {
    std::ifstream f(kestrel::test::shared_path("euroc/V1_02_medium/imu0.csv"));
    std::string line;
    while (std::getline(f, line)) {
      if (line.empty() || line[0] == '#') continue;
      std::replace(line.begin(), line.end(), ',', ' ');
      std::istringstream ss(line);
      ImuSample s;
      ss >> s.t_ns >> s.gyro_rps[0] >> s.gyro_rps[1] >> s.gyro_rps[2] >> s.acc_mps2[0] >> s.acc_mps2[1] >>
          s.acc_mps2[2];
      imu.push_back(s);
    }
  }
  ASSERT_GT(gt.size(), 10000u);
  ASSERT_GT(imu.size(), 10000u);

  std::vector<double> errs;
  size_t gi = 200;
  while (gi + 200 < gt.size()) {
    const Gt& a = gt[gi];
    const Gt& b = gt[gi + 200];  // 1 s later at 200 Hz
    NavState s0;
    s0.t_ns = a.t;
    s0.p_WB = a.p;
    s0.q_WB = a.q;
    s0.v_WB = a.v;
    s0.bg_rps = a.bg;
    s0.ba_mps2 = a.ba;
    ImuPropagatorOptions opt;
    opt.gravity_mps2 = 9.81;
    ImuPropagator p(opt);
    p.reset(s0);
    auto it = std::lower_bound(imu.begin(), imu.end(), a.t,
                               [](const ImuSample& s, int64_t t) { return s.t_ns < t; });
    for (; it != imu.end() && it->t_ns <= b.t; ++it) p.propagate(*it);
    errs.push_back((p.state().p_WB - b.p).norm());
    gi += 1000;  // a window every 5 s
  }
  ASSERT_GT(errs.size(), 10u);
  std::sort(errs.begin(), errs.end());
  const double median = errs[errs.size() / 2];
  std::printf("EuRoC V1_02 1 s IMU-only windows: %zu, median position error %.4f m, max %.4f m\n",
              errs.size(), median, errs.back());
  EXPECT_LT(median, 0.05);
}

#include "jacobian_check.hpp"

// The checker itself must be able to fail, or every Jacobian test built on it
// proves nothing.
TEST(JacobianChecker, AcceptsTheRightJacobianAndRejectsAWrongOne) {
  // r(x) = [x0^2 * x1, sin(x1)] around x = (1.5, 0.3), perturbed additively.
  const Eigen::Vector2d x(1.5, 0.3);
  auto r = [&](const Eigen::VectorXd& d) {
    const Eigen::Vector2d y = x + d;
    Eigen::VectorXd out(2);
    out << y[0] * y[0] * y[1], std::sin(y[1]);
    return out;
  };
  Eigen::Matrix2d J;
  J << 2 * x[0] * x[1], x[0] * x[0], 0, std::cos(x[1]);
  EXPECT_TRUE(kestrel::test::check_jacobian(J, r));
  Eigen::Matrix2d wrong = J;
  wrong(1, 1) *= 1.01;
  EXPECT_FALSE(kestrel::test::check_jacobian(wrong, r));
}
