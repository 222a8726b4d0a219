// Unit tests: 2-point translation solver (paper 000 eq. 3), consistency test,
// LONSC (Algorithm 1), 2-point RANSAC, Gauss-Newton refinement, ordering,
// and "no heap allocation per call".
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <vector>

#include "jacobian_check.hpp"
#include "kestrel/core/lonsc.hpp"
#include "kestrel/core/motion_estimation.hpp"
#include "kestrel/rt/alloc_counter.hpp"
#include "lonsc_sim.hpp"

namespace kc = kestrel::core;
namespace kt = kestrel::test;

namespace {

kt::SimFrame exact_frame(double outlier_frac, uint64_t seed, int n = 300) {
  kt::SimConfig cfg;
  cfg.n = n;
  cfg.noise = false;
  cfg.outlier_frac = outlier_frac;
  return kt::simulate(cfg, seed);
}

double precision(const kt::SimFrame& f, const uint8_t* mask) {
  std::size_t tp = 0, k = 0;
  for (std::size_t i = 0; i < f.c.size(); ++i) {
    k += mask[i];
    tp += mask[i] && f.is_inlier[i];
  }
  return k ? double(tp) / double(k) : 0.0;
}
double recall(const kt::SimFrame& f, const uint8_t* mask) {
  std::size_t tp = 0;
  for (std::size_t i = 0; i < f.c.size(); ++i) tp += mask[i] && f.is_inlier[i];
  return double(tp) / double(f.num_inliers());
}

}  // namespace

TEST(TrackingTranslationLS, TwoNoiseFreeCorrespondencesGiveExactT) {
  for (uint64_t seed = 1; seed <= 20; ++seed) {
    const kt::SimFrame f = exact_frame(0.0, seed, 2);
    Eigen::Vector3d t;
    ASSERT_EQ(kc::translation_least_squares(f.R_true, kt::kinect_k(), f.c.data(), 2, &t),
              kc::MotionStatus::kOk);
    EXPECT_LT((t - f.t_true).norm(), 1e-9) << "seed " << seed;
  }
}

TEST(TrackingTranslationLS, ManyNoiseFreeCorrespondencesGiveExactT) {
  const kt::SimFrame f = exact_frame(0.0, 7);
  Eigen::Vector3d t, tw;
  ASSERT_EQ(kc::translation_least_squares(f.R_true, kt::kinect_k(), f.c.data(), f.c.size(), &t),
            kc::MotionStatus::kOk);
  ASSERT_EQ(kc::translation_least_squares_weighted(f.R_true, kt::kinect_k(), f.c.data(), f.c.size(), &tw),
            kc::MotionStatus::kOk);
  EXPECT_LT((t - f.t_true).norm(), 1e-9);
  EXPECT_LT((tw - f.t_true).norm(), 1e-9);
  // Index subset gives the same.
  const uint32_t idx[] = {3, 50, 299, 120};
  ASSERT_EQ(kc::translation_least_squares(f.R_true, kt::kinect_k(), f.c.data(), 4, &t, idx),
            kc::MotionStatus::kOk);
  EXPECT_LT((t - f.t_true).norm(), 1e-9);
}

TEST(TrackingTranslationLS, WeightedBeatsPlainUnderPixelNoise) {
  // Plain eq. 3 weights residuals by depth^2; with depths 0.5-5 m the ML
  // (depth-normalised) weights should win on average.
  double e_plain = 0, e_w = 0;
  for (uint64_t seed = 100; seed < 160; ++seed) {
    kt::SimConfig cfg;
    cfg.n = 60;
    const kt::SimFrame f = kt::simulate(cfg, seed);
    Eigen::Vector3d t, tw;
    ASSERT_EQ(kc::translation_least_squares(f.R_true, kt::kinect_k(), f.c.data(), f.c.size(), &t),
              kc::MotionStatus::kOk);
    ASSERT_EQ(kc::translation_least_squares_weighted(f.R_true, kt::kinect_k(), f.c.data(), f.c.size(), &tw),
              kc::MotionStatus::kOk);
    e_plain += (t - f.t_true).squaredNorm();
    e_w += (tw - f.t_true).squaredNorm();
  }
  EXPECT_LT(e_w, e_plain);
}

