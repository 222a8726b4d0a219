// 6-DoF motion without an IMU rotation (core/tracking/rigid_consensus.hpp):
// the closed-form rigid fit, and LONSC's ordered runs against RANSAC on
// simulated RGB-D correspondences with outliers and missing depth.
#include <gtest/gtest.h>

#include <algorithm>
#include <random>
#include <vector>

#include "kestrel/core/lonsc.hpp"
#include "kestrel/core/rigid_consensus.hpp"
#include "kestrel/rt/alloc_counter.hpp"
#include "lonsc_sim.hpp"

namespace kestrel::test {
namespace {

using core::RigidMethod;

struct Frame3d {
  std::vector<core::Correspondence2D3D> c;
  std::vector<Eigen::Vector3d> q;
  std::vector<uint8_t> has_q, inlier;
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t = Eigen::Vector3d::Zero();
};

// A hand-held RGB-D camera between a keyframe and the current frame: up to
// 8 deg and 10 cm, Kinect depth noise on both ends, 20 % of the current
// pixels without depth, outliers matched to random pixels (with random depth)
// and ORB-like match costs that overlap between right and wrong matches.
Frame3d simulate3d(double outlier_frac, uint64_t seed, int n = 250) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> U(0.0, 1.0);
  std::normal_distribution<double> N(0.0, 1.0);
  const core::PinholeK K = kinect_k();
  Frame3d f;
  f.R = rot_from_axis_angle(random_unit(rng), 8.0 * M_PI / 180.0 * U(rng));
  f.t = random_unit(rng) * 0.10 * U(rng);
  auto project = [&](const Eigen::Vector3d& p) {
    return Eigen::Vector2d(K.fx * p.x() / p.z() + K.cx, K.fy * p.y() / p.z() + K.cy);
  };
  auto noisy_depth = [&](const Eigen::Vector3d& p) { return p * (1.0 + 0.0025 * p.z() * N(rng)); };
  while (static_cast<int>(f.c.size()) < n) {
    const Eigen::Vector2d u(10 + U(rng) * 620, 10 + U(rng) * 460);
    const double z = 0.6 + U(rng) * 3.0;
    const Eigen::Vector3d p((u.x() - K.cx) / K.fx * z, (u.y() - K.cy) / K.fy * z, z);
    const Eigen::Vector3d pc = f.R * p + f.t;
    const Eigen::Vector2d uc = project(pc);
    if (pc.z() < 0.3 || uc.x() < 5 || uc.x() > 635 || uc.y() < 5 || uc.y() > 475) continue;
    core::Correspondence2D3D c;
    c.p_prev = noisy_depth(p);
    c.sigma_px = 1.0f;
    const bool out = U(rng) < outlier_frac;
    Eigen::Vector3d q;
    if (out) {
      c.u_cur = Eigen::Vector2d(U(rng) * 640, U(rng) * 480);
      const double zq = 0.6 + U(rng) * 3.0;
      q = Eigen::Vector3d((c.u_cur.x() - K.cx) / K.fx * zq, (c.u_cur.y() - K.cy) / K.fy * zq, zq);
      c.match_cost = static_cast<float>(std::round(std::clamp(45 + 10 * N(rng), 0.0, 256.0)));
    } else {
      c.u_cur = uc + 0.7 * Eigen::Vector2d(N(rng), N(rng));
      q = noisy_depth(pc);
      c.match_cost = static_cast<float>(std::round(std::clamp(22 + 8 * N(rng), 0.0, 256.0)));
    }
    c.id = static_cast<uint32_t>(f.c.size());
    f.c.push_back(c);
    f.q.push_back(q);
    f.has_q.push_back(U(rng) < 0.8 ? 1 : 0);
    f.inlier.push_back(out ? 0 : 1);
  }
  return f;
}

TEST(RigidFit, ExactOnCleanPointsAndRefusesCollinearOnes) {
  const Eigen::Matrix3d R = rot_from_axis_angle(Eigen::Vector3d(1, 2, 3), 0.4);
  const Eigen::Vector3d t(0.1, -0.2, 0.05);
  std::vector<Eigen::Vector3d> p = {{0, 0, 1}, {1, 0, 2}, {0, 1, 3}, {1, 1, 1.5}}, q;
  for (const auto& x : p) q.push_back(R * x + t);
  Eigen::Matrix3d R_fit;
  Eigen::Vector3d t_fit;
  ASSERT_TRUE(core::fit_rigid(p.data(), q.data(), nullptr, 4, &R_fit, &t_fit));
  EXPECT_LT((R_fit - R).norm(), 1e-9);
  EXPECT_LT((t_fit - t).norm(), 1e-9);
  std::vector<Eigen::Vector3d> line = {{0, 0, 1}, {0, 0, 2}, {0, 0, 3}}, lq;
  for (const auto& x : line) lq.push_back(R * x + t);
  EXPECT_FALSE(core::fit_rigid(line.data(), lq.data(), nullptr, 3, &R_fit, &t_fit));
}

struct Outcome {
  int correct = 0;
  std::vector<double> fits, checks, inlier_share;
};

Outcome run(RigidMethod m, double outliers, int trials) {
  Outcome o;
  core::RigidConsensus rc(512);
  core::CorrespondenceOrderer orderer(512);
  std::vector<uint32_t> order(512);
  for (int k = 0; k < trials; ++k) {
    const Frame3d f = simulate3d(outliers, 1000 + static_cast<uint64_t>(k));
    const size_t no =
        orderer.order(core::CorrespondenceOrder::kByMatchCost, f.c.data(), f.c.size(), order.data());
    const core::RigidEstimate e = rc.estimate(m, kinect_k(), f.c.data(), f.q.data(), f.has_q.data(),
                                              f.c.size(), no ? order.data() : nullptr);
    const bool good = e.ok() && rotation_error_deg(e.R, f.R) < 0.5 && (e.t - f.t).norm() < 0.015;
    o.correct += good ? 1 : 0;
    o.fits.push_back(e.model_estimates);
    o.checks.push_back(static_cast<double>(e.consistency_checks));
    size_t true_in = 0;
    for (size_t i = 0; i < e.num_inliers; ++i) true_in += f.inlier[rc.inlier_indices()[i]];
    o.inlier_share.push_back(e.num_inliers ? static_cast<double>(true_in) / e.num_inliers : 0.0);
  }
  return o;
}

double median(std::vector<double> v) {
  std::nth_element(v.begin(), v.begin() + static_cast<long>(v.size() / 2), v.end());
  return v[v.size() / 2];
}

TEST(RigidConsensus, LonscRunsAndRansacRecoverTheMotionThroughOutliers) {
  for (double out : {0.3, 0.5, 0.7}) {
    // At 70 % outliers LONSC is right about 92-93 % of the time (300 seeds:
    // x86 278, the aarch64 build 276 - its compiler fuses multiply-adds and
    // so picks other hypotheses; the first 100 seeds gave 95 and 93, and a
    // bound of 95/100 had been set to x86's own count). The
    // bound is a rate with a margin (88 % of 300 is ~3 sigma under 93 %), not
    // one machine's count.
    const int trials = out < 0.6 ? 100 : 300;
    const int lonsc_min = out < 0.6 ? trials * 95 / 100 : trials * 88 / 100;
    const Outcome l = run(RigidMethod::kLonsc, out, trials), r = run(RigidMethod::kRansac, out, trials);
    std::printf(
        "outliers %.0f %%: lonsc %d/%d right, %.0f fits, %.0f pair checks (medians), inliers %.3f correct; "
        "ransac %d/%d right, %.0f fits, %.0f checks, %.3f\n",
        100 * out, l.correct, trials, median(l.fits), median(l.checks), median(l.inlier_share), r.correct,
        trials, median(r.fits), median(r.checks), median(r.inlier_share));
    EXPECT_GE(l.correct, lonsc_min) << "lonsc at " << out;
    EXPECT_GE(r.correct, trials * 90 / 100) << "ransac at " << out;
    EXPECT_GT(median(l.inlier_share), 0.97);
    // Ordered by match cost, the reliable matches come first: the walk tests
    // each pair about once and scores only its few longest runs, where every
    // RANSAC hypothesis tests them all. (Its SVD fits are more, not fewer: a
    // growing run re-fits at every pair, a 3x3 SVD that costs less than one
    // pass over the matches.)
    EXPECT_LT(median(l.checks), median(r.checks)) << "at " << out;
  }
}

TEST(RigidConsensus, TooFewPairsWithDepthIsAStatusAndNothingIsAllocated) {
  Frame3d f = simulate3d(0.2, 7);
  core::RigidConsensus rc(512);
  std::fill(f.has_q.begin(), f.has_q.end(), 0);
  f.has_q[3] = f.has_q[9] = 1;
  const core::RigidEstimate none =
      rc.estimate(RigidMethod::kLonsc, kinect_k(), f.c.data(), f.q.data(), f.has_q.data(), f.c.size());
  EXPECT_EQ(none.status, core::MotionStatus::kTooFewCorrespondences);
  const Frame3d g = simulate3d(0.4, 8);
  for (RigidMethod m : {RigidMethod::kLonsc, RigidMethod::kRansac}) {
    rt::AllocCountScope scope;
    const core::RigidEstimate e =
        rc.estimate(m, kinect_k(), g.c.data(), g.q.data(), g.has_q.data(), g.c.size());
    EXPECT_TRUE(e.ok());
    EXPECT_EQ(scope.count(), 0u) << core::to_string(m);
  }
  // RANSAC is re-seeded every call: the same input gives the same answer.
  const core::RigidEstimate a =
      rc.estimate(RigidMethod::kRansac, kinect_k(), g.c.data(), g.q.data(), g.has_q.data(), g.c.size());
  const core::RigidEstimate b =
      rc.estimate(RigidMethod::kRansac, kinect_k(), g.c.data(), g.q.data(), g.has_q.data(), g.c.size());
  EXPECT_EQ(a.num_inliers, b.num_inliers);
  EXPECT_EQ((a.t - b.t).norm(), 0.0);
}

}  // namespace
}  // namespace kestrel::test
