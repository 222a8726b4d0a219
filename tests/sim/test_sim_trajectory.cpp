// Scenario and spline trajectories: derivatives against finite differences,
// IMU dead reckoning back onto the path, GT files, and the hybrid check of
// the EuRoC spline against the real gyro.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>

#include "kestrel/tools/sim_imu.hpp"
#include "kestrel/tools/sim_trajectory.hpp"
#include "test_data.hpp"

namespace kt = kestrel::tools;
using Eigen::Quaterniond;
using Eigen::Vector3d;

namespace {

constexpr double kDeg = M_PI / 180.0;

// Central differences of the pose give velocity, acceleration and body rate.
void expect_consistent(const kt::MotionModel& tr, double t, double tol_v, double tol_a, double tol_w) {
  const double h = 1e-4;
  const kt::TrajectoryState s = tr.state(t), sm = tr.state(t - h), sp = tr.state(t + h);
  const Vector3d v_fd = (sp.p_WB - sm.p_WB) / (2 * h);
  const Vector3d a_fd = (sp.v_WB - sm.v_WB) / (2 * h);
  const Vector3d a_fd2 = (sp.p_WB - 2 * s.p_WB + sm.p_WB) / (h * h);
  const Vector3d w_fd = kt::so3_log(sm.q_WB.conjugate() * sp.q_WB) / (2 * h);
  EXPECT_LT((v_fd - s.v_WB).norm(), tol_v) << tr.description() << " t=" << t;
  EXPECT_LT((a_fd - s.a_WB).norm(), tol_a) << tr.description() << " t=" << t;
  EXPECT_LT((a_fd2 - s.a_WB).norm(), 1e-3 + tol_a) << tr.description() << " t=" << t;
  EXPECT_LT((w_fd - s.w_B).norm(), tol_w) << tr.description() << " t=" << t;
}

std::vector<kt::GtSample> sample(const kt::MotionModel& tr, double t0, double t1, double rate,
                                 double jitter_s = 0.0) {
  std::vector<kt::GtSample> out;
  kt::SimRng rng(7);
  for (int k = 0;; ++k) {
    double t = t0 + k / rate;
    if (t > t1) break;
    if (jitter_s > 0 && k > 0) t += rng.uniform(-jitter_s, jitter_s);
    const kt::TrajectoryState s = tr.state(t);
    kt::GtSample g;
    g.t_ns = 5'000'000'000 + static_cast<int64_t>(std::llround(t * 1e9));
    g.p_WB = s.p_WB;
    g.q_WB = s.q_WB;
    out.push_back(g);
  }
  return out;
}

}  // namespace

TEST(SimScenario, AnalyticDerivativesMatchFiniteDifferences) {
  for (const std::string& name : kt::scenario_names()) {
    const auto tr = kt::make_scenario(name, 60.0);
    for (double t : {0.3, 1.7, 2.9, 3.5, 4.2, 7.77, 12.34, 29.5, 30.6, 31.9, 33.3, 45.0, 59.0})
      expect_consistent(*tr, t, 2e-6, 5e-5, 2e-6);
  }
  const auto fixed = kt::make_scenario("figure8", 30.0, kt::ScenarioOptions{false});
  for (double t : {0.5, 2.5, 11.0}) expect_consistent(*fixed, t, 2e-6, 5e-5, 2e-6);
}

TEST(SimScenario, StartAtRest) {
  for (const std::string& name : kt::scenario_names()) {
    const kt::TrajectoryState s = kt::make_scenario(name, 20.0)->state(0.0);
    EXPECT_LT(s.v_WB.norm(), 1e-12) << name;
    EXPECT_LT(s.a_WB.norm(), 1e-12) << name;
    EXPECT_LT(s.w_B.norm(), 1e-12) << name;
  }
  EXPECT_DOUBLE_EQ(kt::make_scenario("hover")->duration_s(), 189.0);
  EXPECT_THROW(kt::make_scenario("loop"), std::invalid_argument);
}

