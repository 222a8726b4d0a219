// The BMX055 IMU model: noise densities, bias processes, quantisation,
// saturation and determinism.
#include <gtest/gtest.h>

#include <cmath>

#include "kestrel/tools/sim_imu.hpp"

namespace kt = kestrel::tools;
using Eigen::Vector3d;

namespace {

// Still, or spinning about body z at a constant rate with a constant
// horizontal acceleration.
class ConstantTrajectory final : public kt::MotionModel {
 public:
  ConstantTrajectory(double yaw_rate, Vector3d acc) : yaw_rate_(yaw_rate), acc_(std::move(acc)) {}
  double duration_s() const override { return 1e6; }
  int64_t t0_ns() const override { return 0; }
  std::string description() const override { return "constant"; }
  kt::TrajectoryState state(double t) const override {
    kt::TrajectoryState s;
    s.t_s = t;
    s.q_WB = Eigen::Quaterniond(Eigen::AngleAxisd(yaw_rate_ * t, Vector3d::UnitZ()));
    s.w_B = Vector3d(0, 0, yaw_rate_);
    s.a_WB = acc_;
    s.v_WB = acc_ * t;
    s.p_WB = 0.5 * acc_ * t * t;
    return s;
  }

 private:
  double yaw_rate_;
  Vector3d acc_;
};

struct Stats {
  Vector3d mean = Vector3d::Zero(), std = Vector3d::Zero();
};

Stats stats(const std::vector<Vector3d>& v) {
  Stats s;
  for (const auto& x : v) s.mean += x;
  s.mean /= static_cast<double>(v.size());
  for (const auto& x : v) s.std += (x - s.mean).cwiseAbs2();
  s.std = (s.std / static_cast<double>(v.size() - 1)).cwiseSqrt();
  return s;
}

Vector3d gyro(const kestrel::ImuSample& m) { return {m.gyro_rps[0], m.gyro_rps[1], m.gyro_rps[2]}; }
Vector3d acc(const kestrel::ImuSample& m) { return {m.acc_mps2[0], m.acc_mps2[1], m.acc_mps2[2]}; }

}  // namespace

TEST(SimImu, Bmx055NumbersAreTable1InSi) {
  const kt::ImuModel m = kt::ImuModel::bmx055();
  EXPECT_NEAR(m.gyro_noise_density_rad_s_sqrthz, 2.4435e-4, 1e-8);  // 0.014 deg/s/sqrt(Hz)
  EXPECT_NEAR(m.gyro_bias_init_sigma_rps, 1.7453e-3, 1e-7);         // 360 deg/h
  EXPECT_NEAR(m.acc_noise_density_mps2_sqrthz, 1.4710e-3, 1e-7);    // 150 ug/sqrt(Hz)
  EXPECT_NEAR(m.acc_bias_init_sigma_mps2, 3.9227e-2, 1e-6);         // 4 mg
  EXPECT_NEAR(m.gyro_resolution_rps, 6.9813e-5, 1e-9);              // 0.004 deg/s
  EXPECT_NEAR(m.acc_resolution_mps2, 9.6105e-3, 1e-7);              // 0.98 mg
  EXPECT_NEAR(m.acc_bias_tau_s, 300.0, 0.0);
  // Stationary std of the eq. 6 process equals the 4 mg RMS.
  EXPECT_NEAR(m.acc_random_walk_mps3_sqrthz * std::sqrt(m.acc_bias_tau_s / 2), m.acc_bias_init_sigma_mps2,
              1e-12);
  const kestrel::ImuNoise n = m.to_rig();
  EXPECT_EQ(n.gyro_noise_density_rad_s_sqrthz, m.gyro_noise_density_rad_s_sqrthz);
  EXPECT_EQ(n.acc_bias_tau_s, 300.0);
}

TEST(SimImu, StaticWhiteNoiseMatchesDensityTimesSqrtRate) {
  const double rate = 400.0, g = 9.81;
  const kt::ImuModel model = kt::ImuModel::bmx055();
  kt::ImuSynth imu(model, rate, g, 3);
  const ConstantTrajectory still(0.0, Vector3d::Zero());
  std::vector<Vector3d> gs, as;
  Vector3d bg_sum = Vector3d::Zero();
  for (int k = 0; k < 100 * 400; ++k) {
    const auto m = imu.sample(still.state(k / rate), k);
    // The bias processes wander by about as much as the white noise over
    // 100 s (4 mg RMS at tau = 300 s): take the true bias out first.
    gs.push_back(gyro(m) - imu.gyro_bias_rps());
    as.push_back(acc(m) - imu.acc_bias_mps2());
    bg_sum += imu.gyro_bias_rps();
  }
  const Stats sg = stats(gs), sa = stats(as);
  const double expect_g = model.gyro_noise_density_rad_s_sqrthz * std::sqrt(rate);
  const double expect_a = model.acc_noise_density_mps2_sqrthz * std::sqrt(rate);
  for (int i = 0; i < 3; ++i) {
    EXPECT_NEAR(sg.std[i], expect_g, 0.1 * expect_g) << i;
    EXPECT_NEAR(sa.std[i], expect_a, 0.1 * expect_a) << i;
  }
  // Without the bias the mean is zero rate and gravity along +z (the
  // specific force of a body at rest).
  EXPECT_LT(sg.mean.norm(), 1e-4);
  EXPECT_LT((sa.mean - Vector3d(0, 0, g)).norm(), 1e-3);
  EXPECT_GT(bg_sum.norm(), 0.0);
}

