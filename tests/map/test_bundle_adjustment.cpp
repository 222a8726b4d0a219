// Our local bundle adjustment against Ceres on the same problems: a ring of
// RGB-D keyframes over a textured room with pose and point noise, depth-less
// observations, outliers and the gravity prior. Both must reach the same
// minimum; ours at the mapping thread's iteration budget must get as far.
#include <gtest/gtest.h>

#include <algorithm>
#include <random>
#include <string>

#include "kestrel/core/bundle_adjustment.hpp"
#include "kestrel/core/so3.hpp"

namespace kestrel::core {
namespace {

struct Truth {
  std::vector<Eigen::Matrix3d> R_CM;
  std::vector<Eigen::Vector3d> t_CM, p_M;
};

// n_kf keyframes on a 1 m arc looking at points 2-4 m away; the first
// n_fixed are fixed (the gauge). Observations: 3 % outliers (20 px off),
// 20 % without depth.
BaProblem make_problem(uint32_t seed, int n_kf, int n_fixed, int n_pts, Truth& truth, double huber = 2.8) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> N(0.0, 1.0);
  std::uniform_real_distribution<double> U(0.0, 1.0);
  BaProblem pb;
  pb.K = PinholeK{525.0, 525.0, 319.5, 239.5};
  pb.huber = huber;
  pb.gravity_inv_sigma = 100.0;
  for (int i = 0; i < n_kf; ++i) {
    const double a = 0.15 * i;
    // Camera looking along +z of M with a yaw sweep and a small tilt.
    const Eigen::Matrix3d R_MC = (Eigen::AngleAxisd(0.4 * a, Eigen::Vector3d::UnitY()) *
                                  Eigen::AngleAxisd(0.05 * std::sin(3 * a), Eigen::Vector3d::UnitX()))
                                     .toRotationMatrix();
    const Eigen::Vector3d p_MC(std::sin(a), 0.1 * std::cos(2 * a), 0.3 * (1 - std::cos(a)));
    truth.R_CM.push_back(R_MC.transpose());
    truth.t_CM.push_back(-R_MC.transpose() * p_MC);
    BaPose P;
    P.fixed = i < n_fixed;
    P.has_gravity = !P.fixed;
    // The prior: M's down axis (0, 0, -1) as the truth sees it in C, plus a
    // little noise.
    P.g_C = (truth.R_CM.back() * Eigen::Vector3d(0, 0, -1) + 0.002 * Eigen::Vector3d(N(rng), N(rng), N(rng)));
    P.R_CM = P.fixed ? truth.R_CM.back()
                     : so3::Exp(0.01 * Eigen::Vector3d(N(rng), N(rng), N(rng))) * truth.R_CM.back();
    P.t_CM = P.fixed ? truth.t_CM.back() : truth.t_CM.back() + 0.02 * Eigen::Vector3d(N(rng), N(rng), N(rng));
    pb.poses.push_back(P);
  }
  for (int a = 0; a < n_pts; ++a) {
    const Eigen::Vector3d p(-0.8 + 2.6 * U(rng), -0.8 + 1.6 * U(rng), 2.0 + 2.0 * U(rng));
    truth.p_M.push_back(p);
    pb.points_M.push_back(p + 0.03 * Eigen::Vector3d(N(rng), N(rng), N(rng)));
  }
  for (int i = 0; i < n_kf; ++i)
    for (int a = 0; a < n_pts; ++a) {
      const Eigen::Vector3d c = truth.R_CM[static_cast<size_t>(i)] * truth.p_M[static_cast<size_t>(a)] +
                                truth.t_CM[static_cast<size_t>(i)];
      if (c.z() < 0.3 || U(rng) < 0.3) continue;
      const double u = pb.K.fx * c.x() / c.z() + pb.K.cx, v = pb.K.fy * c.y() / c.z() + pb.K.cy;
      if (u < 0 || v < 0 || u >= 640 || v >= 480) continue;
      BaObservation o;
      o.pose = i;
      o.point = a;
      const double sp = 1.0, sz = 0.0015 * c.z() * c.z() + 0.001;
      o.inv_sigma_px = 1.0 / sp;
      const bool outlier = U(rng) < 0.03;
      o.u_px = u + sp * N(rng) + (outlier ? 20.0 : 0.0);
      o.v_px = v + sp * N(rng);
      if (U(rng) < 0.8) {
        o.depth_m = c.z() + sz * N(rng);
        o.inv_sigma_z = 1.0 / sz;
      }
      pb.obs.push_back(o);
    }
  return pb;
}

double pose_diff_m(const BaProblem& a, const BaProblem& b) {
  double worst = 0;
  for (size_t i = 0; i < a.poses.size(); ++i)
    worst = std::max(worst, (a.poses[i].t_CM - b.poses[i].t_CM).norm());
  return worst;
}
double rot_diff_rad(const BaProblem& a, const BaProblem& b) {
  double worst = 0;
  for (size_t i = 0; i < a.poses.size(); ++i)
    worst = std::max(worst, so3::Log(a.poses[i].R_CM * b.poses[i].R_CM.transpose()).norm());
  return worst;
}
double median_point_diff_m(const BaProblem& a, const BaProblem& b) {
  std::vector<double> d;
  for (size_t i = 0; i < a.points_M.size(); ++i) d.push_back((a.points_M[i] - b.points_M[i]).norm());
  std::nth_element(d.begin(), d.begin() + static_cast<long>(d.size() / 2), d.end());
  return d[d.size() / 2];
}

// Solves `ours` with our solver and a copy with Ceres (300 iterations each),
// expects the same minimum (the tolerances below) and returns our result.
BaResult solve_both_expect_same_minimum(BaProblem& ours, const std::string& what) {
  BaProblem ref = ours;
  BaScratch scratch;
  const BaResult r_ours = solve_bundle_adjustment(ours, 300, scratch);
  const BaResult r_ref = solve_bundle_adjustment_ceres(ref, 300);
  EXPECT_TRUE(r_ours.usable) << what;
  EXPECT_TRUE(r_ref.usable) << what;
  EXPECT_NEAR(r_ours.final_cost, r_ref.final_cost, 1e-5 * r_ref.final_cost) << what;
  EXPECT_LT(pose_diff_m(ours, ref), 5e-4) << what;
  EXPECT_LT(rot_diff_rad(ours, ref), 5e-4) << what;
  EXPECT_LT(median_point_diff_m(ours, ref), 1e-4) << what;
  return r_ours;
}

// Each solver stops at its own tolerance (a relative cost change under 1e-6),
// and these problems have weak directions (a narrow view trades rotation
// against translation; the Huber's weights make both converge linearly), so
// the two meet at the same minimum to 1e-5 of the cost, the keyframes within
// half a millimetre and the median point within a tenth of one.
TEST(BundleAdjustment, ConvergesToCeresMinimum) {
  for (uint32_t seed : {1u, 2u, 3u}) {
    for (const double huber : {2.8, 1e6}) {
      Truth truth;
      BaProblem ours = make_problem(seed, 9, 2, 300, truth, huber);
      const std::string what = "seed " + std::to_string(seed) + " huber " + std::to_string(huber);
      const BaResult r_ours = solve_both_expect_same_minimum(ours, what);
      // With the Huber, near the truth: 2 cm of noise per axis on the camera
      // centres in, a few millimetres out (depth sigma is 1.4 cm at 3 m, and
      // a narrow view trades rotation against translation). Without it the
      // 20 px outliers pull the solution off, as they should.
      if (huber < 10) {
        EXPECT_GT(r_ours.initial_cost, 5 * r_ours.final_cost) << what << ": the noise was not removed";
        double worst_m = 0;
        for (size_t i = 0; i < ours.poses.size(); ++i)
          worst_m = std::max(worst_m, (ours.poses[i].R_CM.transpose() * ours.poses[i].t_CM -
                                       truth.R_CM[i].transpose() * truth.t_CM[i])
                                          .norm());
        EXPECT_LT(worst_m, 0.01) << what;
      }
      // The fixed keyframes did not move.
      EXPECT_EQ((ours.poses[0].t_CM - truth.t_CM[0]).norm(), 0.0);
    }
  }
}

// Global bundle adjustment's relative-pose factors (closed loops) in both
// solvers: Ceres differentiates its own copy of the residual, so a wrong
// analytic Jacobian in ours moves our minimum away from Ceres'.
TEST(BundleAdjustment, ConvergesToCeresMinimumWithRelativePoseFactors) {
  for (uint32_t seed : {11u, 12u}) {
    Truth truth;
    BaProblem ours = make_problem(seed, 9, 1, 200, truth);
    std::mt19937 rng(seed + 100);
    std::normal_distribution<double> N(0.0, 1.0);
    for (const auto& [a, b] : {std::pair<int, int>{0, 8}, {2, 7}, {5, 1}}) {
      BaRelativePose e;
      e.a = a;
      e.b = b;
      // T_CaCb of the truth, a little off, as a loop's verification gives it.
      const Eigen::Matrix3d R =
          truth.R_CM[static_cast<size_t>(a)] * truth.R_CM[static_cast<size_t>(b)].transpose();
      e.R_ab = so3::Exp(0.003 * Eigen::Vector3d(N(rng), N(rng), N(rng))) * R;
      e.t_ab = truth.t_CM[static_cast<size_t>(a)] - R * truth.t_CM[static_cast<size_t>(b)] +
               0.005 * Eigen::Vector3d(N(rng), N(rng), N(rng));
      e.inv_sigma_rad = 1.0 / 0.003;
      e.inv_sigma_m = 1.0 / 0.005;
      ours.relative.push_back(e);
    }
    solve_both_expect_same_minimum(ours, "seed " + std::to_string(seed));
  }
}

// The mapping thread's budget: five iterations per round. Ours must get at
// least as far as Ceres does in five.
TEST(BundleAdjustment, FiveIterationsGetAsFarAsCeres) {
  for (uint32_t seed : {4u, 5u, 6u, 7u}) {
    Truth truth;
    BaProblem ours = make_problem(seed, 9, 1, 400, truth);
    BaProblem ref = ours;
    BaScratch scratch;
    const BaResult r_ours = solve_bundle_adjustment(ours, 5, scratch);
    const BaResult r_ref = solve_bundle_adjustment_ceres(ref, 5);
    ASSERT_TRUE(r_ours.usable && r_ref.usable);
    EXPECT_LE(r_ours.final_cost, 1.01 * r_ref.final_cost) << "seed " << seed;
    EXPECT_LT(pose_diff_m(ours, ref), 1e-3) << "seed " << seed;
  }
}

// One step each, from the same start: the same linear system (Ceres' Huber
// correction is IRLS for a Huber; its Jacobi scaling and half-angle
// quaternion tangent leave a step damped by diag(J'J) unchanged), so the same
// step up to rounding. This checks what convergence alone does not: the
// normal equations, the Schur complement, the damping, the back-substitution.
// One point is measured twice by one keyframe (the Schur complement's
// same-keyframe pair), one sits behind a camera (the clamped depth).
TEST(BundleAdjustment, OneStepMatchesCeres) {
  for (uint32_t seed : {11u, 12u, 13u}) {
    Truth truth;
    BaProblem ours = make_problem(seed, 7, 1, 250, truth);
    size_t k_free = 0;  // an observation by a free keyframe: the first ones are the fixed keyframe's
    while (ours.poses[static_cast<size_t>(ours.obs[k_free].pose)].fixed) ++k_free;
    BaObservation twice = ours.obs[k_free + 5];
    twice.u_px += 0.7;
    twice.v_px -= 0.4;
    ours.obs.push_back(twice);
    BaObservation behind = ours.obs[k_free + 9];
    ours.points_M.push_back(
        -ours.poses[static_cast<size_t>(behind.pose)].R_CM.transpose() *
        (ours.poses[static_cast<size_t>(behind.pose)].t_CM + Eigen::Vector3d(0.1, 0.0, 0.5)));
    behind.point = static_cast<int32_t>(ours.points_M.size() - 1);
    ours.obs.push_back(behind);
    BaProblem ref = ours;
    BaScratch scratch;
    const BaResult r_ours = solve_bundle_adjustment(ours, 1, scratch);
    const BaResult r_ref = solve_bundle_adjustment_ceres(ref, 1);
    ASSERT_TRUE(r_ours.usable && r_ref.usable);
    ASSERT_EQ(r_ours.iterations, 1);
    EXPECT_LT(r_ours.final_cost, r_ours.initial_cost) << "seed " << seed << ": the step was not taken";
    EXPECT_NEAR(r_ours.final_cost, r_ref.final_cost, 1e-9 * r_ref.final_cost) << "seed " << seed;
    EXPECT_LT(pose_diff_m(ours, ref), 1e-9) << "seed " << seed;
    EXPECT_LT(rot_diff_rad(ours, ref), 1e-9) << "seed " << seed;
    double worst = 0;
    for (size_t a = 0; a < ours.points_M.size(); ++a)
      worst = std::max(worst, (ours.points_M[a] - ref.points_M[a]).norm());
    EXPECT_LT(worst, 1e-8) << "seed " << seed;
  }
}

// Disabled observations are out of the cost and the solve; a point seen only
// without depth from one keyframe (a rank-2 block) does not break the solve.
TEST(BundleAdjustment, DisabledObservationsAndWeakPoints) {
  Truth truth;
  BaProblem ours = make_problem(8, 6, 1, 150, truth);
  const double all = ba_cost(ours);
  ours.obs[0].enabled = false;
  EXPECT_LT(ba_cost(ours), all);
  BaObservation lone;
  lone.pose = 3;
  lone.point = static_cast<int32_t>(ours.points_M.size());
  ours.points_M.push_back(Eigen::Vector3d(0.1, 0.2, 2.5));
  const Eigen::Vector3d c = ours.poses[3].R_CM * ours.points_M.back() + ours.poses[3].t_CM;
  lone.u_px = ours.K.fx * c.x() / c.z() + ours.K.cx + 0.5;
  lone.v_px = ours.K.fy * c.y() / c.z() + ours.K.cy;
  ours.obs.push_back(lone);
  BaProblem ref = ours;
  BaProblem erased = ours;
  erased.obs.erase(erased.obs.begin());
  BaScratch scratch;
  const BaResult r = solve_bundle_adjustment(ours, 50, scratch);
  // A disabled observation is as good as none.
  BaScratch scratch2;
  const BaResult re = solve_bundle_adjustment(erased, 50, scratch2);
  EXPECT_NEAR(r.final_cost, re.final_cost, 1e-12 * re.final_cost);
  EXPECT_LT(pose_diff_m(ours, erased), 1e-12);
  const BaResult rr = solve_bundle_adjustment_ceres(ref, 50);
  ASSERT_TRUE(r.usable && rr.usable);
  EXPECT_TRUE(ours.points_M.back().allFinite());
  EXPECT_NEAR(r.final_cost, rr.final_cost, 1e-3 * rr.final_cost);
  EXPECT_LT(pose_diff_m(ours, ref), 1e-4);
}

// A problem with nothing to do: the truth itself, no noise.
TEST(BundleAdjustment, ExactProblemStaysPut) {
  Truth truth;
  BaProblem pb = make_problem(9, 5, 1, 100, truth);
  for (size_t i = 0; i < pb.poses.size(); ++i) {
    pb.poses[i].R_CM = truth.R_CM[i];
    pb.poses[i].t_CM = truth.t_CM[i];
    pb.poses[i].g_C = truth.R_CM[i] * Eigen::Vector3d(0, 0, -1);
  }
  pb.points_M = truth.p_M;
  for (BaObservation& o : pb.obs) {
    const Eigen::Vector3d c =
        truth.R_CM[static_cast<size_t>(o.pose)] * truth.p_M[static_cast<size_t>(o.point)] +
        truth.t_CM[static_cast<size_t>(o.pose)];
    o.u_px = pb.K.fx * c.x() / c.z() + pb.K.cx;
    o.v_px = pb.K.fy * c.y() / c.z() + pb.K.cy;
    if (o.depth_m > 0) o.depth_m = c.z();
  }
  BaScratch scratch;
  const BaResult r = solve_bundle_adjustment(pb, 5, scratch);
  ASSERT_TRUE(r.usable);
  EXPECT_LT(r.final_cost, 1e-12);
  for (size_t i = 0; i < pb.poses.size(); ++i) EXPECT_LT((pb.poses[i].t_CM - truth.t_CM[i]).norm(), 1e-9);
}

}  // namespace
}  // namespace kestrel::core