TEST(TrackingTranslationLS, DegenerateInputs) {
  const kc::PinholeK K = kt::kinect_k();
  const Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t(7, 7, 7);
  kc::Correspondence2D3D c[3];
  EXPECT_EQ(kc::translation_least_squares(R, K, c, 0, &t), kc::MotionStatus::kTooFewCorrespondences);
  c[0].p_prev = {0.1, 0.2, 2.0};
  c[0].u_cur = {300, 200};
  EXPECT_EQ(kc::translation_least_squares(R, K, c, 1, &t), kc::MotionStatus::kTooFewCorrespondences);
  // Same pixel, different points: t_z unobservable (rank 2).
  c[1] = c[0];
  c[1].p_prev = {-0.3, 0.1, 3.0};
  EXPECT_EQ(kc::translation_least_squares(R, K, c, 2, &t), kc::MotionStatus::kDegenerate);
  EXPECT_EQ(t, Eigen::Vector3d(7, 7, 7)) << "output must be untouched on failure";
  // Non-finite and behind-camera inputs are skipped, not propagated.
  c[1].u_cur = {std::numeric_limits<double>::quiet_NaN(), 1.0};
  c[2] = c[0];
  c[2].p_prev.z() = -1.0;
  EXPECT_EQ(kc::translation_least_squares(R, K, c, 3, &t), kc::MotionStatus::kTooFewCorrespondences);
}

TEST(TrackingConsistency, ThresholdAndBehindCamera) {
  const kc::PinholeK K = kt::kinect_k();
  kc::ConsistencyTest test;  // 3 px
  kc::Correspondence2D3D c;
  c.p_prev = {0.0, 0.0, 2.0};
  c.u_cur = {K.cx + 2.9, K.cy};
  const Eigen::Matrix3d I = Eigen::Matrix3d::Identity();
  double e2 = 0;
  EXPECT_TRUE(test.consistent(I, Eigen::Vector3d::Zero(), K, c, &e2));
  EXPECT_NEAR(e2, 2.9 * 2.9, 1e-9);
  c.u_cur.x() = K.cx + 3.1;
  EXPECT_FALSE(test.consistent(I, Eigen::Vector3d::Zero(), K, c));
  // A translation that puts the point behind the camera projects "perfectly"
  // through the origin but must be rejected.
  c.u_cur = {K.cx, K.cy};
  EXPECT_FALSE(test.consistent(I, Eigen::Vector3d(0, 0, -4.0), K, c, &e2));
  EXPECT_TRUE(std::isinf(e2));
  // Sigma scaling.
  test.scale_by_sigma = true;
  c.sigma_px = 2.0f;
  c.u_cur.x() = K.cx + 5.0;
  EXPECT_TRUE(test.consistent(I, Eigen::Vector3d::Zero(), K, c));
}

TEST(TrackingPoseRefine, ReprojectionJacobianMatchesNumeric) {
  const kt::SimFrame f = exact_frame(0.0, 3, 20);
  const kc::PinholeK K = kt::kinect_k();
  const Eigen::Vector3d t = f.t_true + Eigen::Vector3d(0.01, -0.02, 0.015);
  for (std::size_t i = 0; i < f.c.size(); ++i) {
    Eigen::Vector2d r;
    Eigen::Matrix<double, 2, 6> J;
    ASSERT_TRUE(kc::reprojection_residual(f.R_imu, t, K, f.c[i].p_prev, f.c[i].u_cur, &r, &J));
    auto r_of = [&](const Eigen::VectorXd& d) -> Eigen::VectorXd {
      Eigen::Vector2d rr;
      kc::reprojection_residual(kc::so3_exp(d.head<3>()) * f.R_imu, t + d.tail<3>(), K, f.c[i].p_prev,
                                f.c[i].u_cur, &rr);
      return rr;
    };
    EXPECT_TRUE(kestrel::test::check_jacobian(J, r_of, 1e-5, 1e-5)) << "correspondence " << i;
  }
}

TEST(TrackingPoseRefine, RotationPriorJacobianMatchesNumeric) {
  const Eigen::Matrix3d R_prior = kt::rot_from_axis_angle(Eigen::Vector3d(0.3, -1, 0.2), 0.7);
  for (double ang : {0.0, 1e-7, 0.01, 0.5, 2.0}) {
    const Eigen::Matrix3d R = kt::rot_from_axis_angle(Eigen::Vector3d(1, 2, 3), ang) * R_prior;
    Eigen::Matrix3d J;
    kc::rotation_prior_residual(R, R_prior, &J);
    auto r_of = [&](const Eigen::VectorXd& d) -> Eigen::VectorXd {
      return kc::rotation_prior_residual(kc::so3_exp(d) * R, R_prior);
    };
    EXPECT_TRUE(kestrel::test::check_jacobian(J, r_of, 1e-5, 1e-6)) << "angle " << ang;
  }
}