TEST(SimScenario, ShapesAreAsAdvertised) {
  // hover: within a few cm and degrees of 1.2 m.
  const auto hover = kt::make_scenario("hover");
  double max_dev = 0, max_tilt = 0;
  for (double t = 0; t <= hover->duration_s(); t += 0.1) {
    const auto s = hover->state(t);
    max_dev = std::max(max_dev, (s.p_WB - Vector3d(0, 0, 1.2)).norm());
    max_tilt = std::max(max_tilt, std::acos((s.q_WB * Vector3d::UnitZ()).z()));
  }
  EXPECT_LT(max_dev, 0.15);
  EXPECT_GT(max_dev, 0.02);
  EXPECT_LT(max_tilt, 5 * kDeg);

  // figure8: 3 x 2 m at about 1 m/s.
  const auto f8 = kt::make_scenario("figure8", 60);
  Eigen::AlignedBox3d box;
  double speed = 0;
  int n = 0;
  for (double t = 5; t <= 60; t += 0.05, ++n) {
    const auto s = f8->state(t);
    box.extend(s.p_WB);
    speed += s.v_WB.norm();
  }
  EXPECT_NEAR(box.sizes().x(), 3.0, 0.05);
  EXPECT_NEAR(box.sizes().y(), 2.0, 0.05);
  EXPECT_NEAR(speed / n, 1.0, 0.2);

  // aggressive: bursts near 300 deg/s.
  const auto ag = kt::make_scenario("aggressive", 60);
  double max_w = 0;
  for (double t = 0; t <= 60; t += 0.005) max_w = std::max(max_w, ag->state(t).w_B.norm());
  EXPECT_GT(max_w, 280 * kDeg);
  EXPECT_LT(max_w, 420 * kDeg);

  // static: exactly still for min(30, T/2), then moving.
  for (double T : {60.0, 20.0}) {
    const auto st = kt::make_scenario("static", T);
    const double still = std::min(30.0, T / 2);
    const auto s0 = st->state(0);
    for (double t = 0; t < still; t += 0.25) {
      const auto s = st->state(t);
      EXPECT_EQ((s.p_WB - s0.p_WB).norm(), 0.0);
      EXPECT_EQ(s.w_B.norm(), 0.0);
    }
    EXPECT_GT((st->state(still + 3).p_WB - s0.p_WB).norm(), 0.3);
  }
}

// Midpoint dead reckoning of the noise-free synthetic IMU reproduces the path.
TEST(SimScenario, IdealImuIntegratesBackOntoTrajectory) {
  const double g = 9.81, rate = 1000.0, dt = 1.0 / rate;
  for (const auto& [name, t_start] : std::vector<std::pair<std::string, double>>{
           {"aggressive", 10.0}, {"figure8", 7.0}, {"hover", 3.0}, {"static", 29.0}}) {
    const auto tr = kt::make_scenario(name, 60);
    kt::ImuSynth imu(kt::ImuModel::bmx055().ideal(), rate, g, 1);
    kt::TrajectoryState s0 = tr->state(t_start);
    Quaterniond q = s0.q_WB;
    Vector3d v = s0.v_WB, p = s0.p_WB;
    const Vector3d g_W(0, 0, -g);
    auto meas = [&](double t) {
      const auto m = imu.sample(tr->state(t), 0);
      return std::make_pair(Vector3d(m.gyro_rps[0], m.gyro_rps[1], m.gyro_rps[2]),
                            Vector3d(m.acc_mps2[0], m.acc_mps2[1], m.acc_mps2[2]));
    };
    auto [w0, a0] = meas(t_start);
    const int steps = static_cast<int>(2.0 * rate);
    for (int k = 0; k < steps; ++k) {
      const double t1 = t_start + (k + 1) * dt;
      const auto [w1, a1] = meas(t1);
      const Quaterniond q1 = (q * kt::so3_exp(0.5 * (w0 + w1) * dt)).normalized();
      const Vector3d acc0 = q * a0 + g_W, acc1 = q1 * a1 + g_W;
      p += v * dt + (2.0 * acc0 + acc1) / 6.0 * dt * dt;
      v += 0.5 * (acc0 + acc1) * dt;
      q = q1;
      w0 = w1;
      a0 = a1;
    }
    const auto s1 = tr->state(t_start + 2.0);
    EXPECT_LT((p - s1.p_WB).norm(), 0.01) << name;
    EXPECT_LT(kt::so3_log(q.conjugate() * s1.q_WB).norm(), 1e-4) << name;
  }
}

