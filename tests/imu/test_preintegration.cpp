// Preintegration, IMU factor and bias factor: analytic cases, every Jacobian
// against central differences, noise propagation against Monte Carlo, and the
// no-allocation promise.
#include <gtest/gtest.h>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

#include "jacobian_check.hpp"
#include "kestrel/core/preintegration.hpp"
#include "kestrel/core/so3.hpp"
#include "kestrel/rt/alloc_counter.hpp"

namespace kestrel::core {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;
using Eigen::VectorXd;
using kestrel::test::check_jacobian;

// EuRoC's ADIS16448 figures (imu0_sensor.yaml).
ImuNoiseParams euroc_noise(double tau_s = 0.0) {
  ImuNoise n;
  n.gyro_noise_density_rad_s_sqrthz = 1.6968e-4;
  n.gyro_random_walk_rad_s2_sqrthz = 1.9393e-5;
  n.acc_noise_density_mps2_sqrthz = 2.0e-3;
  n.acc_random_walk_mps3_sqrthz = 3.0e-3;
  n.acc_bias_tau_s = tau_s;
  return ImuNoiseParams::from_imu_noise(n, 200.0);
}

PreintegrationParams params(ImuSignalModel m = ImuSignalModel::kZeroOrderHold) {
  PreintegrationParams p;
  p.noise = euroc_noise();
  p.signal = m;
  return p;
}

// A smooth, rotating, accelerating body-frame signal (deterministic).
Vector3d gyro_at(double t) {
  return {0.6 * std::sin(1.3 * t), -0.4 + 0.3 * std::cos(0.7 * t), 0.9 * std::sin(0.5 * t + 1)};
}
Vector3d acc_at(double t) {
  return {1.5 * std::cos(0.9 * t), 0.8 * std::sin(1.7 * t), 9.81 + 0.5 * std::sin(2.1 * t)};
}

void integrate_signal(Preintegrated& pim, double T, double dt, const Vector3d& gyro_offset = Vector3d::Zero(),
                      const Vector3d& acc_offset = Vector3d::Zero()) {
  const int n = static_cast<int>(std::lround(T / dt));
  for (int k = 0; k < n; ++k) {
    const double t = k * dt;
    ASSERT_TRUE(pim.integrate(gyro_at(t) + gyro_offset, acc_at(t) + acc_offset, dt));
  }
}

NavState random_state(std::mt19937& rng) {
  std::normal_distribution<double> N(0.0, 1.0);
  NavState x;
  x.p_WB = Vector3d(N(rng), N(rng), N(rng));
  x.v_WB = Vector3d(N(rng), N(rng), N(rng));
  x.q_WB = Eigen::Quaterniond(so3::Exp(Vector3d(N(rng), N(rng), N(rng)))).normalized();
  x.bg_rps = 0.01 * Vector3d(N(rng), N(rng), N(rng));
  x.ba_mps2 = 0.1 * Vector3d(N(rng), N(rng), N(rng));
  return x;
}

Vector3d v3(const VectorXd& d, int i) { return d.segment<3>(i); }

// ------------------------------------------------------------------ SO(3)

TEST(So3, ExpLogRoundTripIncludingSmallAndNearPi) {
  std::mt19937 rng(7);
  std::normal_distribution<double> N(0.0, 1.0);
  for (double angle : {0.0, 1e-12, 1e-7, 1e-4, 1e-2, 0.5, 2.0, 3.0, M_PI - 1e-4, M_PI - 1e-8}) {
    for (int k = 0; k < 5; ++k) {
      const Vector3d axis = Vector3d(N(rng), N(rng), N(rng)).normalized();
      const Vector3d phi = angle * axis;
      const Matrix3d R = so3::Exp(phi);
      EXPECT_NEAR((R * R.transpose() - Matrix3d::Identity()).norm(), 0.0, 1e-14);
      EXPECT_NEAR(R.determinant(), 1.0, 1e-14);
      const double tol = angle > 3.0 ? 1e-7 : 1e-12;  // near pi the map is ill-conditioned
      EXPECT_LT((so3::Log(R) - phi).norm(), tol) << "angle " << angle;
      EXPECT_LT((Eigen::Matrix3d(so3::exp_quat(phi)) - R).norm(), 1e-12);
    }
  }
}

TEST(So3, RightJacobiansMatchNumericDifferentiation) {
  for (const Vector3d& phi :
       {Vector3d(0.0, 0.0, 0.0), Vector3d(1e-6, -2e-6, 3e-6), Vector3d(3e-3, 1e-3, -2e-3),
        Vector3d(0.3, -0.7, 1.1), Vector3d(2.0, 1.0, -1.5)}) {
    // Exp(phi + d) = Exp(phi) Exp(Jr(phi) d)
    EXPECT_TRUE(check_jacobian(so3::right_jacobian(phi), [&](const VectorXd& d) -> VectorXd {
      return so3::Log(so3::Exp(phi).transpose() * so3::Exp(phi + v3(d, 0)));
    }));
    // Log(Exp(phi) Exp(d)) = phi + Jr^-1(phi) d
    EXPECT_TRUE(check_jacobian(so3::right_jacobian_inv(phi), [&](const VectorXd& d) -> VectorXd {
      return so3::Log(so3::Exp(phi) * so3::Exp(v3(d, 0)));
    }));
    EXPECT_LT((so3::right_jacobian(phi) * so3::right_jacobian_inv(phi) - Matrix3d::Identity()).norm(), 1e-12);
  }
}

// ------------------------------------------------------- analytic motions

TEST(Preintegration, ZeroMotionGivesIdentityDeltas) {
  Preintegrated pim(params());
  for (int k = 0; k < 200; ++k) ASSERT_TRUE(pim.integrate(Vector3d::Zero(), Vector3d::Zero(), 0.005));
  EXPECT_EQ(pim.delta_R(), Matrix3d::Identity());
  EXPECT_EQ(pim.delta_v(), Vector3d::Zero());
  EXPECT_EQ(pim.delta_p(), Vector3d::Zero());
  EXPECT_NEAR(pim.dt_total(), 1.0, 1e-12);
}

TEST(Preintegration, AtRestTheResidualAgainstStillStatesIsZero) {
  // Level and still: the accelerometer reads +g up; states i and j equal.
  Preintegrated pim(params());
  for (int k = 0; k < 200; ++k) ASSERT_TRUE(pim.integrate(Vector3d::Zero(), Vector3d(0, 0, 9.81), 0.005));
  NavState x;
  x.p_WB = Vector3d(1, 2, 3);
  EXPECT_LT(imu_residual(pim, x, x).norm(), 1e-12);
  // A wrong gravity sign is a 2 g dt velocity error.
  NavState falling = x;
  falling.v_WB = Vector3d(0, 0, -2 * 9.81);
  EXPECT_NEAR(imu_residual(pim, x, falling).segment<3>(3).norm(), 2 * 9.81, 1e-9);
}

TEST(Preintegration, ConstantRateIsExact) {
  const Vector3d w(0.3, -1.2, 0.7);
  Preintegrated pim(params());
  for (int k = 0; k < 400; ++k) ASSERT_TRUE(pim.integrate(w, Vector3d::Zero(), 0.0025));
  EXPECT_LT(so3::Log(pim.delta_R().transpose() * so3::Exp(w * 1.0)).norm(), 1e-12);
  EXPECT_LT(pim.delta_v().norm(), 1e-15);
}

TEST(Preintegration, ConstantAccelerationIsExact) {
  const Vector3d a(0.5, -2.0, 11.0);
  Preintegrated pim(params());
  for (int k = 0; k < 400; ++k) ASSERT_TRUE(pim.integrate(Vector3d::Zero(), a, 0.0025));
  EXPECT_LT((pim.delta_v() - a).norm(), 1e-12);
  EXPECT_LT((pim.delta_p() - 0.5 * a).norm(), 1e-12);
}

TEST(Preintegration, ConstantRateAndBodyAccelerationMatchClosedForm) {
  // dv(T) = int_0^T Exp(w t) a dt = T Jr(w T)^T a (left Jacobian); dp by
  // Simpson over that closed form. Euler's error is O(dt): 1 kHz, 1 s.
  const Vector3d w(0.4, -0.9, 1.3), a(1.0, -0.5, 9.0);
  const double T = 1.0, dt = 1e-3;
  Preintegrated pim(params());
  for (int k = 0; k < 1000; ++k) ASSERT_TRUE(pim.integrate(w, a, dt));
  const auto dv_exact = [&](double s) -> Vector3d { return s * so3::right_jacobian(w * s).transpose() * a; };
  Vector3d dp_exact = Vector3d::Zero();
  const int m = 2000;
  for (int k = 0; k <= m; ++k) {
    const double c = (k == 0 || k == m) ? 1.0 : (k % 2 ? 4.0 : 2.0);
    dp_exact += c * dv_exact(T * k / m);
  }
  dp_exact *= T / (3.0 * m);
  EXPECT_LT((pim.delta_v() - dv_exact(T)).norm(), 1e-2);
  EXPECT_LT((pim.delta_p() - dp_exact).norm(), 1e-2);
  // and the error is first order: 4x more steps, ~4x less error
  Preintegrated fine(params());
  for (int k = 0; k < 4000; ++k) ASSERT_TRUE(fine.integrate(w, a, dt / 4));
  const double e1 = (pim.delta_v() - dv_exact(T)).norm(), e4 = (fine.delta_v() - dv_exact(T)).norm();
  EXPECT_GT(e1 / e4, 3.5);
  EXPECT_LT(e1 / e4, 4.5);
}

TEST(Preintegration, RejectsNonFiniteAndNonPositiveSteps) {
  Preintegrated pim(params());
  ASSERT_TRUE(pim.integrate(Vector3d(0.1, 0, 0), Vector3d(0, 0, 9.8), 0.005));
  const Matrix3d R = pim.delta_R();
  const Matrix9d C = pim.covariance();
  EXPECT_FALSE(pim.integrate(Vector3d(NAN, 0, 0), Vector3d(0, 0, 9.8), 0.005));
  EXPECT_FALSE(pim.integrate(Vector3d::Zero(), Vector3d(0, INFINITY, 9.8), 0.005));
  EXPECT_FALSE(pim.integrate(Vector3d::Zero(), Vector3d::Zero(), 0.0));
  EXPECT_FALSE(pim.integrate(Vector3d::Zero(), Vector3d::Zero(), -0.005));
  EXPECT_EQ(pim.rejected(), 4u);
  EXPECT_EQ(pim.steps(), 1);
  EXPECT_EQ(pim.delta_R(), R);
  EXPECT_EQ(pim.covariance(), C);
}

// ---------------------------------------------------------- bias handling

TEST(Preintegration, BiasJacobiansMatchReintegration) {
  const Vector3d bg(0.01, -0.02, 0.005), ba(0.1, 0.05, -0.2);
  Preintegrated pim(params());
  pim.reset(bg, ba);
  integrate_signal(pim, 1.0, 0.005);
  const auto reintegrated = [&](const VectorXd& d) {
    Preintegrated q(params());
    q.reset(bg + v3(d, 0), ba + v3(d, 3));
    integrate_signal(q, 1.0, 0.005);
    VectorXd out(9);
    out << so3::Log(pim.delta_R().transpose() * q.delta_R()), q.delta_v(), q.delta_p();
    return out;
  };
  Eigen::Matrix<double, 9, 6> J = Eigen::Matrix<double, 9, 6>::Zero();
  J.block<3, 3>(0, 0) = pim.dR_dbg();
  J.block<3, 3>(3, 0) = pim.dv_dbg();
  J.block<3, 3>(3, 3) = pim.dv_dba();
  J.block<3, 3>(6, 0) = pim.dp_dbg();
  J.block<3, 3>(6, 3) = pim.dp_dba();
  EXPECT_TRUE(check_jacobian(J, reintegrated, 1e-5, 1e-7, 1e-6));
}

TEST(Preintegration, FirstOrderBiasCorrectionErrorIsSecondOrder) {
  const Vector3d bg(0.01, -0.02, 0.005), ba(0.1, 0.05, -0.2);
  Preintegrated pim(params());
  pim.reset(bg, ba);
  integrate_signal(pim, 1.0, 0.005);
  const Vector3d dbg_dir(0.02, -0.01, 0.015), dba_dir(0.2, 0.3, -0.1);
  double prev_err = 0;
  for (double s : {1.0, 0.1, 0.01}) {
    Preintegrated q(params());
    q.reset(bg + s * dbg_dir, ba + s * dba_dir);
    integrate_signal(q, 1.0, 0.005);
    const PreintegratedDelta d = pim.corrected_delta(bg + s * dbg_dir, ba + s * dba_dir);
    const double err = so3::Log(d.R.transpose() * q.delta_R()).norm() + (d.v - q.delta_v()).norm() +
                       (d.p - q.delta_p()).norm();
    // Versus the uncorrected measurement, the correction must remove almost all of the change.
    const double change = so3::Log(pim.delta_R().transpose() * q.delta_R()).norm() +
                          (pim.delta_v() - q.delta_v()).norm() + (pim.delta_p() - q.delta_p()).norm();
    EXPECT_LT(err, 0.05 * change) << "scale " << s;
    if (prev_err > 0) {
      const double ratio = prev_err / err;  // O(db^2): ~100 per decade
      EXPECT_GT(ratio, 50.0) << "scale " << s;
      EXPECT_LT(ratio, 200.0) << "scale " << s;
    }
    prev_err = err;
  }
}

// ------------------------------------------------------------ covariance

TEST(Preintegration, CovarianceGrowsMonotonically) {
  Preintegrated pim(params());
  double prev_tr[3] = {0, 0, 0};
  double prev_det = 0;
  for (int k = 0; k < 400; ++k) {
    const double t = k * 0.005;
    ASSERT_TRUE(pim.integrate(gyro_at(t), acc_at(t), 0.005));
    const Matrix9d& C = pim.covariance();
    for (int b = 0; b < 3; ++b) {
      const double tr = C.block<3, 3>(3 * b, 3 * b).trace();
      EXPECT_GT(tr, prev_tr[b]) << "block " << b << " step " << k;
      prev_tr[b] = tr;
    }
    // One step adds rank 6 (v and p share the accelerometer noise); from the
    // second on the covariance is full rank and its volume only grows.
    if (k >= 1) {
      const double det = C.determinant();
      EXPECT_GT(det, prev_det) << "step " << k;
      prev_det = det;
      EXPECT_GT(Eigen::SelfAdjointEigenSolver<Matrix9d>(C).eigenvalues().minCoeff(), 0.0) << "step " << k;
    }
  }
  // Pure rotation-noise scale: after 2 s the angle variance is s_g^2 T per axis.
  const double ng = params().noise.gyro_noise_density_rad_s_sqrthz;
  const double var_2s = ng * ng * 2.0;
  const double var_rot = pim.covariance().block<3, 3>(0, 0).trace() / 3.0;
  EXPECT_NEAR(var_rot, var_2s, 0.05 * var_2s);
}

TEST(Preintegration, CovarianceMatchesMonteCarlo) {
  // Noisy samples drawn with the discrete variances the integrator assumes;
  // the spread of the residual against the noiseless measurement must match
  // the propagated covariance (a factor 10 in the noise fails by far).
  const PreintegrationParams p = params();
  const double dt = 0.005;
  const int n = 100;  // 0.5 s
  Preintegrated clean(p);
  integrate_signal(clean, n * dt, dt);
  std::mt19937 rng(42);
  std::normal_distribution<double> N(0.0, 1.0);
  const double sg = p.noise.gyro_noise_density_rad_s_sqrthz / std::sqrt(dt);
  const double sa = p.noise.acc_noise_density_mps2_sqrthz / std::sqrt(dt);
  const int runs = 2000;
  Matrix9d S = Matrix9d::Zero();
  double nees = 0;
  const Matrix9d W = clean.sqrt_information();
  for (int r = 0; r < runs; ++r) {
    Preintegrated noisy(p);
    for (int k = 0; k < n; ++k) {
      const double t = k * dt;
      noisy.integrate(gyro_at(t) + sg * Vector3d(N(rng), N(rng), N(rng)),
                      acc_at(t) + sa * Vector3d(N(rng), N(rng), N(rng)), dt);
    }
    // Measurement error as Forster defines it: dR~ = dR Exp(dphi), dv~ = dv + ddv, ...
    Vector9d e;
    e << so3::Log(clean.delta_R().transpose() * noisy.delta_R()), noisy.delta_v() - clean.delta_v(),
        noisy.delta_p() - clean.delta_p();
    S += e * e.transpose();
    nees += (W * e).squaredNorm();
  }
  S /= runs;
  nees /= runs;
  EXPECT_NEAR(nees, 9.0, 0.5);  // chi^2(9) mean; sd of the mean of 2000 is ~0.1
  for (int b = 0; b < 3; ++b) {
    const double mc = S.block<3, 3>(3 * b, 3 * b).trace(),
                 pr = clean.covariance().block<3, 3>(3 * b, 3 * b).trace();
    EXPECT_NEAR(mc / pr, 1.0, 0.1) << "block " << b;
  }
}

// ------------------------------------------------- residual and Jacobians

struct FactorCase {
  Preintegrated pim;
  NavState xi, xj;
};

FactorCase make_case(unsigned seed) {
  std::mt19937 rng(seed);
  FactorCase c{Preintegrated(params()), random_state(rng), NavState{}};
  c.pim.reset(c.xi.bg_rps + Vector3d(0.003, -0.002, 0.001), c.xi.ba_mps2 + Vector3d(-0.02, 0.03, 0.01));
  integrate_signal(c.pim, 0.7, 0.005);
  // x_j near but not at the prediction: a non-zero residual exercises Jr^-1.
  c.xj = predict(c.xi, c.pim);
  std::normal_distribution<double> N(0.0, 0.2);
  c.xj.q_WB = c.xj.q_WB * Eigen::Quaterniond(so3::Exp(Vector3d(N(rng), N(rng), N(rng))));
  c.xj.p_WB += Vector3d(N(rng), N(rng), N(rng));
  c.xj.v_WB += Vector3d(N(rng), N(rng), N(rng));
  return c;
}

enum class Block { kPhiI, kPI, kVI, kBgI, kBaI, kPhiJ, kPJ, kVJ };

void perturb(NavState& xi, NavState& xj, Block b, const Vector3d& d) {
  const Eigen::Quaterniond dq(so3::Exp(d));
  switch (b) {
    case Block::kPhiI:
      xi.q_WB = xi.q_WB * dq;
      break;
    case Block::kPI:
      xi.p_WB += d;
      break;
    case Block::kVI:
      xi.v_WB += d;
      break;
    case Block::kBgI:
      xi.bg_rps += d;
      break;
    case Block::kBaI:
      xi.ba_mps2 += d;
      break;
    case Block::kPhiJ:
      xj.q_WB = xj.q_WB * dq;
      break;
    case Block::kPJ:
      xj.p_WB += d;
      break;
    case Block::kVJ:
      xj.v_WB += d;
      break;
  }
}

TEST(ImuFactor, EveryJacobianBlockMatchesNumericDifferentiation) {
  for (unsigned seed : {1u, 2u, 3u}) {
    const FactorCase c = make_case(seed);
    ImuFactorJacobians J;
    const Vector9d r0 = imu_residual(c.pim, c.xi, c.xj, &J);
    ASSERT_GT(r0.segment<3>(0).norm(), 0.05);  // far enough from zero to test Jr^-1
    const std::pair<Block, const Matrix93d*> blocks[] = {
        {Block::kPhiI, &J.phi_i}, {Block::kPI, &J.p_i},     {Block::kVI, &J.v_i}, {Block::kBgI, &J.bg_i},
        {Block::kBaI, &J.ba_i},   {Block::kPhiJ, &J.phi_j}, {Block::kPJ, &J.p_j}, {Block::kVJ, &J.v_j}};
    for (const auto& entry : blocks) {
      // Not a structured binding: C++17 (and clang 14, the sanitizer build's
      // compiler) cannot capture one in a lambda.
      const Block block = entry.first;
      const Matrix93d* Jb = entry.second;
      EXPECT_TRUE(check_jacobian(*Jb,
                                 [&](const VectorXd& d) -> VectorXd {
                                   NavState xi = c.xi, xj = c.xj;
                                   perturb(xi, xj, block, v3(d, 0));
                                   return imu_residual(c.pim, xi, xj);
                                 }))
          << "seed " << seed << " block " << static_cast<int>(block);
    }
  }
}

TEST(ImuFactor, PredictGivesZeroResidual) {
  for (unsigned seed : {4u, 5u}) {
    const FactorCase c = make_case(seed);
    const NavState xj = predict(c.xi, c.pim);
    EXPECT_LT(imu_residual(c.pim, c.xi, xj).norm(), 1e-9);
    EXPECT_EQ(xj.t_ns, c.xi.t_ns + 700'000'000);
    EXPECT_LT(bias_residual(c.xi, xj, c.pim.dt_total(), c.pim.params().noise).norm(), 1e-15);
  }
  // With the bounded random walk the accelerometer bias decays toward zero.
  PreintegrationParams p = params();
  p.noise.acc_bias_tau_s = 2.0;
  Preintegrated pim(p);
  integrate_signal(pim, 0.5, 0.005);
  NavState xi;
  xi.ba_mps2 = Vector3d(0.1, -0.2, 0.3);
  const NavState xj = predict(xi, pim);
  EXPECT_LT((xj.ba_mps2 - std::exp(-0.25) * xi.ba_mps2).norm(), 1e-15);
  EXPECT_LT(bias_residual(xi, xj, pim.dt_total(), p.noise).norm(), 1e-15);
}

TEST(ImuFactor, WhitenedResidualUsesTheCovariance) {
  const FactorCase c = make_case(9);
  const Vector9d r = imu_residual(c.pim, c.xi, c.xj);
  const double direct = r.dot(c.pim.covariance().ldlt().solve(r));
  EXPECT_NEAR((c.pim.sqrt_information() * r).squaredNorm() / direct, 1.0, 1e-6);
}

TEST(BiasFactor, JacobiansMatchNumericDifferentiation) {
  for (double tau : {0.0, 3.0}) {
    std::mt19937 rng(11);
    const NavState xi = random_state(rng), xj = random_state(rng);
    const ImuNoiseParams noise = euroc_noise(tau);
    BiasFactorJacobians J;
    bias_residual(xi, xj, 0.4, noise, &J);
    const std::pair<int, const Matrix63d*> blocks[] = {
        {0, &J.bg_i}, {1, &J.ba_i}, {2, &J.bg_j}, {3, &J.ba_j}};
    for (const auto& entry : blocks) {
      const int which = entry.first;  // captured below: see the Jacobian test above
      const Matrix63d* Jb = entry.second;
      EXPECT_TRUE(check_jacobian(*Jb,
                                 [&](const VectorXd& d) -> VectorXd {
                                   NavState a = xi, b = xj;
                                   if (which == 0) a.bg_rps += v3(d, 0);
                                   if (which == 1) a.ba_mps2 += v3(d, 0);
                                   if (which == 2) b.bg_rps += v3(d, 0);
                                   if (which == 3) b.ba_mps2 += v3(d, 0);
                                   return bias_residual(a, b, 0.4, noise);
                                 }))
          << "tau " << tau << " block " << which;
    }
  }
}

TEST(BiasFactor, CovarianceIsTheDiscreteOrnsteinUhlenbeckVariance) {
  const ImuNoiseParams rw = euroc_noise(0.0);
  const double dt = 0.3;
  const Matrix6d C = bias_covariance(dt, rw);
  EXPECT_DOUBLE_EQ(C(0, 0), 1.9393e-5 * 1.9393e-5 * dt);
  EXPECT_DOUBLE_EQ(C(3, 3), 3.0e-3 * 3.0e-3 * dt);
  // tau >> dt tends to the random walk; tau << dt to the stationary variance s^2 tau / 2.
  EXPECT_NEAR(bias_covariance(dt, euroc_noise(1e6))(3, 3) / C(3, 3), 1.0, 1e-5);
  EXPECT_NEAR(bias_covariance(dt, euroc_noise(0.01))(3, 3), 9e-6 * 0.005, 1e-15);
  // Monte Carlo of the OU SDE with fine Euler-Maruyama steps, tau = 0.5 s.
  const double tau = 0.5, s = 3.0e-3, h = 1e-3;
  std::mt19937 rng(3);
  std::normal_distribution<double> N(0.0, 1.0);
  double sum2 = 0;
  const int runs = 4000;
  for (int r = 0; r < runs; ++r) {
    double b = 0.0;
    for (int k = 0; k < static_cast<int>(dt / h); ++k) b += -b / tau * h + s * std::sqrt(h) * N(rng);
    sum2 += b * b;
  }
  EXPECT_NEAR(sum2 / runs / bias_covariance(dt, euroc_noise(tau))(3, 3), 1.0, 0.08);
}

// ------------------------------------------------- splitting at keyframes

std::vector<ImuSample> make_samples(int64_t t0_ns, int64_t step_ns, int n) {
  std::vector<ImuSample> v(n);
  for (int k = 0; k < n; ++k) {
    const int64_t t = t0_ns + k * step_ns;
    const double ts = 1e-9 * static_cast<double>(t - t0_ns);
    v[k].t_ns = t;
    const Vector3d g = gyro_at(ts), a = acc_at(ts);
    v[k].gyro_rps = {g.x(), g.y(), g.z()};
    v[k].acc_mps2 = {a.x(), a.y(), a.z()};
  }
  return v;
}

// Forster eq. 33-35 composed over two consecutive intervals.
PreintegratedDelta compose(const Preintegrated& a, const Preintegrated& b) {
  PreintegratedDelta d;
  d.R = a.delta_R() * b.delta_R();
  d.v = a.delta_v() + a.delta_R() * b.delta_v();
  d.p = a.delta_p() + a.delta_v() * b.dt_total() + a.delta_R() * b.delta_p();
  return d;
}

TEST(PreintegrateWindow, SplittingAtAKeyframeBetweenSamplesIsExact) {
  for (ImuSignalModel m : {ImuSignalModel::kZeroOrderHold, ImuSignalModel::kLinear}) {
    const auto samples = make_samples(1'000'000'000, 5'000'000, 300);
    const int64_t t_i = 1'012'345'678, t_m = 1'503'210'987, t_j = 2'107'654'321;  // none on a sample
    Preintegrated first(params(m)), second(params(m));
    const WindowReport r = preintegrate_window(first, samples, t_i, t_m, Vector3d::Zero(), Vector3d::Zero());
    preintegrate_window(second, samples, t_m, t_j, Vector3d::Zero(), Vector3d::Zero());
    EXPECT_EQ(r.extrapolated_ns, 0);
    EXPECT_EQ(r.skipped_unusable, 0);
    EXPECT_EQ(first.t_start_ns(), t_i);
    EXPECT_EQ(first.t_end_ns(), t_m);
    EXPECT_EQ(second.t_end_ns(), t_j);
    EXPECT_NEAR(first.dt_total() + second.dt_total(), 1e-9 * static_cast<double>(t_j - t_i), 1e-12);
    // The same pieces fed by hand into one preintegration: the two keyframe
    // intervals compose to it exactly (Forster eq. 33-35), so nothing is lost
    // or counted twice at t_m.
    Preintegrated by_hand(params(m));
    by_hand.reset(Vector3d::Zero(), Vector3d::Zero(), t_i);
    for (std::size_t k = 0; k + 1 < samples.size(); ++k) {
      const ImuSample &a = samples[k], &b = samples[k + 1];
      const int64_t lo = std::max(a.t_ns, t_i), hi = std::min(b.t_ns, t_j);
      if (lo < t_m && t_m < hi) {
        ASSERT_TRUE(by_hand.integrate_segment(a, b, lo, t_m));
        ASSERT_TRUE(by_hand.integrate_segment(a, b, t_m, hi));
      } else if (hi > lo) {
        ASSERT_TRUE(by_hand.integrate_segment(a, b, lo, hi));
      }
    }
    const PreintegratedDelta d = compose(first, second);
    EXPECT_LT(so3::Log(d.R.transpose() * by_hand.delta_R()).norm(), 1e-12);
    EXPECT_LT((d.v - by_hand.delta_v()).norm(), 1e-12);
    EXPECT_LT((d.p - by_hand.delta_p()).norm(), 1e-12);
    // and the unsplit window differs from it only by the discretisation.
    Preintegrated whole(params(m));
    preintegrate_window(whole, samples, t_i, t_j, Vector3d::Zero(), Vector3d::Zero());
    EXPECT_LT((d.v - whole.delta_v()).norm(), 1e-4);
  }
}

TEST(PreintegrateWindow, LinearModelBeatsZeroOrderHoldOnASmoothSignal) {
  // Reference: the continuous signal at 0.1 ms steps.
  const int64_t t_i = 1'000'000'000, t_j = 2'000'000'000;
  Preintegrated ref(params());
  for (int k = 0; k < 10000; ++k) {
    const double t = (k + 0.5) * 1e-4;
    ref.integrate(gyro_at(t), acc_at(t), 1e-4);
  }
  const auto samples = make_samples(t_i, 5'000'000, 201);
  double err[2];
  for (int mi = 0; mi < 2; ++mi) {
    Preintegrated pim(params(mi == 0 ? ImuSignalModel::kZeroOrderHold : ImuSignalModel::kLinear));
    preintegrate_window(pim, samples, t_i, t_j, Vector3d::Zero(), Vector3d::Zero());
    err[mi] = so3::Log(ref.delta_R().transpose() * pim.delta_R()).norm();
  }
  // The hold lags the signal by half a sample (first order); the linear
  // model's mean is the trapezoid (second order). Velocity is not compared:
  // there the Euler step's own first-order term dominates both.
  EXPECT_LT(err[1], 0.05 * err[0]) << "zoh " << err[0] << " linear " << err[1];
}

TEST(PreintegrateWindow, BridgesBadSamplesAndReportsExtrapolation) {
  auto samples = make_samples(1'000'000'000, 5'000'000, 50);
  samples[10].acc_mps2[1] = NAN;
  samples[20].flags = kImuGyroSaturated;
  Preintegrated pim(params());
  // Starts before the first sample and ends after the last.
  const WindowReport r =
      preintegrate_window(pim, samples, 990'000'000, 1'260'000'000, Vector3d::Zero(), Vector3d::Zero());
  EXPECT_EQ(r.skipped_unusable, 2);
  EXPECT_EQ(r.extrapolated_ns, 10'000'000 + 15'000'000);
  EXPECT_NEAR(pim.dt_total(), 0.27, 1e-12);
  EXPECT_TRUE(pim.delta_v().allFinite());
  EXPECT_EQ(pim.rejected(), 0u);
  // Nothing to integrate: empty input, empty window.
  Preintegrated empty(params());
  EXPECT_FALSE(
      preintegrate_window(empty, std::vector<ImuSample>{}, 0, 1000, Vector3d::Zero(), Vector3d::Zero()).ok());
  EXPECT_FALSE(
      preintegrate_window(empty, samples, 1'100'000'000, 1'100'000'000, Vector3d::Zero(), Vector3d::Zero())
          .ok());
}

// ------------------------------------------------------------ real time

TEST(Preintegration, NothingAllocatesPerSampleOrPerFactor) {
  ASSERT_TRUE(rt::alloc_hook_linked());
  const auto samples = make_samples(1'000'000'000, 5'000'000, 400);
  Preintegrated pim(params(ImuSignalModel::kLinear));
  NavState xi;
  ImuFactorJacobians J;
  BiasFactorJacobians Jb;
  double sink = 0;
  rt::AllocCountScope scope;
  for (int k = 0; k < 399; ++k)
    pim.integrate_segment(samples[k], samples[k + 1], samples[k].t_ns, samples[k + 1].t_ns);
  pim.integrate(Vector3d(0.1, 0.2, 0.3), Vector3d(0, 0, 9.8), 0.005);
  preintegrate_window(pim, samples, 1'002'000'000, 2'001'000'000, Vector3d::Zero(), Vector3d::Zero());
  const NavState xj = predict(xi, pim);
  sink += imu_residual(pim, xi, xj, &J).norm();
  sink += bias_residual(xi, xj, pim.dt_total(), pim.params().noise, &Jb).norm();
  sink += bias_covariance(pim.dt_total(), pim.params().noise).trace();
  sink += pim.sqrt_information().trace();
  sink += pim.corrected_delta(Vector3d(0.01, 0, 0), Vector3d::Zero()).p.norm();
  EXPECT_EQ(scope.count(), 0u);
  EXPECT_TRUE(std::isfinite(sink));
}

TEST(ImuNoiseParams, DiscreteVariancesFromDensitiesAndRate) {
  const ImuNoiseParams p = euroc_noise();
  EXPECT_TRUE(p.valid());
  EXPECT_DOUBLE_EQ(p.gyro_var_d, 1.6968e-4 * 1.6968e-4 * 200.0);
  EXPECT_DOUBLE_EQ(p.acc_var_d, 2.0e-3 * 2.0e-3 * 200.0);
  EXPECT_DOUBLE_EQ(p.gyro_bias_var_d, 1.9393e-5 * 1.9393e-5 / 200.0);
  EXPECT_DOUBLE_EQ(p.acc_bias_var_d, 3.0e-3 * 3.0e-3 / 200.0);
  EXPECT_DOUBLE_EQ(p.scaled(10.0).acc_var_d, 100.0 * p.acc_var_d);
  Rig rig;
  rig.imu.gyro_noise_density_rad_s_sqrthz = 1.6968e-4;
  rig.imu_rate_hz = 200;
  rig.gravity_mps2 = 9.80665;
  EXPECT_FALSE(ImuNoiseParams::from_rig(rig).valid());  // other densities missing
  EXPECT_DOUBLE_EQ(PreintegrationParams::from_rig(rig).gravity_W().z(), -9.80665);
}

}  // namespace
}  // namespace kestrel::core