namespace kestrel::core {
namespace {

// Central differences of f (3 rows) at the problem's values, over the pose's
// left perturbation and the point, against the analytic columns.
template <class F>
double worst_column_error(const Eigen::MatrixXd& J, int n, F f) {
  const double h = 1e-6;
  double worst = 0;
  for (int d = 0; d < n; ++d) {
    const Eigen::VectorXd numeric = (f(d, h) - f(d, -h)) / (2 * h);
    worst = std::max(worst, (numeric - J.col(d)).norm() / std::max(1.0, numeric.norm()));
  }
  return worst;
}

BaProblem perturbed(const BaProblem& pb, const BaObservation& o, int d, double h) {
  BaProblem q = pb;
  BaPose& P = q.poses[static_cast<size_t>(o.pose)];
  if (d < 3) P.R_CM = so3::Exp(h * Eigen::Vector3d::Unit(d)) * P.R_CM;
  if (d >= 3 && d < 6) P.t_CM[d - 3] += h;
  if (d >= 6) q.points_M[static_cast<size_t>(o.point)][d - 6] += h;
  return q;
}

struct Linearised {
  Eigen::Vector3d r;
  Eigen::Matrix<double, 3, 6> J_pose;
  Eigen::Matrix3d J_point;
};
Linearised linearised(const BaProblem& pb, const BaObservation& o) {
  Linearised L;
  ba_observation_residual(pb, o, &L.r, &L.J_pose, &L.J_point);
  return L;
}

// The gravity prior's Jacobian over the pose's six columns (none in t).
Eigen::Matrix<double, 3, 6> gravity_jacobian(const BaProblem& pb, const BaPose& P) {
  Eigen::Matrix3d J;
  ba_gravity_residual(pb, P, &J);
  Eigen::Matrix<double, 3, 6> J6 = Eigen::Matrix<double, 3, 6>::Zero();
  J6.leftCols<3>() = J;
  return J6;
}

TEST(BundleAdjustmentResiduals, ObservationAndGravityJacobiansMatchNumeric) {
  Truth truth;
  const BaProblem pb = make_problem(7, 6, 1, 40, truth);
  int with_depth = 0, without = 0;
  for (size_t k = 0; k < pb.obs.size(); k += 7) {
    const BaObservation& o = pb.obs[k];
    const Linearised L = linearised(pb, o);
    const Eigen::Matrix<double, 3, 6>& Jp = L.J_pose;
    const Eigen::Matrix3d& Jl = L.J_point;
    Eigen::Matrix<double, 3, 9> J;
    J << Jp, Jl;
    (o.depth_m > 0 ? with_depth : without)++;
    EXPECT_LT(
        worst_column_error(
            J, 9, [&](int d, double h) { return Eigen::VectorXd(linearised(perturbed(pb, o, d, h), o).r); }),
        1e-6)
        << "observation " << k;
    const BaPose& P = pb.poses[static_cast<size_t>(o.pose)];
    const Eigen::Matrix<double, 3, 6> Jg6 = gravity_jacobian(pb, P);
    EXPECT_LT(worst_column_error(Jg6, 6,
                                 [&](int d, double h) {
                                   const BaProblem q = perturbed(pb, o, d, h);
                                   return Eigen::VectorXd(
                                       ba_gravity_residual(q, q.poses[static_cast<size_t>(o.pose)]));
                                 }),
              1e-6);
  }
  EXPECT_GT(with_depth, 3);
  EXPECT_GT(without, 0);
}

// The null spaces of the bundle adjustment's blocks. A rigid change of the
// map's coordinates, p_M <- Exp(w) p_M + tau, leaves what a camera sees
// unchanged when each pose moves by dtheta = -R_CM w, dt = -R_CM tau (its
// left perturbation), and each point by tau + w x p_M. Columns: [tau, w].
Eigen::Matrix<double, 6, 6> pose_motion(const BaPose& P) {
  Eigen::Matrix<double, 6, 6> N = Eigen::Matrix<double, 6, 6>::Zero();
  N.block<3, 3>(0, 3) = -P.R_CM;
  N.block<3, 3>(3, 0) = -P.R_CM;
  return N;
}

TEST(BundleAdjustmentResiduals, BlocksDoNotSeeWhatTheMapCannotObserve) {
  Truth truth;
  BaProblem pb = make_problem(11, 6, 1, 40, truth);
  // Reprojection and depth: none of the six directions.
  for (size_t k = 0; k < pb.obs.size(); k += 5) {
    const BaObservation& o = pb.obs[k];
    const Linearised L = linearised(pb, o);
    const Eigen::Matrix<double, 3, 6>& Jp = L.J_pose;
    const Eigen::Matrix3d& Jl = L.J_point;
    const Eigen::Vector3d& p = pb.points_M[static_cast<size_t>(o.point)];
    Eigen::Matrix<double, 3, 6> Np;
    Np << Eigen::Matrix3d::Identity(), -so3::hat(p);
    const Eigen::Matrix<double, 3, 6> JN = Jp * pose_motion(pb.poses[static_cast<size_t>(o.pose)]) + Jl * Np;
    EXPECT_LT(JN.cwiseAbs().maxCoeff() / (Jp.cwiseAbs().maxCoeff() * std::max(1.0, p.norm())), 1e-12)
        << "observation " << k << "\n"
        << JN;
  }
  // Relative poses: none of the six either.
  BaRelativePose e;
  e.a = 1;
  e.b = 4;
  e.R_ab = so3::Exp(Eigen::Vector3d(0.01, -0.02, 0.03)) * pb.poses[1].R_CM * pb.poses[4].R_CM.transpose();
  e.t_ab = Eigen::Vector3d(0.3, -0.1, 0.05);
  e.inv_sigma_rad = 100;
  e.inv_sigma_m = 50;
  Eigen::Matrix<double, 6, 1> rr;
  Eigen::Matrix<double, 6, 6> Ja, Jb;
  ba_relative_residual(pb, e, &rr, &Ja, &Jb);
  const Eigen::Matrix<double, 6, 6> JN = Ja * pose_motion(pb.poses[1]) + Jb * pose_motion(pb.poses[4]);
  EXPECT_LT(JN.cwiseAbs().maxCoeff() / (std::max(Ja.cwiseAbs().maxCoeff(), Jb.cwiseAbs().maxCoeff()) *
                                        std::max(1.0, pb.poses[4].t_CM.norm())),
            1e-12)
      << JN;
  // Gravity (M's z): translation and yaw about z unseen, roll and pitch seen,
  // which also shows the check can fail.
  for (size_t i = 1; i < pb.poses.size(); ++i) {
    const Eigen::Matrix<double, 3, 6> Jg6 = gravity_jacobian(pb, pb.poses[i]);
    const Eigen::Matrix<double, 3, 6> GN = Jg6 * pose_motion(pb.poses[i]);
    const double scale = Jg6.cwiseAbs().maxCoeff();
    for (const int k : {0, 1, 2, 5}) EXPECT_LT(GN.col(k).cwiseAbs().maxCoeff() / scale, 1e-12) << k;
    for (const int k : {3, 4}) EXPECT_GT(GN.col(k).cwiseAbs().maxCoeff() / scale, 1e-3) << k;
  }
}

}  // namespace
}  // namespace kestrel::core