TEST(SimSpline, PassesThroughSmoothSamplesWithConsistentDerivatives) {
  const auto truth = kt::make_scenario("figure8", 40);
  for (double jitter : {0.0, 0.01}) {
    const auto samples = sample(*truth, 2.0, 38.0, 20.0, jitter);
    const kt::SplineTrajectory sp = kt::SplineTrajectory::fit(samples);
    EXPECT_LT(sp.max_position_residual_m(), 1e-3) << "jitter " << jitter;
    EXPECT_LT(sp.max_rotation_residual_rad(), 1e-3) << "jitter " << jitter;
    // Between samples too, and its derivatives follow the motion.
    for (double t = 0.5; t < sp.duration_s() - 0.5; t += 0.37) {
      const auto s = sp.state(t);
      const auto ref = truth->state(2.0 + t);
      EXPECT_LT((s.p_WB - ref.p_WB).norm(), 1e-3);
      EXPECT_LT((s.v_WB - ref.v_WB).norm(), 0.01);
      EXPECT_LT((s.a_WB - ref.a_WB).norm(), 0.1);
      EXPECT_LT((s.w_B - ref.w_B).norm(), 0.01);
      expect_consistent(sp, t, 1e-6, 1e-4, 1e-5);
    }
  }
}

TEST(SimSpline, ReadsEurocAndTumFilesAndNamesBadLines) {
  const std::string dir = kestrel::test::temp_dir("sim_spline_files");
  const auto truth = kt::make_scenario("hover", 10);
  const auto samples = sample(*truth, 0.0, 10.0, 30.0);
  {
    std::ofstream e(dir + "/gt.csv"), t(dir + "/gt.txt");
    e << "#timestamp [ns],p_WB_x [m],p_WB_y [m],p_WB_z [m],q_WB_w [],q_WB_x [],q_WB_y [],q_WB_z []\n";
    t << "# timestamp tx ty tz qx qy qz qw\n";
    e.precision(12);
    t.precision(12);
    for (const auto& s : samples) {
      e << s.t_ns << ',' << s.p_WB.x() << ',' << s.p_WB.y() << ',' << s.p_WB.z() << ',' << s.q_WB.w() << ','
        << s.q_WB.x() << ',' << s.q_WB.y() << ',' << s.q_WB.z() << '\n';
      char stamp[32];
      std::snprintf(stamp, sizeof stamp, "%lld.%09lld", static_cast<long long>(s.t_ns / 1'000'000'000),
                    static_cast<long long>(s.t_ns % 1'000'000'000));
      t << stamp << ' ' << s.p_WB.x() << ' ' << s.p_WB.y() << ' ' << s.p_WB.z() << ' ' << s.q_WB.x() << ' '
        << s.q_WB.y() << ' ' << s.q_WB.z() << ' ' << s.q_WB.w() << '\n';
    }
  }
  for (const char* f : {"/gt.csv", "/gt.txt"}) {
    const auto loaded = kt::load_gt_file(dir + f);
    ASSERT_EQ(loaded.size(), samples.size()) << f;
    for (size_t k = 0; k < loaded.size(); ++k) {
      EXPECT_EQ(loaded[k].t_ns, samples[k].t_ns);
      EXPECT_LT((loaded[k].p_WB - samples[k].p_WB).norm(), 1e-9);
      EXPECT_LT(loaded[k].q_WB.angularDistance(samples[k].q_WB), 1e-9);
    }
    // A span of it.
    const auto sp = kt::SplineTrajectory::from_file(dir + f, 2.0, 3.0);
    EXPECT_NEAR(sp.duration_s(), 3.0, 1.0 / 30.0);
    EXPECT_NEAR(1e-9 * (sp.t0_ns() - samples.front().t_ns), 2.0, 1.0 / 30.0);
  }
  EXPECT_THROW(kt::SplineTrajectory::from_file(dir + "/gt.csv", 100.0, 1.0), std::invalid_argument);

  auto expect_error = [&](const std::string& body, const std::string& needle) {
    const std::string path = dir + "/bad.csv";
    std::ofstream(path) << body;
    try {
      kt::load_gt_file(path);
      ADD_FAILURE() << "no error for " << body;
    } catch (const std::runtime_error& e) {
      EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
    }
  };
  const std::string ok = "1000,0,0,1,1,0,0,0\n2000,0,0,1,1,0,0,0\n";
  expect_error("# header\n" + ok + "3000,0,zero,1,1,0,0,0\n", "bad.csv:4");
  expect_error(ok + "3000,0,0,1\n", "bad.csv:3");
  expect_error(ok + "1500,0,0,1,1,0,0,0\n", "does not increase");
  expect_error(ok + "3000,0,0,1,2,0,0,0\n", "quaternion");
  expect_error(ok, "at least 4");
  EXPECT_THROW(kt::load_gt_file(dir + "/missing.csv"), std::runtime_error);
}

// Hybrid mode's premise: the spline through EuRoC's ground truth predicts the
// real gyro up to a constant bias, so frames, units and time all line up.
TEST(SimSpline, EurocSplinePredictsTheRealGyro) {
  KESTREL_REQUIRE_SHARED("euroc/V1_02_medium/gt_body_20hz.csv");
  KESTREL_REQUIRE_SHARED("euroc/V1_02_medium/imu0.csv");
  const auto sp =
      kt::SplineTrajectory::from_file(kestrel::test::shared_path("euroc/V1_02_medium/gt_body_20hz.csv"));
  const auto imu = kt::load_euroc_imu_csv(kestrel::test::shared_path("euroc/V1_02_medium/imu0.csv"));
  std::vector<Vector3d> rg, ra;
  for (const auto& m : imu) {
    const double t = 1e-9 * static_cast<double>(m.t_ns - sp.t0_ns());
    if (t < 1.0 || t > sp.duration_s() - 1.0) continue;
    const auto s = sp.state(t);
    Vector3d w, a;
    kt::true_imu(s, 9.81, w, a);
    rg.push_back(Vector3d(m.gyro_rps[0], m.gyro_rps[1], m.gyro_rps[2]) - w);
    ra.push_back(Vector3d(m.acc_mps2[0], m.acc_mps2[1], m.acc_mps2[2]) - a);
  }
  ASSERT_GT(rg.size(), 10000u);
  Vector3d mg = Vector3d::Zero(), ma = Vector3d::Zero();
  for (size_t k = 0; k < rg.size(); ++k) {
    mg += rg[k];
    ma += ra[k];
  }
  mg /= rg.size();
  ma /= ra.size();
  double eg = 0, ea = 0;
  for (size_t k = 0; k < rg.size(); ++k) {
    eg += (rg[k] - mg).cwiseAbs().mean();
    ea += (ra[k] - ma).cwiseAbs().mean();
  }
  eg /= rg.size();
  ea /= ra.size();
  std::printf(
      "V1_02 spline vs real IMU: gyro bias %.4f %.4f %.4f rad/s, mean |residual| %.4f rad/s; "
      "acc mean |residual| %.3f m/s^2\n",
      mg.x(), mg.y(), mg.z(), eg, ea);
  EXPECT_LT(eg, 0.05);
  // The real bias (gt_official_200hz: about -0.002 0.021 0.076 rad/s) is small.
  EXPECT_LT(mg.norm(), 0.15);
  // Accelerometers carry rotor vibration (0.68 m/s^2 mean |residual| whatever
  // the knot spacing), hence the looser bound.
  EXPECT_LT(ea, 1.0);
}
