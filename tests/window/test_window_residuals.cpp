// Every analytic Jacobian of the window's residuals against central
// differences through the same perturbation (tests/common/jacobian_check.hpp).
#include <gtest/gtest.h>

#include <algorithm>
#include <random>

#include "jacobian_check.hpp"
#include "kestrel/core/so3.hpp"
#include "kestrel/core/window_problem.hpp"
#include "window_sim.hpp"

namespace kestrel::core {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;
using Eigen::VectorXd;
using kestrel::test::check_jacobian;

Vector15d to15(const VectorXd& d) { return Vector15d(d.head<15>()); }

WindowProblem make_problem(bool bounded = false) {
  WindowProblem P;
  P.opt = kestrel::test::sim_options();
  P.opt.huber_px = 2.0;
  P.bias_noise = P.opt.imu;
  P.bias_noise.acc_bias_tau_s = bounded ? 300.0 : 0.0;
  P.K = kestrel::test::sim_K();
  const Eigen::Isometry3d T_BC = kestrel::test::sim_T_BC();
  P.R_CB = T_BC.linear().transpose();
  P.p_CB = -P.R_CB * T_BC.translation();
  return P;
}

NavState some_state(std::mt19937_64& rng) {
  std::normal_distribution<double> N(0.0, 1.0);
  NavState x;
  x.p_WB = Vector3d(N(rng), N(rng), N(rng));
  x.q_WB = Eigen::Quaterniond(so3::Exp(0.8 * Vector3d(N(rng), N(rng), N(rng))));
  x.v_WB = Vector3d(N(rng), N(rng), N(rng));
  x.bg_rps = 0.01 * Vector3d(N(rng), N(rng), N(rng));
  x.ba_mps2 = 0.1 * Vector3d(N(rng), N(rng), N(rng));
  return x;
}

TEST(WindowResiduals, VisualJacobiansWithAndWithoutDepthAndTimeOffset) {
  WindowProblem P = make_problem();
  P.opt.estimate_time_offset = true;
  std::mt19937_64 rng(3);
  for (int depth = 0; depth < 2; ++depth) {
    for (int trial = 0; trial < 5; ++trial) {
      NavState x = some_state(rng);
      // A landmark 3 m in front of the camera.
      const Matrix3d R = x.q_WB.toRotationMatrix();
      const Vector3d p_C(0.3 * trial - 0.5, 0.2, 3.0);
      const Vector3d l = R * (P.R_CB.transpose() * (p_C - P.p_CB)) + x.p_WB;
      WindowObs o;
      o.uv = Eigen::Vector2d(300.0, 250.0);
      o.sigma_px = 0.7;
      o.depth_m = depth ? 2.9 : 0.0;
      o.sigma_depth_m = 0.02;
      o.uv_vel_pxps = Eigen::Vector2d(120.0 - 60.0 * trial, 35.0 * trial);  // image motion [px/s]
      o.depth_vel_mps = 0.4 - 0.2 * trial;                                  // approaching, then receding
      const double td_s = 0.004 * trial - 0.01;
      Vector3d r, Jt;
      Matrix36d Jp;
      Matrix3d Jl;
      const int rows = visual_residual(P, x, l, o, td_s, &r, &Jp, &Jl, &Jt);
      ASSERT_EQ(rows, depth ? 3 : 2);
      EXPECT_TRUE(check_jacobian(Jp.topRows(rows), [&](const VectorXd& d) {
        Vector15d d15 = Vector15d::Zero();
        d15.head<6>() = d;
        Vector3d rr;
        visual_residual(P, state_plus(x, d15), l, o, td_s, &rr);
        return VectorXd(rr.head(rows));
      }));
      EXPECT_TRUE(check_jacobian(Jl.topRows(rows), [&](const VectorXd& d) {
        Vector3d rr;
        visual_residual(P, x, l + d.head<3>(), o, td_s, &rr);
        return VectorXd(rr.head(rows));
      }));
      EXPECT_TRUE(check_jacobian(Jt.head(rows), [&](const VectorXd& d) {
        Vector3d rr;
        visual_residual(P, x, l, o, td_s + d(0), &rr);
        return VectorXd(rr.head(rows));
      }));
      // The offset moves the pixel back along its image velocity: a point seen
      // at uv while moving at uv_vel was at uv - uv_vel td at the state's time.
      Vector3d r0;
      visual_residual(P, x, l, o, 0.0, &r0);
      EXPECT_NEAR(r(0) - r0(0), o.uv_vel_pxps.x() * td_s / o.sigma_px, 1e-9);
      EXPECT_NEAR(r(1) - r0(1), o.uv_vel_pxps.y() * td_s / o.sigma_px, 1e-9);
      // The depth likewise along its rate.
      if (depth) {
        EXPECT_NEAR(r(2) - r0(2), o.depth_vel_mps * td_s / o.sigma_depth_m, 1e-9);
      }
    }
  }
  double J = 0.0;
  const double r = time_offset_prior_residual(P, 0.003, &J);
  EXPECT_TRUE(check_jacobian(Eigen::Matrix<double, 1, 1>::Constant(J), [&](const VectorXd& d) {
    return VectorXd::Constant(1, time_offset_prior_residual(P, 0.003 + d(0)));
  }));
  EXPECT_NEAR(r, 0.003 / (1e-3 * P.opt.time_offset_prior_sigma_ms), 1e-12);
  // With a measurement of t_d (the rotation correlation) the prior is centred on it.
  P.td_meas_s = -0.02;
  P.td_meas_sigma_s = 0.0005;
  EXPECT_NEAR(time_offset_prior_residual(P, -0.019, &J), 0.001 / 0.0005, 1e-9);
  EXPECT_NEAR(J, 1.0 / 0.0005, 1e-9);
}

TEST(WindowResiduals, BehindTheCameraHasNoRows) {
  const WindowProblem P = make_problem();
  NavState x;
  WindowObs o;
  Vector3d r;
  // Camera looks along body x: a point behind the body is behind the camera.
  EXPECT_EQ(visual_residual(P, x, Vector3d(-3, 0, 0), o, 0.0, &r), 0);
}

// The IMU factor between the first two frames of a simulated flight, at four
// pairs of states perturbed from the truth: f(P, sj, xi, xj, Ji, Jj).
template <class F>
void for_each_imu_factor(bool bounded, uint64_t seed, F f) {
  const WindowProblem P = make_problem(bounded);
  std::mt19937_64 rng(seed);
  kestrel::test::SimConfig c;
  kestrel::test::SimWorld world(c);
  const std::vector<kestrel::test::SimFrame> frames = world.frames(2, 1.0);
  WindowState sj;
  sj.pim = frames[1].pim;
  sj.imu_sqrt_info = sj.pim.sqrt_information();
  const Matrix6d C = bias_covariance(sj.pim.dt_total(), P.bias_noise);
  for (int i = 0; i < 6; ++i) sj.bias_sqrt_info(i) = 1.0 / std::sqrt(C(i, i));
  for (int trial = 0; trial < 4; ++trial) {
    const NavState xi = kestrel::test::perturb(frames[0].truth, rng, 0.1, 0.1);
    const NavState xj = kestrel::test::perturb(frames[1].truth, rng, 0.1, 0.1);
    Matrix15d Ji, Jj;
    imu_bias_residual(P, sj, xi, xj, &Ji, &Jj);
    f(P, sj, xi, xj, Ji, Jj);
  }
}

void check_imu(bool bounded) {
  for_each_imu_factor(bounded, bounded ? 7 : 5,
                      [](const WindowProblem& P, const WindowState& sj, const NavState& xi,
                         const NavState& xj, const Matrix15d& Ji, const Matrix15d& Jj) {
                        // Whitened residuals are large (1e3-1e5 per unit): relative tolerance on the worst
                        // entry.
                        EXPECT_TRUE(check_jacobian(
                            Ji,
                            [&](const VectorXd& d) {
                              return VectorXd(imu_bias_residual(P, sj, state_plus(xi, to15(d)), xj));
                            },
                            1e-5, 1e-6, 1e-7));
                        EXPECT_TRUE(check_jacobian(
                            Jj,
                            [&](const VectorXd& d) {
                              return VectorXd(imu_bias_residual(P, sj, xi, state_plus(xj, to15(d))));
                            },
                            1e-5, 1e-6, 1e-7));
                      });
}

TEST(WindowResiduals, ImuAndBiasJacobiansRandomWalk) { check_imu(false); }
TEST(WindowResiduals, ImuAndBiasJacobiansBoundedRandomWalk) { check_imu(true); }

TEST(WindowResiduals, GaugeJacobian) {
  WindowProblem P = make_problem();
  P.opt.gauge_sigma = 1e-2;
  std::mt19937_64 rng(11);
  for (int trial = 0; trial < 6; ++trial) {
    const NavState x = some_state(rng);
    P.gauge_p = x.p_WB + Vector3d(0.01, -0.02, 0.03);
    P.gauge_yaw = yaw_of(x.q_WB) + 0.05;
    Eigen::Matrix<double, 4, 6> J;
    gauge_residual(P, x, &J);
    EXPECT_TRUE(check_jacobian(J, [&](const VectorXd& d) {
      Vector15d d15 = Vector15d::Zero();
      d15.head<6>() = d;
      return VectorXd(gauge_residual(P, state_plus(x, d15)));
    }));
  }
}

// A state carrying a map pose factor a little off its estimate.
WindowState with_map_pose_factor(const NavState& x) {
  WindowState st;
  st.prior_p_WB = x.p_WB + Vector3d(0.02, -0.01, 0.03);
  st.prior_q_WB = Eigen::Quaterniond(x.q_WB.toRotationMatrix() * so3::Exp(Vector3d(0.05, -0.04, 0.1)));
  st.prior_sigma_p_m = 0.02;
  st.prior_sigma_rad = 0.01;
  return st;
}

// The two priors whose analytic Jacobians the Ceres twin reused, so the
// cross-check could not catch an error in them (issue 45): numerically here.
TEST(WindowResiduals, PosePriorJacobian) {
  std::mt19937_64 rng(17);
  for (int trial = 0; trial < 6; ++trial) {
    const NavState x = some_state(rng);
    const WindowState st = with_map_pose_factor(x);
    Matrix6d J;
    pose_prior_residual(st, x, &J);
    EXPECT_TRUE(check_jacobian(J, [&](const VectorXd& d) {
      Vector15d d15 = Vector15d::Zero();
      d15.head<6>() = d;
      return VectorXd(pose_prior_residual(st, state_plus(x, d15)));
    }));
  }
}

TEST(WindowResiduals, GaugeRotationJacobian) {
  WindowProblem P = make_problem();
  P.opt.gauge_sigma = 1e-2;
  std::mt19937_64 rng(19);
  for (int trial = 0; trial < 6; ++trial) {
    const NavState x = some_state(rng);
    P.gauge_q = Eigen::Quaterniond(x.q_WB.toRotationMatrix() * so3::Exp(Vector3d(-0.03, 0.08, 0.02)));
    Eigen::Matrix<double, 3, 6> J;
    gauge_rotation_residual(P, x, &J);
    EXPECT_TRUE(check_jacobian(J, [&](const VectorXd& d) {
      Vector15d d15 = Vector15d::Zero();
      d15.head<6>() = d;
      return VectorXd(gauge_rotation_residual(P, state_plus(x, d15)));
    }));
  }
}

// The null spaces: a factor must not see the directions the problem cannot
// observe, or the solver gains false information along them (and the window's
// gauge drifts or locks where it should not). A global rigid motion of the
// world (translation dt, rotation w about W's axes) moves a state's tangent by
//   dp = dt + w x p,  dphi = R^T w,  dv = w x v,  biases unchanged,
// and a landmark by dl = dt + w x l. Vision cannot see any of the six; the IMU
// factor, which sees gravity along W's z, cannot see translation and yaw.
Eigen::Matrix<double, 15, 6> global_motion(const NavState& x) {
  Eigen::Matrix<double, 15, 6> N = Eigen::Matrix<double, 15, 6>::Zero();
  N.block<3, 3>(0, 0).setIdentity();
  N.block<3, 3>(0, 3) = -so3::hat(x.p_WB);
  N.block<3, 3>(3, 3) = x.q_WB.toRotationMatrix().transpose();
  N.block<3, 3>(6, 3) = -so3::hat(x.v_WB);
  return N;
}

// Largest entry of J N against the scale of J and N, so that the check is
// relative to how strongly the factor sees anything.
template <class A, class B>
double relative_leak(const A& JN, const B& J, double n_scale) {
  return JN.cwiseAbs().maxCoeff() / (J.cwiseAbs().maxCoeff() * n_scale);
}

TEST(WindowResiduals, VisualFactorDoesNotSeeAGlobalRigidMotion) {
  const WindowProblem P = make_problem();
  std::mt19937_64 rng(23);
  for (int depth = 0; depth < 2; ++depth) {
    for (int trial = 0; trial < 5; ++trial) {
      const NavState x = some_state(rng);
      const Vector3d p_C(0.2 * trial - 0.4, -0.1, 2.5);
      const Vector3d l = x.q_WB.toRotationMatrix() * (P.R_CB.transpose() * (p_C - P.p_CB)) + x.p_WB;
      WindowObs o;
      o.uv = Eigen::Vector2d(310.0, 240.0);
      o.sigma_px = 0.7;
      o.depth_m = depth ? 2.4 : 0.0;
      o.sigma_depth_m = 0.02;
      Vector3d r;
      Matrix36d Jp;
      Matrix3d Jl;
      const int rows = visual_residual(P, x, l, o, 0.0, &r, &Jp, &Jl);
      ASSERT_EQ(rows, depth ? 3 : 2);
      const Eigen::Matrix<double, 15, 6> N = global_motion(x);
      Eigen::Matrix<double, 3, 6> Nl;
      Nl << Matrix3d::Identity(), -so3::hat(l);
      const Eigen::MatrixXd JN = Jp.topRows(rows) * N.topRows<6>() + Jl.topRows(rows) * Nl;
      const double n_scale = std::max({1.0, x.p_WB.norm(), l.norm()});
      EXPECT_LT(relative_leak(JN, Jp.topRows(rows), n_scale), 1e-12) << "depth " << depth << "\n" << JN;
    }
  }
}

TEST(WindowResiduals, ImuFactorDoesNotSeeTranslationOrYawButSeesRollAndPitch) {
  for (const bool bounded : {false, true}) {
    for_each_imu_factor(
        bounded, 29,
        [](const WindowProblem&, const WindowState&, const NavState& xi, const NavState& xj,
           const Matrix15d& Ji, const Matrix15d& Jj) {
          const Eigen::Matrix<double, 15, 6> JN = Ji * global_motion(xi) + Jj * global_motion(xj);
          const double n_scale =
              std::max({1.0, xi.p_WB.norm(), xj.p_WB.norm(), xi.v_WB.norm(), xj.v_WB.norm()});
          const double J_scale = std::max(Ji.cwiseAbs().maxCoeff(), Jj.cwiseAbs().maxCoeff()) * n_scale;
          // Columns 0-2: translation, 5: yaw about W's z (gravity's axis).
          for (const int k : {0, 1, 2, 5})
            EXPECT_LT(JN.col(k).cwiseAbs().maxCoeff() / J_scale, 1e-12) << "direction " << k << "\n"
                                                                        << JN.col(k);
          // Roll and pitch tilt gravity in the body: the factor sees them, which is
          // also what shows the check above can fail.
          for (const int k : {3, 4})
            EXPECT_GT(JN.col(k).cwiseAbs().maxCoeff() / J_scale, 1e-4) << "direction " << k;
        });
  }
}

// The gauge factors are there to fix exactly the directions the other
// factors cannot see: each must see every one of them.
TEST(WindowResiduals, GaugeFactorsSeeEveryUnobservableDirection) {
  WindowProblem P = make_problem();
  P.opt.gauge_sigma = 1e-2;
  std::mt19937_64 rng(31);
  for (int trial = 0; trial < 4; ++trial) {
    const NavState x = some_state(rng);
    const Eigen::Matrix<double, 15, 6> N = global_motion(x);
    P.gauge_p = x.p_WB;
    P.gauge_yaw = yaw_of(x.q_WB);
    P.gauge_q = x.q_WB;
    Eigen::Matrix<double, 4, 6> Jg;
    gauge_residual(P, x, &Jg);
    Eigen::Matrix<double, 6, 4> N4;  // translation and yaw
    N4 << N.block<6, 3>(0, 0), N.block<6, 1>(0, 5);
    EXPECT_EQ(Eigen::FullPivLU<Eigen::Matrix4d>(Jg * N4).rank(), 4);
    // Without IMU factors all six are free, and the attitude gauge with the
    // position gauge's first three rows fixes them.
    Eigen::Matrix<double, 3, 6> Jr;
    gauge_rotation_residual(P, x, &Jr);
    Eigen::Matrix<double, 6, 6> Jall;
    Jall << Jg.topRows<3>(), Jr;
    using Matrix6x6 = Eigen::Matrix<double, 6, 6>;
    EXPECT_EQ(Eigen::FullPivLU<Matrix6x6>(Jall * N.topRows<6>()).rank(), 6);
  }
}

// The map pose factor ties a state to the map: like the gauges, it must see
// all six directions. The zero-velocity and hold factors act on the velocity
// and the biases: no translation reaches them, and a rotation does through
// the velocity (dv = w x v).
TEST(WindowResiduals, MapPoseZeroVelocityAndHoldFactorsNullSpaces) {
  WindowProblem P = make_problem();
  std::mt19937_64 rng(37);
  for (int trial = 0; trial < 4; ++trial) {
    const NavState x = some_state(rng);
    ASSERT_GT(x.v_WB.norm(), 0.05);
    const Eigen::Matrix<double, 15, 6> N = global_motion(x);
    const WindowState st = with_map_pose_factor(x);
    Matrix6d Jm;
    pose_prior_residual(st, x, &Jm);
    EXPECT_EQ(Eigen::FullPivLU<Matrix6d>(Jm * N.topRows<6>()).rank(), 6);
    // Zero velocity, r = v / sigma: d r / d dv = I / sigma.
    const Matrix3d Jz = Matrix3d::Identity() / P.opt.zero_velocity_sigma_mps;
    const Eigen::Matrix<double, 3, 6> ZN = Jz * N.middleRows<3>(6);
    // Hold on [v, bg, ba]: its Jacobian is the diagonal of hold_weights.
    const Eigen::Matrix<double, 9, 6> HN = hold_weights(P).asDiagonal() * N.bottomRows<9>();
    for (int k = 0; k < 3; ++k) {
      EXPECT_EQ(ZN.col(k).cwiseAbs().maxCoeff(), 0.0) << "translation " << k;
      EXPECT_EQ(HN.col(k).cwiseAbs().maxCoeff(), 0.0) << "translation " << k;
    }
    EXPECT_GT(ZN.rightCols<3>().cwiseAbs().maxCoeff(), 1e-3) << "a rotation turns the velocity";
    EXPECT_GT(HN.rightCols<3>().cwiseAbs().maxCoeff(), 1e-3);
  }
}

TEST(WindowResiduals, StateMinusJacobianAndRoundTrip) {
  std::mt19937_64 rng(13);
  for (int trial = 0; trial < 5; ++trial) {
    const NavState x0 = some_state(rng);
    const NavState x = kestrel::test::perturb(x0, rng, 0.2, 0.5);
    Matrix3d Jr;
    const Vector15d d = state_minus(x, x0, &Jr);
    const NavState back = state_plus(x0, d);
    EXPECT_LT((back.p_WB - x.p_WB).norm(), 1e-12);
    EXPECT_LT(kestrel::test::rot_err(back.q_WB, x.q_WB), 1e-12);
    EXPECT_TRUE(check_jacobian(Jr, [&](const VectorXd& dd) {
      Vector15d d15 = Vector15d::Zero();
      d15.segment<3>(3) = dd;
      return VectorXd(state_minus(state_plus(x, d15), x0).segment<3>(3));
    }));
  }
}

TEST(WindowResiduals, HuberMatchesCeresConvention) {
  double r1 = 0;
  EXPECT_DOUBLE_EQ(huber_rho(3.0, 2.0, &r1), 3.0);
  EXPECT_DOUBLE_EQ(r1, 1.0);
  EXPECT_DOUBLE_EQ(huber_rho(9.0, 2.0, &r1), 2.0 * 2.0 * 3.0 - 4.0);
  EXPECT_DOUBLE_EQ(r1, 2.0 / 3.0);
  EXPECT_DOUBLE_EQ(huber_rho(9.0, 0.0, &r1), 9.0);
}

}  // namespace
}  // namespace kestrel::core