TEST(SimImu, AccelerometerBiasIsABoundedRandomWalk) {
  // tau = 1 s so a 2000 s run holds 2000 correlation times.
  kt::ImuModel model = kt::ImuModel::bmx055(1.0);
  model.acc_random_walk_mps3_sqrthz = 0.04 / std::sqrt(0.5);  // stationary std 0.04 m/s^2
  const double rate = 100.0;
  kt::ImuSynth imu(model, rate, 9.81, 11);
  const ConstantTrajectory still(0.0, Vector3d::Zero());
  std::vector<double> b;
  for (int k = 0; k < 200000; ++k) {
    imu.sample(still.state(k / rate), k);
    b.push_back(imu.acc_bias_mps2().x());
  }
  double m = 0, v = 0, c = 0;
  for (double x : b) m += x;
  m /= b.size();
  for (double x : b) v += (x - m) * (x - m);
  v /= b.size();
  const size_t lag = static_cast<size_t>(rate);  // one tau
  for (size_t k = 0; k + lag < b.size(); ++k) c += (b[k] - m) * (b[k + lag] - m);
  c /= (b.size() - lag);
  EXPECT_NEAR(std::sqrt(v), 0.04, 0.004);
  EXPECT_NEAR(c / v, std::exp(-1.0), 0.08);
}

TEST(SimImu, GyroBiasRandomWalkGrowsWithSqrtTime) {
  kt::ImuModel model = kt::ImuModel::bmx055();
  model.gyro_random_walk_rad_s2_sqrthz = 1e-3;
  const double rate = 100.0, T = 4.0;
  const ConstantTrajectory still(0.0, Vector3d::Zero());
  std::vector<Vector3d> d;
  for (uint64_t seed = 1; seed <= 300; ++seed) {
    kt::ImuSynth imu(model, rate, 9.81, seed);
    const Vector3d b0 = imu.gyro_bias_rps();
    for (int k = 0; k <= static_cast<int>(T * rate); ++k) imu.sample(still.state(k / rate), k);
    d.push_back(imu.gyro_bias_rps() - b0);
  }
  const Stats s = stats(d);
  for (int i = 0; i < 3; ++i) EXPECT_NEAR(s.std[i], 1e-3 * std::sqrt(T), 0.15 * 1e-3 * std::sqrt(T));
}

TEST(SimImu, QuantisesAndSaturatesWithFlags) {
  const kt::ImuModel model = kt::ImuModel::bmx055();
  kt::ImuSynth imu(model, 400.0, 9.81, 5);
  const ConstantTrajectory slow(1.0, Vector3d(3, 0, 0));
  for (int k = 0; k < 50; ++k) {
    const auto m = imu.sample(slow.state(k / 400.0), k);
    EXPECT_EQ(m.flags, 0u);
    for (int i = 0; i < 3; ++i) {
      const double qg = m.gyro_rps[i] / model.gyro_resolution_rps,
                   qa = m.acc_mps2[i] / model.acc_resolution_mps2;
      EXPECT_NEAR(qg, std::round(qg), 1e-6);
      EXPECT_NEAR(qa, std::round(qa), 1e-6);
    }
  }
  // 2500 deg/s and 20 g: both clipped at the range and flagged.
  const ConstantTrajectory wild(2500.0 * M_PI / 180.0, Vector3d(20 * 9.81, 0, 0));
  const auto m = imu.sample(wild.state(0.1), 1);
  EXPECT_TRUE(m.flags & kestrel::kImuGyroSaturated);
  EXPECT_TRUE(m.flags & kestrel::kImuAccSaturated);
  EXPECT_NEAR(m.gyro_rps[2], model.gyro_range_rps, model.gyro_resolution_rps);
  EXPECT_LE(std::abs(m.acc_mps2[0]), model.acc_range_mps2 + model.acc_resolution_mps2);
}

TEST(SimImu, IdealModelIsExactAndSeedsAreReproducible) {
  const ConstantTrajectory tr(0.7, Vector3d(1, 2, 0));
  kt::ImuSynth ideal(kt::ImuModel::bmx055().ideal(), 200.0, 9.81, 1);
  const auto s = tr.state(0.3);
  const auto m = ideal.sample(s, 0);
  Vector3d w, a;
  kt::true_imu(s, 9.81, w, a);
  EXPECT_EQ(gyro(m), w);
  EXPECT_EQ(acc(m), a);

  auto run = [&](uint64_t seed) {
    kt::ImuSynth imu(kt::ImuModel::bmx055(), 200.0, 9.81, seed);
    std::vector<double> out;
    for (int k = 0; k < 100; ++k) {
      const auto x = imu.sample(tr.state(k / 200.0), k);
      out.insert(out.end(),
                 {x.gyro_rps[0], x.gyro_rps[1], x.gyro_rps[2], x.acc_mps2[0], x.acc_mps2[1], x.acc_mps2[2]});
    }
    return out;
  };
  EXPECT_EQ(run(42), run(42));
  EXPECT_NE(run(42), run(43));
}

TEST(SimImu, RngIsPortableBoxMuller) {
  // The engine is std::mt19937_64 (fully specified by the standard); the
  // normals are ours, so these values hold on every platform.
  kt::SimRng a(1, kt::RngStream::kImu), b(1, kt::RngStream::kImu), c(1, kt::RngStream::kScene);
  double sum = 0, sum2 = 0;
  for (int i = 0; i < 200000; ++i) {
    const double x = a.normal();
    EXPECT_EQ(x, b.normal());
    sum += x;
    sum2 += x * x;
  }
  EXPECT_NE(a.normal(), c.normal());
  EXPECT_NEAR(sum / 200000, 0.0, 0.01);
  EXPECT_NEAR(sum2 / 200000, 1.0, 0.01);
}