TEST(TrackingPoseRefine, ConvergesFromImuRotationOnExactData) {
  const kt::SimFrame f = exact_frame(0.0, 11);
  Eigen::Matrix3d R = f.R_imu;
  Eigen::Vector3d t;
  ASSERT_EQ(kc::translation_least_squares(R, kt::kinect_k(), f.c.data(), f.c.size(), &t),
            kc::MotionStatus::kOk);
  kc::PoseRefineOptions opt;
  opt.max_iterations = 5;
  const auto res =
      kc::refine_pose_gauss_newton(&R, &t, kt::kinect_k(), f.c.data(), f.c.size(), nullptr, 0, opt);
  ASSERT_TRUE(res.ok);
  EXPECT_LT(res.cost_final, res.cost_initial);
  EXPECT_LT(kt::rotation_error_deg(R, f.R_true), 1e-6);
  EXPECT_LT((t - f.t_true).norm(), 1e-8);
}

TEST(TrackingPoseRefine, RotationPriorPullsTowardsImu) {
  const kt::SimFrame f = exact_frame(0.0, 12, 10);
  kc::PoseRefineOptions opt;
  opt.rotation_prior_sigma_rad = 1e-6;  // overwhelming prior
  Eigen::Matrix3d R = f.R_imu;
  Eigen::Vector3d t = f.t_true;
  kc::refine_pose_gauss_newton(&R, &t, kt::kinect_k(), f.c.data(), f.c.size(), nullptr, 0, opt, &f.R_imu);
  EXPECT_LT(kt::rotation_error_deg(R, f.R_imu), 1e-3);
  // Too few points: refused, input untouched.
  Eigen::Matrix3d R2 = f.R_imu;
  const auto res = kc::refine_pose_gauss_newton(&R2, &t, kt::kinect_k(), f.c.data(), 2, nullptr, 0, {});
  EXPECT_FALSE(res.ok);
  EXPECT_EQ(R2, f.R_imu);
}

TEST(TrackingLonsc, ExactDataNoOutliersGivesExactT) {
  const kt::SimFrame f = exact_frame(0.0, 21);
  kc::LonscEstimator est(512);
  const auto r = est.estimate(f.R_true, kt::kinect_k(), f.c.data(), f.c.size());
  ASSERT_TRUE(r.ok()) << kc::to_string(r.status);
  EXPECT_LT((r.t - f.t_true).norm(), 1e-9);
  EXPECT_EQ(r.num_inliers, f.c.size());
  // T = 0 fails early, then (after at most a couple of too-close pairs) one run to the end.
  EXPECT_GE(r.longest_run, static_cast<int>(f.c.size()) - 3);
  EXPECT_LE(r.model_estimates, 3);
}

TEST(TrackingLonsc, ExactDataWithOutliersFindsExactInlierSet) {
  for (double frac : {0.1, 0.3, 0.5}) {
    const kt::SimFrame f = exact_frame(frac, 22);
    kc::LonscEstimator est(512);
    kc::CorrespondenceOrderer ord(512);
    std::vector<uint32_t> order(f.c.size());
    ord.order(kc::CorrespondenceOrder::kByMatchCost, f.c.data(), f.c.size(), order.data());
    const auto r = est.estimate(f.R_true, kt::kinect_k(), f.c.data(), f.c.size(), order.data());
    ASSERT_TRUE(r.ok()) << frac;
    EXPECT_LT((r.t - f.t_true).norm(), 1e-9) << frac;
    EXPECT_EQ(recall(f, est.inlier_mask()), 1.0) << frac;
    EXPECT_GT(precision(f, est.inlier_mask()), 0.99) << frac;  // a random pixel may land within 3 px
    for (std::size_t k = 1; k < r.num_inliers; ++k)
      EXPECT_LT(est.inlier_indices()[k - 1], est.inlier_indices()[k]);
  }
}

