// The rgbd backend (RGB-D tracking without an IMU) on simulated flights with
// the IMU withheld: accuracy after an SE(3) alignment, every frame posed,
// LONSC-ordered runs against RANSAC, no heap allocation, and the automatic
// choice for logs without an IMU.
#include <gtest/gtest.h>

#include "estimator_harness.hpp"
#include "kestrel/core/estimator_config.hpp"
#include "kestrel/core/rgbd_estimator.hpp"

using namespace kestrel;

namespace {

const auto kNoImu = [](const ImuSample&) { return false; };

test::EstimatorMaker rgbd_maker(core::RigidMethod method = core::RigidMethod::kLonsc, bool window = true) {
  return [=](const Rig& rig) -> std::unique_ptr<core::Estimator> {
    core::EstimatorConfig c = core::EstimatorConfig::defaults("rgbd");
    c.tracker.rigid_method = method;
    c.rgbd.use_window = window;
    return core::make_estimator(c, rig);
  };
}

double ate_se3(const test::RunResult& r) {
  tools::EvalOptions eo;
  eo.align = tools::Alignment::kSe3;
  return tools::evaluate(r.gt, r.est, eo).ate_m.rmse;
}

// Forwards a log but withholds every k-th depth image, as the 7-Scenes
// reader withholds a depth image byte-identical to the one before.
class WithholdDepth : public drivers::LogSource {
 public:
  WithholdDepth(drivers::LogSource& in, int every) : in_(in), every_(every) {}
  const Rig& rig() const override { return in_.rig(); }
  bool next(drivers::LogRecord& out) override {
    while (in_.next(out)) {
      if (out.type == drivers::RecordType::kDepth && ++depth_seen_ % every_ == 0) continue;
      return true;
    }
    return false;
  }
  void rewind() override { in_.rewind(); }
  const std::vector<drivers::LogProblem>& problems() const override { return in_.problems(); }
  std::string format_name() const override { return in_.format_name(); }

 private:
  drivers::LogSource& in_;
  int every_;
  int depth_seen_ = 0;
};

const core::RgbdEstimator& as_rgbd(const std::unique_ptr<core::Estimator>& e) {
  return dynamic_cast<const core::RgbdEstimator&>(*e);
}

}  // namespace

TEST(RgbdEstimator, Figure8WithoutImuTracksEveryFrame) {
  const std::string path = test::simulate("figure8", 10.0, 3);
  std::unique_ptr<core::Estimator> est;
  const test::RunResult r = test::run(path, rgbd_maker(), kNoImu, &est);
  const core::RgbdCounters& c = as_rgbd(est).rgbd_counters();
  const double ate = ate_se3(r);
  std::printf("figure8 10 s without IMU: ATE (se3) %.4f m over %zu poses of %llu frames; %s\n", ate,
              r.est.size(), static_cast<unsigned long long>(r.frames_total), est->backend_summary().c_str());
  EXPECT_EQ(std::string(est->name()), "rgbd");
  EXPECT_EQ(r.est.size(), r.frames_total);
  EXPECT_GE(c.tracked + c.keyframes, r.frames_total * 98 / 100);
  EXPECT_EQ(c.restarts, 0u);
  EXPECT_GE(c.solves_ok, c.tracked * 9 / 10);
  EXPECT_LT(ate, 0.03);
  EXPECT_EQ(est->output().quality, core::TrackingQuality::kVisionOnly);
  EXPECT_EQ(est->counters().imu_used, 0u);
}

