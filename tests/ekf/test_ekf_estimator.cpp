// The EKF backend as a pipeline estimator (`--estimator ekf`) on simulated
// RGB-D + IMU logs: accuracy against IMU dead reckoning, consistency of its
// pose covariance (NEES against ground truth), and zero heap allocations per
// frame in steady state.
#include <gtest/gtest.h>

#include <cmath>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "estimator_harness.hpp"
#include "kestrel/core/ekf_estimator.hpp"
#include "kestrel/core/estimator.hpp"
#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/drivers/log_source.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/rt/alloc_counter.hpp"
#include "kestrel/tools/simulator.hpp"
#include "kestrel/tools/trajectory_eval.hpp"
#include "test_data.hpp"

using namespace kestrel;

namespace {

std::string simulate(const std::string& scenario, double duration_s, uint64_t seed) {
  return test::simulate(scenario, duration_s, seed, "ekf_estimator");
}

using test::ate;
using test::run;
using test::RunResult;

core::ekf::Pose to_pose(const tools::TimedPose& p) { return {p.q.normalized().toRotationMatrix(), p.p}; }

// Position and yaw are unobservable and fixed by the static initialiser (zero
// at start-up, with a millimetre / 10 mrad prior): ground truth is moved into
// the estimator's frame by the position + yaw that make the two agree at the
// first estimate, once, not fitted over the run (that would hide drift the
// covariance must explain).
struct Nees {
  double mean = 0, mean_pos = 0, mean_rot = 0, ate_m = 0;
  int n = 0;
};

Nees pose_nees(const std::string& log_path, double skip_s) {
  auto rig_log = drivers::open_log(log_path);
  core::EkfEstimator est(rig_log->rig());
  bool aligned = false;
  core::ekf::Pose A;  // ground-truth world -> estimator world
  int64_t t0 = -1;
  double sum = 0, sum_p = 0, sum_r = 0, pos2 = 0;
  int n = 0;
  run(log_path, est, [&](const tools::TimedPose& gt) {
    const core::ekf::Pose T_gt = to_pose(gt);
    const core::ekf::Pose& T_est = est.filter().pose();
    if (!aligned) {
      // Yaw of the body x axis projected on the ground plane.
      const auto yaw_of = [](const Eigen::Matrix3d& R) { return std::atan2(R(1, 0), R(0, 0)); };
      const double dyaw = yaw_of(T_est.R) - yaw_of(T_gt.R);
      A.R = Eigen::AngleAxisd(dyaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
      A.p = T_est.p - A.R * T_gt.p;
      aligned = true;
      t0 = gt.t_ns;
    }
    if (1e-9 * static_cast<double>(gt.t_ns - t0) < skip_s) return;
    const core::ekf::Pose T_true = A * T_gt;
    const core::ekf::Vec6 e = core::ekf::se3_log(T_est.inverse() * T_true);
    const core::ekf::Mat6 P = est.pose_covariance();
    sum += e.dot(P.ldlt().solve(e));
    sum_p += e.head<3>().dot(P.topLeftCorner<3, 3>().ldlt().solve(e.head<3>()));
    sum_r += e.tail<3>().dot(P.bottomRightCorner<3, 3>().ldlt().solve(e.tail<3>()));
    pos2 += (T_est.p - T_true.p).squaredNorm();
    ++n;
  });
  Nees r;
  r.n = n;
  if (n > 0) {
    r.mean = sum / n;
    r.mean_pos = sum_p / n;
    r.mean_rot = sum_r / n;
    r.ate_m = std::sqrt(pos2 / n);
  }
  return r;
}

}  // namespace

TEST(EkfEstimator, FactoryKnowsIt) {
  EXPECT_TRUE(core::estimator_known("ekf"));
  EXPECT_NE(std::string(core::estimator_names()).find("ekf"), std::string::npos);
  auto log = drivers::open_log(simulate("static", 1.0, 3));
  auto est = core::make_estimator("ekf", log->rig());
  EXPECT_STREQ(est->name(), "ekf");
}

// A log that starts on a running airframe (rotor vibration) shows no still
// window for a second or more. Every IMU backend starts from a moving window
// after its moving_start_after_ns (0.25 s by default, the window's value):
// with the old 2 s, vo and ekf left the first second of the EuRoC MH_01
// flights unposed (96.6 % of frames). A still IMU still starts at once.
TEST(EkfEstimator, EveryImuBackendStartsWithinAQuarterSecondWithoutAStillWindow) {
  auto log = drivers::open_log(simulate("static", 1.0, 3));
  const Rig& rig = log->rig();
  const double g = rig.gravity_mps2;
  // The first time [s] the backend's state exists, fed 1 s of 400 Hz IMU:
  // rocking at 3 Hz (the still test compares 0.1 s block means, so the
  // motion must be slower than a block; far beyond its thresholds) or still.
  auto first_state_s = [&](const std::string& name, bool moving) {
    auto est = core::make_estimator(name, rig);
    for (int i = 0; i < 400; ++i) {
      ImuSample s;
      s.t_ns = 1'000'000'000 + int64_t{i} * 2'500'000;
      const double v = moving ? std::sin(2 * M_PI * 3.0 * i * 0.0025) : 0.0;
      s.gyro_rps = {0.3 * v, -0.2 * v, 0.1 * v};
      s.acc_mps2 = {2.0 * v, 1.0 * v, g + 3.0 * v};
      est->add_imu(s);
      if (est->output().quality != core::TrackingQuality::kUninitialized)
        return 1e-9 * static_cast<double>(i) * 2.5e6;
    }
    return -1.0;
  };
  for (const char* name : {"vo", "ekf", "imu"}) {
    const double moving_s = first_state_s(name, true), still_s = first_state_s(name, false);
    std::printf("%s: first state at %.3f s moving, %.3f s still\n", name, moving_s, still_s);
    EXPECT_GT(moving_s, 0.24) << name << ": a moving start must wait for a still window first";
    EXPECT_LT(moving_s, 0.27) << name;
    EXPECT_GT(still_s, 0.0) << name;
    EXPECT_LT(still_s, 0.22) << name << ": a still window starts at once";
  }
}

// After a divergence the filter restarts from its coasted position, which is
// a guess: its position sigma says so (ekf.restart_position_sigma_m), where a
// 1 mm sigma made it refuse every local-map pose more than ~8 cm away.
TEST(EkfEstimator, ARestartKeepsThePositionAsAGuessNotAsTheOrigin) {
  auto log = drivers::open_log(simulate("static", 1.0, 3));
  const Rig& rig = log->rig();
  auto est = core::make_estimator("ekf", rig);
  auto position_sigma_m = [&] {
    const core::PoseCovariance& c = est->output().pose_cov;
    return c.valid ? std::sqrt(c.cov.topLeftCorner<3, 3>().diagonal().maxCoeff()) : -1.0;
  };
  int64_t t_ns = 1'000'000'000;
  auto feed = [&](double seconds, double push_mps2) {
    for (int i = 0; i < static_cast<int>(seconds * 400); ++i, t_ns += 2'500'000) {
      ImuSample s;
      s.t_ns = t_ns;
      s.acc_mps2 = {push_mps2, 0.0, rig.gravity_mps2};
      est->add_imu(s);
    }
  };
  // A still start defines W: its position sigma is init_position_sigma_m.
  while (est->output().quality == core::TrackingQuality::kUninitialized && t_ns < 2'000'000'000)
    feed(0.0025, 0.0);
  const double sigma_before = position_sigma_m();
  ASSERT_GT(sigma_before, 0.0);
  EXPECT_LT(sigma_before, 0.005);
  feed(0.3, 0.0);
  const uint32_t resets_before = est->output().reset_counter;
  // A push no airframe survives: past max_speed_mps (25 m/s) within 0.3 s.
  int64_t restart_t_ns = -1;
  for (int i = 0; i < 160 && restart_t_ns < 0; ++i) {
    feed(0.0025, 100.0);
    if (est->output().reset_counter != resets_before) restart_t_ns = t_ns;
  }
  ASSERT_GT(restart_t_ns, 0) << "the speed check never fired";
  const double sigma_after = position_sigma_m();
  std::printf("position sigma %.4f m at the start, %.4f m right after the restart\n", sigma_before,
              sigma_after);
  EXPECT_GE(sigma_after, 0.045);
  EXPECT_LT(sigma_after, 0.2);
}

TEST(EkfEstimator, HoverBeatsDeadReckoningWithinCentimetres) {
  const std::string path = simulate("hover", 8.0, 7);
  auto log = drivers::open_log(path);
  core::EkfEstimator ekf(log->rig());
  const RunResult r = run(path, ekf);
  auto imu = core::make_estimator("imu", log->rig());
  const RunResult ri = run(path, *imu);
  const double ate_ekf = ate(r), ate_imu = ate(ri);
  const auto& c = ekf.ekf_counters();
  std::printf(
      "[ figure ] hover 8 s 320x240: ATE ekf %.4f m, IMU only %.4f m; frames used %llu of %llu; "
      "observations %llu (no depth %llu), landmarks initialised %llu, gated %llu, capacity full %llu\n",
      ate_ekf, ate_imu, (unsigned long long)r.counters.frames_used, (unsigned long long)r.counters.frames_in,
      (unsigned long long)c.observations_in, (unsigned long long)c.observations_no_depth,
      (unsigned long long)ekf.filter().counters().landmarks_initialised,
      (unsigned long long)ekf.filter().counters().observations_gated,
      (unsigned long long)ekf.filter().counters().capacity_full);
  EXPECT_LT(ate_ekf, 0.02);
  EXPECT_LT(ate_ekf, 0.2 * ate_imu);
  // Of the frames it takes (min_frame_interval_ms skips the others).
  EXPECT_GT(r.counters.frames_used, (r.counters.frames_in - c.frames_skipped) * 9 / 10);
  EXPECT_GT(ekf.filter().counters().observations_used, 1000u);
  EXPECT_EQ(c.filter_resets, 0u);
}

// min_frame_interval_ms: at 50 ms a 30 Hz camera is taken at 15 Hz, at 0
// every frame; the output keeps a pose for every frame either way, and the
// skipped frames cost no tracking. The default is 0 without the map, 50 with.
TEST(EkfEstimator, FramesCloserThanTheIntervalAreSkippedAndTheIMUCarriesTheState) {
  const std::string path = simulate("figure8", 6.0, 21);
  auto log = drivers::open_log(path);
  const double frame_rate_hz = log->rig().camera_rate_hz;
  ASSERT_GT(frame_rate_hz, 25.0) << "the test needs a camera faster than 1 / 50 ms";

  core::EkfEstimatorOptions every;
  every.min_frame_interval_ms = 0.0;
  core::EkfEstimator all(log->rig(), every);
  const RunResult ra = run(path, all);
  core::EkfEstimatorOptions fifty;
  fifty.min_frame_interval_ms = 50.0;
  core::EkfEstimator half(log->rig(), fifty);
  const RunResult rh = run(path, half);
  core::EkfEstimatorOptions defaults;
  EXPECT_EQ(defaults.frame_interval_ms(), 0.0);
  defaults.mapping = true;
  EXPECT_EQ(defaults.frame_interval_ms(), 50.0);

  const auto& ca = all.ekf_counters();
  const auto& ch = half.ekf_counters();
  std::printf(
      "[ figure ] figure8 6 s %.0f Hz: every frame: ATE %.4f m, %llu frames used; "
      "50 ms: ATE %.4f m, %llu used, %llu skipped\n",
      frame_rate_hz, ate(ra), (unsigned long long)ra.counters.frames_used, ate(rh),
      (unsigned long long)rh.counters.frames_used, (unsigned long long)ch.frames_skipped);
  EXPECT_EQ(ca.frames_skipped, 0u);
  // Every other frame of a camera faster than 20 Hz, once started (the
  // frames before the IMU start are neither taken nor skipped).
  EXPECT_GE(ch.frames_skipped, rh.counters.frames_in * 45 / 100);
  EXPECT_LE(ch.frames_skipped, rh.counters.frames_in / 2 + 1);
  EXPECT_LE(rh.counters.frames_used, ra.counters.frames_used / 2 + 2);
  EXPECT_EQ(rh.est.size(), ra.est.size()) << "a skipped frame still gets the propagated pose";
  EXPECT_LT(ate(rh), 0.05);
  EXPECT_LT(ate(ra), 0.05);
}

TEST(EkfEstimator, AfterAFrameThatDidNotTrackEveryFrameIsTakenUntilOneDoes) {
  // A loss at half the frame rate would last twice as long in frames of
  // the camera (on `hard` at 50 ms: 8.4 % of the flight lost instead of 4.1 %).
  const std::string path =
      test::simulate("figure8", 6.0, 23, "ekf_estimator_cover", [](tools::SimOptions& o) {
        o.cover_at_s = 2.5;
        o.cover_s = 1.0;
      });
  auto log = drivers::open_log(path);
  core::EkfEstimatorOptions fifty;
  fifty.min_frame_interval_ms = 50.0;
  core::EkfEstimator est(log->rig(), fifty);
  bool prev_tracking = false;
  uint64_t prev_skipped = 0;
  int after_loss = 0, skipped_after_loss = 0, after_fix = 0, skipped_after_fix = 0;
  test::run(path, est, [&](const tools::TimedPose&) {
    const uint64_t skipped = est.ekf_counters().frames_skipped;
    const bool skipped_now = skipped > prev_skipped;
    (prev_tracking ? after_fix : after_loss) += 1;
    (prev_tracking ? skipped_after_fix : skipped_after_loss) += skipped_now ? 1 : 0;
    prev_skipped = skipped;
    prev_tracking = est.output().quality == core::TrackingQuality::kTracking;
  });
  std::printf(
      "[ figure ] figure8 6 s, lens covered 1 s, 50 ms: %d frames after a fix (%d skipped), "
      "%d after a frame that did not track (%d skipped)\n",
      after_fix, skipped_after_fix, after_loss, skipped_after_loss);
  ASSERT_GE(after_loss, 25) << "the covered second must lose tracking";
  EXPECT_EQ(skipped_after_loss, 0);
  EXPECT_GE(skipped_after_fix, after_fix * 40 / 100) << "every other frame while tracking";
}

TEST(EkfEstimator, PoseNeesIsConsistentOnFigure8) {
  // Mean NEES of a consistent 6-dof pose estimate is 6. EKF-SLAM is known to
  // be mildly over-confident (docs/ekf.md); the band admits up to 3x.
  const Nees n = pose_nees(simulate("figure8", 10.0, 5), 1.0);
  std::printf(
      "[ figure ] figure8 10 s 320x240: pose NEES mean %.2f (6 dof), position %.2f (3), rotation %.2f (3), "
      "ATE (start-aligned) %.4f m over %d frames\n",
      n.mean, n.mean_pos, n.mean_rot, n.ate_m, n.n);
  ASSERT_GT(n.n, 200);
  EXPECT_GT(n.mean, 0.5 * 6);
  EXPECT_LT(n.mean, 3.0 * 6);
  EXPECT_LT(n.ate_m, 0.05);
}

TEST(EkfEstimator, NoHeapAllocationPerFrameInSteadyState) {
  const std::string path = simulate("figure8", 4.0, 11);
  auto log = drivers::open_log(path);
  core::EkfEstimator ekf(log->rig());
  const RunResult r = run(path, ekf);
  ASSERT_TRUE(rt::alloc_hook_linked());
  ASSERT_GT(r.frames, 50u);
  ASSERT_GT(ekf.filter().counters().observations_used, 1000u) << "the run must exercise the update";
  EXPECT_EQ(r.steady_allocs, 0u) << "allocations in add_imu/add_frame after warm-up";
  EXPECT_EQ(ekf.filter().counters().observations_used_without_depth, 0u) << "off by default";
  // With the pixels without depth in the update (2-row observations mixed
  // into the chunks) the frame stays allocation-free, and they are used.
  core::EkfEstimatorOptions with_pixels;
  with_pixels.depthless_observations = true;
  core::EkfEstimator ekf2(log->rig(), with_pixels);
  const RunResult r2 = run(path, ekf2);
  std::printf("[ figure ] figure8 4 s: observations without depth %llu, used %llu\n",
              (unsigned long long)ekf2.ekf_counters().observations_no_depth,
              (unsigned long long)ekf2.filter().counters().observations_used_without_depth);
  ASSERT_GT(ekf2.ekf_counters().observations_no_depth, 0u) << "the flight must have pixels without depth";
  EXPECT_GT(ekf2.filter().counters().observations_used_without_depth, 0u);
  EXPECT_EQ(r2.steady_allocs, 0u) << "allocations with pixels without depth";
}