TEST(TrackingLonsc, CandidateRunsBeatAMovingObjectWithTheLongestRun) {
  // Order built so that a moving object gives the longest run (all its
  // correspondences first), while the static scene, the majority, is broken
  // into short runs by interleaved outliers.
  kt::SimConfig cfg;
  cfg.noise = false;
  cfg.imu_err_min_deg = cfg.imu_err_max_deg = 0.0;
  cfg.outlier_frac = 0.45;
  cfg.structured = true;
  const kt::SimFrame f = kt::simulate(cfg, 61);
  std::vector<uint32_t> obj, in, un, order;
  for (uint32_t i = 0; i < f.c.size(); ++i) (f.role[i] == 2 ? obj : f.role[i] == 1 ? un : in).push_back(i);
  ASSERT_GT(in.size(), obj.size());
  order = obj;
  for (std::size_t k = 0, u = 0; k < in.size(); ++k) {
    order.push_back(in[k]);
    if (k % 4 == 3 && u < un.size()) order.push_back(un[u++]);
  }
  kc::LonscOptions opt;
  opt.candidate_runs = 1;  // paper: the longest run wins
  kc::LonscEstimator paper(512, opt);
  const auto rp = paper.estimate(f.R_true, kt::kinect_k(), f.c.data(), f.c.size(), order.data());
  EXPECT_GE(rp.longest_run, static_cast<int>(obj.size()) - 2);
  EXPECT_GT((rp.t - f.t_true).norm(), 0.05) << "the longest run is the moving object";
  opt.candidate_runs = 3;
  kc::LonscEstimator est(512, opt);
  const auto r = est.estimate(f.R_true, kt::kinect_k(), f.c.data(), f.c.size(), order.data());
  ASSERT_TRUE(r.ok());
  EXPECT_LT((r.t - f.t_true).norm(), 1e-9);
  EXPECT_LT(r.chosen_run, r.longest_run);
  EXPECT_EQ(recall(f, est.inlier_mask()), 1.0);
}

TEST(TrackingLonsc, PaperLiteralModeAlsoWorks) {
  const kt::SimFrame f = exact_frame(0.3, 23);
  kc::LonscOptions opt;
  opt.verify_seed_pair = false;
  opt.refine_passes = 0;
  opt.weighted_least_squares = false;
  opt.grow_model = false;
  opt.candidate_runs = 1;
  kc::LonscEstimator est(512, opt);
  const auto r = est.estimate(f.R_true, kt::kinect_k(), f.c.data(), f.c.size());
  ASSERT_TRUE(r.ok());
  EXPECT_LT((r.t - f.t_true).norm(), 1e-9);
}

TEST(TrackingLonsc, EdgeCases) {
  const kc::PinholeK K = kt::kinect_k();
  const Eigen::Matrix3d I = Eigen::Matrix3d::Identity();
  kc::LonscEstimator est(8);
  kc::Correspondence2D3D c[10];
  EXPECT_EQ(est.estimate(I, K, c, 0).status, kc::MotionStatus::kTooFewCorrespondences);
  c[0].p_prev = {0, 0, 2};
  c[0].u_cur = {K.cx, K.cy};
  EXPECT_EQ(est.estimate(I, K, c, 1).status, kc::MotionStatus::kTooFewCorrespondences);
  // All pixels identical: every pair is degenerate -> no run, no crash.
  for (int i = 1; i < 10; ++i) {
    c[i] = c[0];
    c[i].p_prev = {0.01 * i, -0.02 * i, 1.0 + i};
  }
  auto r = est.estimate(I, K, c, 10);
  EXPECT_EQ(r.truncated, 2u);
  EXPECT_EQ(r.num_used, 8u);
  EXPECT_FALSE(r.ok());
  // Pure noise: mutually inconsistent random correspondences.
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> U(0, 1);
  std::vector<kc::Correspondence2D3D> noise(200);
  for (auto& n : noise) {
    n.p_prev = {U(rng) - 0.5, U(rng) - 0.5, 0.5 + 4 * U(rng)};
    n.u_cur = {640 * U(rng), 480 * U(rng)};
  }
  kc::LonscEstimator big(256);
  r = big.estimate(I, K, noise.data(), noise.size());
  EXPECT_FALSE(r.ok()) << "found " << r.num_inliers << " inliers in noise";
  // Order entries out of range are skipped.
  const kt::SimFrame f = exact_frame(0.0, 24, 20);
  std::vector<uint32_t> order = {0,    1,  999, 2,  3,  4,  5,  6,  7,  8,  9,
                                 1000, 10, 11,  12, 13, 14, 15, 16, 17, 18, 19};
  r = big.estimate(f.R_true, K, f.c.data(), f.c.size(), order.data());
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(r.num_inliers, 20u);
}

TEST(TrackingRansac, ExactDataAndDeterminism) {
  const kt::SimFrame f = exact_frame(0.5, 31);
  kc::TwoPointRansac ransac(512);
  const auto a = ransac.estimate(f.R_true, kt::kinect_k(), f.c.data(), f.c.size());
  ASSERT_TRUE(a.ok());
  EXPECT_LT((a.t - f.t_true).norm(), 1e-9);
  EXPECT_EQ(recall(f, ransac.inlier_mask()), 1.0);
  const auto b = ransac.estimate(f.R_true, kt::kinect_k(), f.c.data(), f.c.size());
  EXPECT_EQ(a.t, b.t);
  EXPECT_EQ(a.iterations, b.iterations);
  // Adaptive stop: far fewer than max_iterations at 50 % outliers (~17 needed).
  EXPECT_LT(a.iterations, 60);
}

