// Statistical summary of LONSC vs 2-point RANSAC on simulated RGB-D frames
// (the full table is bench_lonsc). Assertions are deliberately loose: only
// what holds with margin, so a broken algorithm fails and noise does not.
#include <gtest/gtest.h>

#include <cstdio>

#include "lonsc_eval.hpp"

namespace kc = kestrel::core;
namespace kt = kestrel::test;

namespace {
constexpr int kTrials = 100;
constexpr uint64_t kSeed = 20240601;
}  // namespace

TEST(TrackingLonscSummary, ThirtyPercentUniformOutliers) {
  kt::SimConfig cfg;
  cfg.outlier_frac = 0.3;
  kt::LonscMethod lonsc(kc::CorrespondenceOrder::kByMatchCost, false);
  kt::LonscMethod lonsc_gn(kc::CorrespondenceOrder::kByMatchCost, true);
  kt::RansacMethod ransac(false);
  const auto sl = kt::summarize("lonsc by_match_cost", kt::run_trials(cfg, std::ref(lonsc), kTrials, kSeed));
  const auto sg =
      kt::summarize("lonsc by_match_cost + GN", kt::run_trials(cfg, std::ref(lonsc_gn), kTrials, kSeed));
  const auto sr = kt::summarize("ransac 2pt", kt::run_trials(cfg, std::ref(ransac), kTrials, kSeed));
  kt::print_header(stdout);
  kt::print_row(stdout, sl);
  kt::print_row(stdout, sg);
  kt::print_row(stdout, sr);

  EXPECT_LT(sl.t_err_cm, 1.0);
  EXPECT_GT(sl.recall, 0.9);
  EXPECT_GT(sl.precision, 0.97);
  EXPECT_LT(sl.bad_frac, 0.05);
  // As accurate as RANSAC (same final least squares once the inlier set is right).
  EXPECT_LT(sl.t_err_cm, 1.25 * sr.t_err_cm + 0.05);
  // GN on the inliers improves on the IMU rotation (0.1-0.3 deg error).
  EXPECT_LT(sg.r_err_deg, 0.7 * sl.r_err_deg);
}

TEST(TrackingLonscSummary, ExactDataNoOutliersExactT) {
  kt::SimConfig cfg;
  cfg.noise = false;
  cfg.imu_err_min_deg = cfg.imu_err_max_deg = 0.0;
  kt::LonscMethod lonsc(kc::CorrespondenceOrder::kAsGiven, false);
  for (const auto& m : kt::run_trials(cfg, std::ref(lonsc), 20, kSeed)) {
    ASSERT_TRUE(m.ok);
    EXPECT_LT(m.t_err_cm, 1e-7);  // 1e-9 m
    EXPECT_EQ(m.recall, 1.0);
  }
}

TEST(TrackingLonscSummary, SeventyPercentUniformStillMostlyWorksWithCostOrder) {
  // With the match-cost order the head of the sequence is inlier-rich, so
  // runs exist even at 70 %; shuffled order is where LONSC breaks (bench).
  kt::SimConfig cfg;
  cfg.outlier_frac = 0.7;
  kt::LonscMethod lonsc(kc::CorrespondenceOrder::kByMatchCost, false);
  const auto s = kt::summarize("lonsc 70%", kt::run_trials(cfg, std::ref(lonsc), kTrials, kSeed));
  kt::print_row(stdout, s);
  EXPECT_LT(s.t_err_cm, 1.0);
  EXPECT_LT(s.bad_frac, 0.1);
}

TEST(TrackingLonscSummary, MovingObjectThirdOfTheScene) {
  // 50 % outliers, 2/3 of them one moving object (33 % of the scene): the
  // K-candidate consensus must keep LONSC on the static majority, where the
  // paper's longest-run rule alone fails in ~10 % of frames (bench_lonsc).
  kt::SimConfig cfg;
  cfg.outlier_frac = 0.5;
  cfg.structured = true;
  kt::LonscMethod lonsc(kc::CorrespondenceOrder::kByMatchCost, false);
  const auto s = kt::summarize("lonsc structured 50%", kt::run_trials(cfg, std::ref(lonsc), kTrials, kSeed));
  kt::print_row(stdout, s);
  EXPECT_LT(s.t_err_cm, 1.0);
  EXPECT_GT(s.recall, 0.9);
  EXPECT_LT(s.bad_frac, 0.05);
}
