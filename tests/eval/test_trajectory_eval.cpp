// Association, alignment and metrics on hand-computable cases.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "eval_test_util.hpp"
#include "kestrel/tools/trajectory_eval.hpp"
#include "test_data.hpp"

namespace kestrel::tools {
namespace {

using test::lissajous;
using test::transformed;

constexpr double kDeg = M_PI / 180.0;

EvalOptions with_align(Alignment a) {
  EvalOptions o;
  o.align = a;
  return o;
}

TEST(EvalMetrics, IdenticalTrajectoriesGiveZeroForEveryAlignment) {
  const Trajectory gt = lissajous();
  for (Alignment a : {Alignment::kNone, Alignment::kSe3, Alignment::kSim3, Alignment::kPosYaw}) {
    SCOPED_TRACE(alignment_name(a));
    const EvalResult r = evaluate(gt, gt, with_align(a));
    EXPECT_EQ(r.matched, static_cast<int>(gt.size()));
    EXPECT_EQ(r.unmatched, 0);
    EXPECT_NEAR(r.ate_m.rmse, 0.0, 1e-9);
    EXPECT_NEAR(r.ate_m.max, 0.0, 1e-9);
    EXPECT_NEAR(r.ate_rot_deg.rmse, 0.0, 1e-5);
    EXPECT_GT(r.rpe_pairs, 0);
    EXPECT_NEAR(r.rpe_trans_rmse_m, 0.0, 1e-9);
    EXPECT_NEAR(r.rpe_rot_rmse_deg, 0.0, 1e-5);
    EXPECT_NEAR(r.T_align.scale, 1.0, 1e-9);
    EXPECT_NEAR(r.coverage, 1.0, 1e-12);
  }
}

TEST(EvalAlignment, Se3RecoversAKnownRigidTransform) {
  const Trajectory gt = lissajous();
  // est lives in a world rotated and shifted w.r.t. gt: gt = R est + t.
  const Eigen::Matrix3d R =
      Eigen::AngleAxisd(0.8, Eigen::Vector3d(0.2, -0.5, 1.0).normalized()).toRotationMatrix();
  const Eigen::Vector3d t(1.0, -2.0, 0.5);
  const Trajectory est = transformed(gt, 1.0, R.transpose(), -(R.transpose() * t));

  const EvalResult r = evaluate(gt, est, with_align(Alignment::kSe3));
  EXPECT_LT((r.T_align.R - R).norm(), 1e-9);
  EXPECT_LT((r.T_align.t - t).norm(), 1e-9);
  EXPECT_NEAR(r.T_align.scale, 1.0, 1e-12);
  EXPECT_NEAR(r.ate_m.rmse, 0.0, 1e-9);
  EXPECT_NEAR(r.ate_rot_deg.rmse, 0.0, 1e-5);

  // Unaligned, the error is exactly how far the transform moves each point.
  const EvalResult n = evaluate(gt, est, with_align(Alignment::kNone));
  double sum_sq = 0;
  double max_err = 0;
  for (size_t i = 0; i < gt.size(); ++i) {
    const double e = (gt[i].p - est[i].p).norm();
    sum_sq += e * e;
    max_err = std::max(max_err, e);
  }
  EXPECT_NEAR(n.ate_m.rmse, std::sqrt(sum_sq / gt.size()), 1e-12);
  EXPECT_NEAR(n.ate_m.max, max_err, 1e-12);
  // The attitude error without alignment is the rotation angle of R, at every pose.
  EXPECT_NEAR(n.ate_rot_deg.rmse, 0.8 / kDeg, 1e-6);
  EXPECT_NEAR(n.ate_rot_deg.min, 0.8 / kDeg, 1e-6);
}

TEST(EvalAlignment, NoneReportsAPureTranslationOffsetExactly) {
  const Trajectory gt = lissajous();
  const Eigen::Vector3d t(1.0, -2.0, 0.5);
  const Trajectory est = transformed(gt, 1.0, Eigen::Matrix3d::Identity(), t);
  const EvalResult r = evaluate(gt, est, with_align(Alignment::kNone));
  EXPECT_NEAR(r.ate_m.rmse, t.norm(), 1e-12);
  EXPECT_NEAR(r.ate_m.min, t.norm(), 1e-12);
  EXPECT_NEAR(r.ate_m.max, t.norm(), 1e-12);
  // Relative motion does not see a constant offset.
  EXPECT_NEAR(r.rpe_trans_rmse_m, 0.0, 1e-12);
}

TEST(EvalAlignment, ConstantOffsetAlongXIsExactlyTenCentimetres) {
  const Trajectory gt = lissajous();
  const Trajectory est = transformed(gt, 1.0, Eigen::Matrix3d::Identity(), Eigen::Vector3d(0.1, 0, 0));
  const EvalResult r = evaluate(gt, est, with_align(Alignment::kNone));
  EXPECT_NEAR(r.ate_m.rmse, 0.1, 1e-12);
  EXPECT_NEAR(r.ate_m.mean, 0.1, 1e-12);
  EXPECT_NEAR(r.ate_m.median, 0.1, 1e-12);
  EXPECT_NEAR(r.ate_m.std, 0.0, 1e-9);
  EXPECT_NEAR(r.ate_rot_deg.rmse, 0.0, 1e-9);
  // Any alignment with translation removes it.
  EXPECT_NEAR(evaluate(gt, est, with_align(Alignment::kPosYaw)).ate_m.rmse, 0.0, 1e-9);
}

TEST(EvalAlignment, Sim3RecoversAKnownScale) {
  const Trajectory gt = lissajous();
  const Eigen::Matrix3d R = Eigen::AngleAxisd(-0.4, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  const double s = 0.5;  // est is half size: monocular-style scale error
  const Trajectory est = transformed(gt, s, R, Eigen::Vector3d(0.3, 0.2, -0.1));

  const EvalResult r = evaluate(gt, est, with_align(Alignment::kSim3));
  EXPECT_NEAR(r.T_align.scale, 1.0 / s, 1e-9);
  EXPECT_LT((r.T_align.R - R.transpose()).norm(), 1e-9);
  EXPECT_NEAR(r.ate_m.rmse, 0.0, 1e-9);
  EXPECT_NEAR(r.ate_rot_deg.rmse, 0.0, 1e-5);
  EXPECT_NEAR(r.rpe_trans_rmse_m, 0.0, 1e-9);  // RPE uses the scaled estimate

  // Without scale the error cannot vanish.
  const EvalResult se3 = evaluate(gt, est, with_align(Alignment::kSe3));
  EXPECT_NEAR(se3.T_align.scale, 1.0, 0.0);
  EXPECT_GT(se3.ate_m.rmse, 0.1);
}

TEST(EvalAlignment, PosYawRemovesYawAndTranslation) {
  const Trajectory gt = lissajous();
  const Eigen::Matrix3d Rz = Eigen::AngleAxisd(30 * kDeg, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  const Trajectory est = transformed(gt, 1.0, Rz, Eigen::Vector3d(5, -3, 2));
  const EvalResult r = evaluate(gt, est, with_align(Alignment::kPosYaw));
  EXPECT_NEAR(r.ate_m.rmse, 0.0, 1e-9);
  EXPECT_NEAR(r.ate_rot_deg.rmse, 0.0, 1e-5);
  EXPECT_NEAR(Eigen::AngleAxisd(r.T_align.R).angle(), 30 * kDeg, 1e-9);
}

TEST(EvalAlignment, PosYawDoesNotRemoveRollOrPitch) {
  // VIO observes gravity, so a tilt of the estimate is a real error and must show.
  const Trajectory gt = lissajous();
  const Eigen::Matrix3d tilt = (Eigen::AngleAxisd(30 * kDeg, Eigen::Vector3d::UnitZ()) *
                                Eigen::AngleAxisd(10 * kDeg, Eigen::Vector3d::UnitX()))
                                   .toRotationMatrix();
  const Trajectory est = transformed(gt, 1.0, tilt, Eigen::Vector3d(1, 2, 3));

  const EvalResult py = evaluate(gt, est, with_align(Alignment::kPosYaw));
  // The remaining attitude error is the 10 degree roll (give or take the yaw fit).
  EXPECT_GT(py.ate_rot_deg.rmse, 9.0);
  EXPECT_LT(py.ate_rot_deg.rmse, 11.0);
  EXPECT_GT(py.ate_m.rmse, 0.05);
  // Its rotation is about z only, whatever the data.
  EXPECT_LT((py.T_align.R * Eigen::Vector3d::UnitZ() - Eigen::Vector3d::UnitZ()).norm(), 1e-12);

  const EvalResult se3 = evaluate(gt, est, with_align(Alignment::kSe3));
  EXPECT_NEAR(se3.ate_m.rmse, 0.0, 1e-9);
  EXPECT_NEAR(se3.ate_rot_deg.rmse, 0.0, 1e-5);
}

TEST(EvalAlignment, PosYawClosedFormMatchesABruteForceSearch) {
  std::mt19937 rng(7);
  std::normal_distribution<double> n01(0.0, 1.0);
  std::vector<Eigen::Vector3d> est, gt;
  const Eigen::Matrix3d R = Eigen::AngleAxisd(-2.0, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  for (int i = 0; i < 200; ++i) {
    const Eigen::Vector3d e(n01(rng), n01(rng), n01(rng));
    est.push_back(e);
    gt.push_back(R * e + Eigen::Vector3d(1, 2, 3) + 0.3 * Eigen::Vector3d(n01(rng), n01(rng), n01(rng)));
  }
  const Sim3 T = align_positions(est, gt, Alignment::kPosYaw);
  auto cost = [&](double yaw) {
    const Eigen::Matrix3d Ry = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
    Eigen::Vector3d mu_e = Eigen::Vector3d::Zero(), mu_g = Eigen::Vector3d::Zero();
    for (size_t i = 0; i < est.size(); ++i) {
      mu_e += est[i] / est.size();
      mu_g += gt[i] / gt.size();
    }
    double c = 0;
    for (size_t i = 0; i < est.size(); ++i) c += (gt[i] - (Ry * est[i] + mu_g - Ry * mu_e)).squaredNorm();
    return c;
  };
  double best_yaw = 0, best = INFINITY;
  for (int k = 0; k < 36000; ++k) {
    const double yaw = -M_PI + k * (2 * M_PI / 36000);
    if (cost(yaw) < best) {
      best = cost(yaw);
      best_yaw = yaw;
    }
  }
  const double yaw = std::atan2(T.R(1, 0), T.R(0, 0));
  EXPECT_NEAR(std::remainder(yaw - best_yaw, 2 * M_PI), 0.0, 2 * M_PI / 36000);
  EXPECT_LE(cost(yaw), best + 1e-9);
}

TEST(EvalAlignment, Se3MatchesEigenUmeyamaOnNoisyData) {
  std::mt19937 rng(11);
  std::normal_distribution<double> n01(0.0, 1.0);
  std::vector<Eigen::Vector3d> est, gt;
  Eigen::Matrix3Xd src(3, 100), dst(3, 100);
  const Eigen::Matrix3d R = Eigen::AngleAxisd(1.1, Eigen::Vector3d(1, 1, 0).normalized()).toRotationMatrix();
  for (int i = 0; i < 100; ++i) {
    const Eigen::Vector3d e(n01(rng), n01(rng), n01(rng));
    est.push_back(e);
    gt.push_back(R * e + Eigen::Vector3d(-1, 0, 4) + 0.05 * Eigen::Vector3d(n01(rng), n01(rng), n01(rng)));
    src.col(i) = est.back();
    dst.col(i) = gt.back();
  }
  const Sim3 T = align_positions(est, gt, Alignment::kSe3);
  const Eigen::Matrix4d ref = Eigen::umeyama(src, dst, false);
  EXPECT_LT((T.R - ref.topLeftCorner<3, 3>()).norm(), 1e-12);
  EXPECT_LT((T.t - ref.topRightCorner<3, 1>()).norm(), 1e-12);
  EXPECT_LT((T.R - R).norm(), 0.05);
}

TEST(EvalMetrics, ZeroMeanNoiseGivesSigmaTimesSqrt3) {
  const Trajectory gt = lissajous(200.0, 100.0);  // 20001 poses
  std::mt19937 rng(42);
  const double sigma = 0.05;
  std::normal_distribution<double> noise(0.0, sigma);
  Trajectory est = gt;
  for (auto& p : est) p.p += Eigen::Vector3d(noise(rng), noise(rng), noise(rng));
  const double expected = sigma * std::sqrt(3.0);
  // Relative standard error of the RMSE is ~0.3% here; 2% is a wide, still failing, margin.
  const EvalResult r = evaluate(gt, est, with_align(Alignment::kNone));
  EXPECT_NEAR(r.ate_m.rmse, expected, 0.02 * expected);
  const EvalResult a = evaluate(gt, est, with_align(Alignment::kSe3));
  EXPECT_NEAR(a.ate_m.rmse, expected, 0.02 * expected);
  EXPECT_LE(a.ate_m.rmse, r.ate_m.rmse + 1e-12);  // least squares can only lower it
}

// Straight line along x at 1 m/s, 100 Hz, 20 s.
Trajectory straight_line(double speed_mps, double yaw_rate_rps = 0.0, bool moving = true) {
  Trajectory t;
  for (int i = 0; i <= 2000; ++i) {
    TimedPose p;
    p.t_ns = static_cast<int64_t>(i) * 10'000'000;
    const double ts = i * 0.01;
    p.p = moving ? Eigen::Vector3d(speed_mps * ts, 0, 0) : Eigen::Vector3d::Zero();
    p.q = Eigen::AngleAxisd(yaw_rate_rps * ts, Eigen::Vector3d::UnitZ());
    t.push_back(p);
  }
  return t;
}

// An estimate that turns 10 % less than the truth about the body's x axis
// (and exactly as much about y and z) reports that gain whatever the world
// alignment; an axis the truth barely turns about has no gain.
TEST(EvalMetrics, RotationGainFindsAnAxisThatTurnsTenPercentShort) {
  Trajectory gt, est;
  for (int i = 0; i <= 300; ++i) {
    const double t = i / 30.0;
    TimedPose g;
    g.t_ns = 1'000'000'000 + static_cast<int64_t>(std::llround(t * 1e9));
    g.p = Eigen::Vector3d(0.3 * t, 0.2 * std::sin(t), 1.0);
    const Eigen::Vector3d w(0.3 * std::sin(0.7 * t), 0.25 * std::sin(0.5 * t), 0.01 * std::sin(t));
    g.q = Eigen::Quaterniond(Eigen::AngleAxisd(w.norm(), w.normalized()));
    TimedPose e = g;
    const Eigen::Vector3d we(0.9 * w.x(), w.y(), w.z());
    e.q = Eigen::Quaterniond(Eigen::AngleAxisd(we.norm(), we.normalized()));
    gt.push_back(g);
    est.push_back(e);
  }
  const Eigen::Matrix3d R = Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  const EvalResult r =
      evaluate(gt, transformed(est, 1.0, R, Eigen::Vector3d(1, 2, 3)), with_align(Alignment::kSe3));
  EXPECT_NEAR(r.rot_gain.x(), 0.9, 0.01);
  EXPECT_NEAR(r.rot_gain.y(), 1.0, 0.01);
  EXPECT_TRUE(std::isnan(r.rot_gain.z())) << "the truth turns 0.6 degrees about z: " << r.rot_gain.z();
  const EvalResult same = evaluate(gt, gt, with_align(Alignment::kSe3));
  EXPECT_NEAR(same.rot_gain.x(), 1.0, 1e-9);
  EXPECT_NEAR(same.rot_gain.y(), 1.0, 1e-9);
}

TEST(EvalRpe, ConstantVelocityErrorGivesErrorTimesDelta) {
  const double dv = 0.05;
  const Trajectory gt = straight_line(1.0);
  const Trajectory est = straight_line(1.0 + dv);
  for (Alignment a : {Alignment::kNone, Alignment::kPosYaw}) {
    SCOPED_TRACE(alignment_name(a));
    EvalOptions o = with_align(a);
    o.rpe_delta_s = 1.0;
    const EvalResult r = evaluate(gt, est, o);
    EXPECT_EQ(r.rpe_pairs, 1901);  // starts 0.00 .. 19.00 s
    EXPECT_NEAR(r.rpe_trans_rmse_m, dv * 1.0, 1e-9);
    EXPECT_NEAR(r.rpe_trans_mean_m, dv * 1.0, 1e-9);
    EXPECT_NEAR(r.rpe_trans_m_per_s, dv, 1e-9);
    EXPECT_NEAR(r.rpe_rot_rmse_deg, 0.0, 1e-9);
    o.rpe_delta_s = 2.0;
    EXPECT_NEAR(evaluate(gt, est, o).rpe_trans_rmse_m, dv * 2.0, 1e-9);
    EXPECT_NEAR(evaluate(gt, est, o).rpe_trans_m_per_s, dv, 1e-9);
  }
}

TEST(EvalRpe, ConstantYawRateErrorGivesRateTimesDelta) {
  const double dw = 0.01;  // rad/s
  const Trajectory gt = straight_line(0.0, 0.0, false);
  const Trajectory est = straight_line(0.0, dw, false);
  EvalOptions o = with_align(Alignment::kNone);
  o.rpe_delta_s = 0.5;
  const EvalResult r = evaluate(gt, est, o);
  EXPECT_NEAR(r.rpe_rot_rmse_deg, dw * 0.5 / kDeg, 1e-7);
  EXPECT_NEAR(r.rpe_rot_mean_deg, dw * 0.5 / kDeg, 1e-7);
  EXPECT_NEAR(r.rpe_trans_rmse_m, 0.0, 1e-12);
}

TEST(EvalRpe, KittiSegmentsReportPercentOfDistance) {
  const Trajectory gt = straight_line(1.0);    // 20 m
  const Trajectory est = straight_line(1.05);  // travels 5% too far
  EvalOptions o = with_align(Alignment::kNone);
  o.segment_lengths_m = {1.0, 5.0, 50.0};
  const EvalResult r = evaluate(gt, est, o);
  ASSERT_EQ(r.segments.size(), 3u);
  for (int k = 0; k < 2; ++k) {
    EXPECT_GT(r.segments[k].count, 0);
    EXPECT_NEAR(r.segments[k].trans_pct, 5.0, 1e-6);
    EXPECT_NEAR(r.segments[k].rot_deg_per_m, 0.0, 1e-9);
  }
  EXPECT_EQ(r.segments[0].count, 1901);  // starts 0 .. 19 m
  EXPECT_EQ(r.segments[2].count, 0);     // longer than the trajectory
  EXPECT_TRUE(std::isnan(r.segments[2].trans_pct));
}

TEST(EvalAssociation, InterpolatesPositionLinearlyAndRotationBySlerp) {
  Trajectory gt(2);
  gt[0].t_ns = 0;
  gt[0].p = Eigen::Vector3d(0, 0, 0);
  gt[1].t_ns = 10'000'000;
  gt[1].p = Eigen::Vector3d(1, 2, 3);
  gt[1].q = Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ());
  bool interp = false;
  auto p = pose_at(gt, 2'500'000, 20'000'000, &interp);
  ASSERT_TRUE(p.has_value());
  EXPECT_TRUE(interp);
  EXPECT_EQ(p->t_ns, 2'500'000);
  EXPECT_LT((p->p - Eigen::Vector3d(0.25, 0.5, 0.75)).norm(), 1e-15);
  const Eigen::Quaterniond expect(Eigen::AngleAxisd(M_PI / 8, Eigen::Vector3d::UnitZ()));
  EXPECT_NEAR(p->q.angularDistance(expect), 0.0, 1e-12);

  // A gap wider than the tolerance: nearest neighbour within it, or nothing.
  p = pose_at(gt, 2'500'000, 5'000'000, &interp);
  ASSERT_TRUE(p.has_value());
  EXPECT_FALSE(interp);
  EXPECT_LT(p->p.norm(), 1e-15);
  p = pose_at(gt, 9'000'000, 5'000'000, &interp);
  ASSERT_TRUE(p.has_value());
  EXPECT_LT((p->p - Eigen::Vector3d(1, 2, 3)).norm(), 1e-15);
  EXPECT_FALSE(pose_at(gt, 5'000'000, 4'000'000).has_value());
  EXPECT_FALSE(pose_at(gt, 31'000'000, 20'000'000).has_value());
  EXPECT_TRUE(pose_at(gt, 30'000'000, 20'000'000).has_value());  // tolerance is inclusive
  // An exact hit returns the sample itself.
  p = pose_at(gt, 10'000'000, 0, &interp);
  ASSERT_TRUE(p.has_value());
  EXPECT_FALSE(interp);
  EXPECT_LT((p->p - Eigen::Vector3d(1, 2, 3)).norm(), 0.0 + 1e-300);

  // Slerp takes the short way even when the stored signs disagree.
  gt[1].q.coeffs() = -gt[1].q.coeffs();
  p = pose_at(gt, 2'500'000, 20'000'000);
  EXPECT_NEAR(p->q.angularDistance(expect), 0.0, 1e-12);
}

TEST(EvalAssociation, TimeOffsetsAndGapsCountUnmatched) {
  // GT at 100 Hz over [0, 10] s, moving at (1, 2, 0) m/s, with (4 s, 5 s) missing.
  Trajectory gt;
  for (int i = 0; i <= 1000; ++i) {
    if (i > 400 && i < 500) continue;
    TimedPose p;
    p.t_ns = static_cast<int64_t>(i) * 10'000'000;
    p.p = Eigen::Vector3d(1, 2, 0) * (i * 0.01);
    gt.push_back(p);
  }
  // Estimate at 20 Hz, 3 ms late, running 0.95 s past the ground truth.
  Trajectory est;
  for (int k = 0; k < 220; ++k) {
    TimedPose p;
    p.t_ns = 3'000'000 + static_cast<int64_t>(k) * 50'000'000;
    p.p = Eigen::Vector3d(1, 2, 0) * (p.t_ns * 1e-9);
    est.push_back(p);
  }
  const EvalResult r = evaluate(gt, est, with_align(Alignment::kNone));
  // Unmatched by hand: 4.053 .. 4.953 s (19, inside the hole) and 10.053 .. 10.953 s (19, past the end).
  EXPECT_EQ(r.unmatched, 38);
  EXPECT_EQ(r.matched, 182);
  // 4.003 s and 10.003 s have one neighbour only: nearest, not interpolated.
  EXPECT_EQ(r.interpolated, 180);
  ASSERT_FALSE(r.warnings.empty());
  EXPECT_NE(r.warnings.front().find("38 of 220"), std::string::npos) << r.warnings.front();
  // Interpolated poses are exact on a straight line; the two nearest ones are 3 ms off.
  EXPECT_NEAR(r.ate_m.max, 0.003 * std::sqrt(5.0), 1e-9);
  EXPECT_NEAR(r.ate_m.median, 0.0, 1e-9);
  // Coverage: the 1 s hole breaks the estimate into two covered stretches.
  EXPECT_NEAR(r.coverage, (4.003 - 0.003 + 10.003 - 5.003) / 10.0, 1e-9);
}

TEST(EvalAssociation, TooFewMatchesThrowsWithCounts) {
  const Trajectory gt = lissajous(5.0);
  Trajectory est = lissajous(5.0, 100.0, 1'000'000'000'000);  // another clock entirely
  try {
    evaluate(gt, est, with_align(Alignment::kSe3));
    FAIL() << "expected an exception";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("only 0 of 501"), std::string::npos) << e.what();
  }
}

TEST(EvalAssociation, RejectsNonsenseOptions) {
  const Trajectory gt = lissajous(5.0);
  EvalOptions o;
  o.rpe_delta_s = 0;
  EXPECT_THROW(evaluate(gt, gt, o), std::invalid_argument);
  o = EvalOptions{};
  o.max_gap_ms = -1;
  EXPECT_THROW(evaluate(gt, gt, o), std::invalid_argument);
  EXPECT_FALSE(parse_alignment("se(3)").has_value());
  EXPECT_EQ(parse_alignment("sim3"), Alignment::kSim3);
}

TEST(EvalAssociation, UnsortedInputIsSortedAndSaid) {
  const Trajectory gt = lissajous(5.0);
  Trajectory est = gt;
  std::swap(est[10], est[20]);
  const EvalResult r = evaluate(gt, est, with_align(Alignment::kNone));
  EXPECT_NEAR(r.ate_m.rmse, 0.0, 1e-12);
  ASSERT_FALSE(r.warnings.empty());
  EXPECT_NE(r.warnings.front().find("not sorted"), std::string::npos);
}

TEST(EvalRealData, TumFr1XyzAssociatesWithItselfShiftedBy5ms) {
  KESTREL_REQUIRE_SHARED("tum-rgbd/rgbd_dataset_freiburg1_xyz/groundtruth.txt");
  const std::string path = test::shared_path("tum-rgbd/rgbd_dataset_freiburg1_xyz/groundtruth.txt");
  std::vector<std::string> warnings;
  const Trajectory gt = load_trajectory(path, &warnings);
  for (const auto& w : warnings) ADD_FAILURE() << "unexpected warning: " << w;
  ASSERT_GT(gt.size(), 1000u);

  // The same poses stamped 5 ms later: what a camera-clock offset looks like.
  Trajectory est = gt;
  for (auto& p : est) p.t_ns += 5'000'000;
  EvalOptions o = with_align(Alignment::kNone);
  const EvalResult r = evaluate(gt, est, o);

  // Each shifted pose has a ground-truth neighbour 5 ms before it; every one associates,
  // by interpolation unless the mocap skipped a sample there.
  EXPECT_EQ(r.matched, static_cast<int>(gt.size()));
  EXPECT_EQ(r.unmatched, 0);
  int expect_interp = 0;
  double max_step = 0;
  for (size_t i = 0; i + 1 < gt.size(); ++i) {
    const bool both = gt[i + 1].t_ns - (gt[i].t_ns + 5'000'000) <= 20'000'000;
    if (both) ++expect_interp;
    max_step = std::max(max_step, (gt[i + 1].p - gt[i].p).norm());
  }
  EXPECT_EQ(r.interpolated, expect_interp);
  // The error is the motion over 5 ms: positive, and never more than one mocap step.
  EXPECT_GT(r.ate_m.rmse, 1e-5);
  EXPECT_LE(r.ate_m.max, max_step + 1e-12);
  EXPECT_GT(r.coverage, 0.99);

  // With no shift the association is exact.
  const EvalResult self = evaluate(gt, gt, o);
  EXPECT_EQ(self.interpolated, 0);
  EXPECT_EQ(self.ate_m.max, 0.0);
}

// ---- anchor_to_keyframes: the odometry through the map's final keyframes ----

Eigen::Isometry3d iso_of(const TimedPose& p) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = p.q.toRotationMatrix();
  T.translation() = p.p;
  return T;
}

Eigen::Isometry3d correction(double x, double yaw) {
  Eigen::Isometry3d C = Eigen::Isometry3d::Identity();
  C.linear() = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  C.translation() = Eigen::Vector3d(x, 0.3, -0.1);
  return C;
}

KeyframeAnchor anchor(const Trajectory& odom, size_t i, const Eigen::Isometry3d& C) {
  return {odom[i].t_ns, C * iso_of(odom[i]), iso_of(odom[i])};
}

TEST(EvalKeyframeAnchors, OneCorrectionEverywhereMovesEveryPoseByIt) {
  const Trajectory odom = lissajous();
  ASSERT_GT(odom.size(), 100u);
  const Eigen::Isometry3d C = correction(1.0, 0.4);
  const std::vector<KeyframeAnchor> kfs{anchor(odom, 10, C), anchor(odom, 50, C), anchor(odom, 90, C)};
  const Trajectory out = anchor_to_keyframes(odom, kfs);
  ASSERT_EQ(out.size(), odom.size());
  for (size_t i = 0; i < odom.size(); ++i) {
    const Eigen::Isometry3d want = C * iso_of(odom[i]);
    EXPECT_EQ(out[i].t_ns, odom[i].t_ns);
    EXPECT_NEAR((out[i].p - want.translation()).norm(), 0.0, 1e-9) << i;
    EXPECT_NEAR(out[i].q.angularDistance(Eigen::Quaterniond(want.linear())), 0.0, 1e-9) << i;
  }
  EXPECT_EQ(anchor_to_keyframes(odom, {}).size(), odom.size());
  EXPECT_NEAR((anchor_to_keyframes(odom, {})[7].p - odom[7].p).norm(), 0.0, 0.0);
}

TEST(EvalKeyframeAnchors, KeyframesLandOnTheirMapPosesAndTheDriftBetweenIsShared) {
  const Trajectory odom = lissajous();
  // The map moved the second keyframe 4 cm along W's x against the first.
  const Eigen::Isometry3d Ca = correction(0.0, 0.3);
  const Eigen::Isometry3d Cb = Ca * Eigen::Translation3d(0.04, 0.0, 0.0);
  std::vector<KeyframeAnchor> kfs{anchor(odom, 20, Ca), anchor(odom, 60, Cb)};
  // The keyframe's own odometry pose was refined after the output went out:
  // the output's pose at its stamp is what lands on the map pose.
  kfs[0].T_WB.translation() += Eigen::Vector3d(0.005, -0.003, 0.002);
  const Trajectory out = anchor_to_keyframes(odom, kfs);
  EXPECT_NEAR((out[20].p - kfs[0].T_MB.translation()).norm(), 0.0, 1e-9);
  EXPECT_NEAR((out[60].p - kfs[1].T_MB.translation()).norm(), 0.0, 1e-9);
  EXPECT_NEAR(out[60].q.angularDistance(Eigen::Quaterniond(kfs[1].T_MB.linear())), 0.0, 1e-9);
  // Before the first and after the last keyframe: that keyframe's correction.
  EXPECT_NEAR((out[5].p - (Ca * iso_of(odom[5])).translation()).norm(), 0.0, 1e-9);
  EXPECT_NEAR((out[90].p - (Cb * iso_of(odom[90])).translation()).norm(), 0.0, 1e-9);
  // Halfway in time: half the 4 cm, along the same axis.
  const size_t mid = 40;
  ASSERT_EQ(odom[mid].t_ns - odom[20].t_ns, odom[60].t_ns - odom[mid].t_ns);
  const Eigen::Vector3d want = Ca * (odom[mid].p + Eigen::Vector3d(0.02, 0.0, 0.0));
  EXPECT_NEAR((out[mid].p - want).norm(), 0.0, 1e-9);
  EXPECT_NEAR(out[mid].q.angularDistance(Eigen::Quaterniond(Ca.linear()) * odom[mid].q), 0.0, 1e-9);
  // A keyframe stamp the odometry has no pose at: the keyframe's own odometry pose anchors it.
  KeyframeAnchor off = kfs[1];
  off.t_ns += 1;
  const Trajectory out2 = anchor_to_keyframes(odom, {kfs[0], off});
  EXPECT_NEAR((out2[90].p - (Cb * iso_of(odom[90])).translation()).norm(), 0.0, 1e-9);
}

TEST(EvalKeyframeAnchors, AJumpBetweenTwoKeyframesIsNotSpreadOverThePosesBetween) {
  const Trajectory odom = lissajous();
  // 1 m or 0.3 rad apart: a relocalisation or an odometry reset, not drift.
  for (const Eigen::Isometry3d& Cb : {correction(1.0, 0.0), correction(0.0, 0.3)}) {
    const Eigen::Isometry3d Ca = correction(0.0, 0.0);
    const Trajectory out = anchor_to_keyframes(odom, {anchor(odom, 20, Ca), anchor(odom, 60, Cb)});
    for (size_t i = 20; i < 60; ++i)
      EXPECT_NEAR((out[i].p - (Ca * iso_of(odom[i])).translation()).norm(), 0.0, 1e-9) << i;
    EXPECT_NEAR((out[60].p - (Cb * iso_of(odom[60])).translation()).norm(), 0.0, 1e-9);
  }
  // The gate sees the step at the body, not at W's origin: 0.01 rad of yaw
  // between the corrections is drift even 30 m from the origin.
  Trajectory far = odom;
  for (TimedPose& p : far) p.p += Eigen::Vector3d(30.0, 0.0, 0.0);
  const Eigen::Isometry3d Ca = Eigen::Isometry3d::Identity();
  Eigen::Isometry3d Cb = Eigen::Isometry3d::Identity();
  Cb.linear() = Eigen::AngleAxisd(0.01, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  // About the keyframe's own position, as drift acts.
  const Eigen::Vector3d c = far[60].p;
  Cb.translation() = c - Cb.linear() * c;
  const Trajectory out = anchor_to_keyframes(far, {anchor(far, 20, Ca), anchor(far, 60, Cb)});
  EXPECT_GT((out[40].p - far[40].p).norm(), 1e-4) << "0.01 rad of drift was taken for a jump";
}

}  // namespace
}  // namespace kestrel::tools