TEST(TrackingOrdering, ByMatchCostAndHilbert) {
  kt::SimConfig cfg;
  cfg.outlier_frac = 0.3;
  const kt::SimFrame f = kt::simulate(cfg, 41);
  kc::CorrespondenceOrderer ord(512);
  std::vector<uint32_t> o(f.c.size());
  ASSERT_EQ(ord.order(kc::CorrespondenceOrder::kByMatchCost, f.c.data(), f.c.size(), o.data()), f.c.size());
  for (std::size_t k = 1; k < o.size(); ++k) EXPECT_LE(f.c[o[k - 1]].match_cost, f.c[o[k]].match_cost);
  // Hilbert: a permutation whose consecutive pixels are much closer than random.
  ord.order(kc::CorrespondenceOrder::kHilbert, f.c.data(), f.c.size(), o.data());
  std::vector<uint8_t> seen(o.size(), 0);
  double step_h = 0, step_raw = 0;
  for (std::size_t k = 0; k < o.size(); ++k) {
    ASSERT_LT(o[k], o.size());
    EXPECT_EQ(seen[o[k]]++, 0);
    if (k) {
      step_h += (f.c[o[k]].u_cur - f.c[o[k - 1]].u_cur).norm();
      step_raw += (f.c[k].u_cur - f.c[k - 1].u_cur).norm();
    }
  }
  EXPECT_LT(step_h, 0.5 * step_raw);
  // Shuffle: deterministic per seed, different across seeds.
  std::vector<uint32_t> o2(o.size()), o3(o.size());
  ord.order(kc::CorrespondenceOrder::kShuffled, f.c.data(), f.c.size(), o.data(), 640, 480, 9);
  ord.order(kc::CorrespondenceOrder::kShuffled, f.c.data(), f.c.size(), o2.data(), 640, 480, 9);
  ord.order(kc::CorrespondenceOrder::kShuffled, f.c.data(), f.c.size(), o3.data(), 640, 480, 10);
  EXPECT_EQ(o, o2);
  EXPECT_NE(o, o3);
}

TEST(TrackingAllocation, NoHeapAllocationPerCall) {
  ASSERT_TRUE(kestrel::rt::alloc_hook_linked());
  kt::SimConfig cfg;
  cfg.outlier_frac = 0.3;
  const kt::SimFrame f = kt::simulate(cfg, 51);
  const kc::PinholeK K = kt::kinect_k();
  kc::LonscEstimator lonsc(512);
  kc::TwoPointRansac ransac(512);
  kc::CorrespondenceOrderer ord(512);
  std::vector<uint32_t> order(512);
  // Warm-up call (nothing should be lazily allocated, but that is what we measure after).
  lonsc.estimate(f.R_imu, K, f.c.data(), f.c.size());
  kestrel::rt::AllocCountScope scope;
  for (int rep = 0; rep < 3; ++rep) {
    for (auto mode : {kc::CorrespondenceOrder::kAsGiven, kc::CorrespondenceOrder::kByMatchCost,
                      kc::CorrespondenceOrder::kHilbert, kc::CorrespondenceOrder::kShuffled}) {
      ord.order(mode, f.c.data(), f.c.size(), order.data());
      const auto r = lonsc.estimate(f.R_imu, K, f.c.data(), f.c.size(), order.data());
      ASSERT_TRUE(r.ok());
      Eigen::Matrix3d R = f.R_imu;
      Eigen::Vector3d t = r.t;
      kc::PoseRefineOptions popt;
      popt.rotation_prior_sigma_rad = 0.005;
      kc::refine_pose_gauss_newton(&R, &t, K, f.c.data(), f.c.size(), lonsc.inlier_indices(), r.num_inliers,
                                   popt, &f.R_imu);
    }
    const auto rr = ransac.estimate(f.R_imu, K, f.c.data(), f.c.size());
    ASSERT_TRUE(rr.ok());
    Eigen::Vector3d t;
    kc::translation_least_squares(f.R_imu, K, f.c.data(), f.c.size(), &t);
    kc::translation_least_squares_weighted(f.R_imu, K, f.c.data(), f.c.size(), &t);
  }
  EXPECT_EQ(scope.count(), 0u) << scope.bytes() << " bytes allocated";
}