TEST(RgbdEstimator, LonscRunsAndRansacBothTrackAndTheWindowHelps) {
  const std::string path = test::simulate("figure8", 6.0, 5);
  std::unique_ptr<core::Estimator> l, r, t;
  const double ate_l = ate_se3(test::run(path, rgbd_maker(core::RigidMethod::kLonsc), kNoImu, &l));
  const double ate_r = ate_se3(test::run(path, rgbd_maker(core::RigidMethod::kRansac), kNoImu, &r));
  const double ate_t = ate_se3(test::run(path, rgbd_maker(core::RigidMethod::kLonsc, false), kNoImu, &t));
  std::printf("figure8 6 s without IMU: ATE lonsc %.4f m (%s)\n  ransac %.4f m (%s)\n  no window %.4f m\n",
              ate_l, l->backend_summary().c_str(), ate_r, r->backend_summary().c_str(), ate_t);
  EXPECT_LT(ate_l, 0.03);
  EXPECT_LT(ate_r, 0.03);
  EXPECT_LT(ate_l, ate_t * 1.05);
  EXPECT_EQ(as_rgbd(l).rgbd_counters().restarts, 0u);
  EXPECT_EQ(as_rgbd(r).rgbd_counters().restarts, 0u);
}

// A frame without depth has no 3D-3D pairs for the rigid consensus; the
// motion-model fallback poses it from the keyframe's points alone. Off, the
// same frames are lost.
TEST(RgbdEstimator, AFrameWithoutDepthIsPosedByTheMotionModel) {
  const std::string path = test::simulate("figure8", 6.0, 7);
  auto run_with = [&](int min_inliers, std::unique_ptr<core::Estimator>* est) {
    auto log = drivers::open_log(path);
    WithholdDepth holed(*log, 7);
    core::EstimatorConfig c = core::EstimatorConfig::defaults("rgbd");
    c.tracker.motion_model_min_inliers = min_inliers;
    *est = core::make_estimator(c, log->rig());
    return test::run_on(holed, **est, kNoImu);
  };
  std::unique_ptr<core::Estimator> on, off;
  const test::RunResult r_on = run_with(30, &on);
  const test::RunResult r_off = run_with(0, &off);
  const core::RgbdCounters& c_on = as_rgbd(on).rgbd_counters();
  const core::RgbdCounters& c_off = as_rgbd(off).rgbd_counters();
  const double ate_on = ate_se3(r_on);
  std::printf("figure8 6 s, every 7th depth withheld: fallback on ATE %.4f m (%s)\n  off: %s\n", ate_on,
              on->backend_summary().c_str(), off->backend_summary().c_str());
  const uint64_t holes = r_on.frames_total / 7;
  ASSERT_GT(holes, 20u);
  EXPECT_GE(c_off.lost_no_motion, holes * 9 / 10) << "without the fallback a depth-less frame is lost";
  EXPECT_GE(c_on.motion_model, holes * 9 / 10);
  EXPECT_EQ(c_on.lost, 0u);
  EXPECT_LT(ate_on, 0.03);
}

TEST(RgbdEstimator, NoHeapAllocationInSteadyState) {
  const std::string path = test::simulate("figure8", 5.0, 11);
  std::unique_ptr<core::Estimator> est;
  const test::RunResult r = test::run(path, rgbd_maker(), kNoImu, &est);
  ASSERT_TRUE(rt::alloc_hook_linked());
  ASSERT_GT(r.frames, 60u);
  EXPECT_GT(as_rgbd(est).rgbd_counters().solves_ok, 60u);
  EXPECT_EQ(r.steady_allocs, 0u) << "allocations in add_frame (tracking + window inline) after warm-up";
}

TEST(RgbdEstimator, ChosenAutomaticallyWhenTheRigHasNoImu) {
  Rig rig = tools::default_sim_rig(320, 240);
  EXPECT_EQ(std::string(core::make_estimator("auto", rig)->name()), "window");
  rig.imu_rate_hz = 0;
  EXPECT_EQ(std::string(core::make_estimator("auto", rig)->name()), "rgbd");
  EXPECT_EQ(core::resolve_backend("auto", rig), "rgbd");
  EXPECT_EQ(core::resolve_backend("vo", rig), "vo");
  EXPECT_EQ(core::EstimatorConfig{}.backend, "auto");
}
