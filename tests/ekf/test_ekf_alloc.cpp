// Fixed memory: after warm-up, prediction, IMU propagation and the update
// (association, gating, chunked Cholesky updates with and without depth,
// freezing, initialisation)
// make no heap allocation at all.
//
// rt's allocation hook counts operator new and, outside sanitizer builds,
// malloc & co. too (Eigen allocates with malloc).
#include <gtest/gtest.h>

#include <cstdlib>

#include "ekf_sim.hpp"
#include "kestrel/core/ekf_slam.hpp"
#include "kestrel/rt/alloc_counter.hpp"

namespace {

using namespace kestrel;

// The project's hook counts malloc too (outside sanitizer builds).
unsigned long mallocs_now() { return rt::alloc_hook_counts_malloc() ? rt::alloc_count_this_thread() : 0; }

void run_and_count(core::EkfMotionModel motion, int capacity) {
  ASSERT_TRUE(rt::alloc_hook_linked());
  if (rt::alloc_hook_counts_malloc()) {
    const unsigned long before = mallocs_now();
    void* volatile p = std::malloc(64);
    std::free(p);
    ASSERT_GT(mallocs_now(), before) << "malloc interposition is not in effect";
  }
  const auto traj = tools::make_scenario("figure8", 20.0);
  const test::EkfSimWorld world = test::make_ekf_world(7);
  tools::SimRng rng(5, tools::RngStream::kCamera);
  core::EkfSlamOptions opt;
  opt.motion = motion;
  opt.landmark_capacity = capacity;
  opt.max_missed_frames = 1;
  opt.max_init_depth_m = 15.0;
  core::EkfSlam ekf(opt, world.cam);
  const auto s0 = traj->state(0.0);
  ekf.reset_imu(test::pose_of(s0), s0.v_WB, Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero(),
                core::ekf::Mat6::Identity() * 1e-8, 1e-3, 1e-3, 1e-2);
  // Observations are generated up front: only the filter is measured.
  const double dt = 0.005;
  const int frames = 120;
  std::vector<std::vector<core::StereoObservation>> obs(frames);
  std::vector<std::array<Eigen::Vector3d, 2>> inputs;
  for (int f = 0; f < frames; ++f) {
    for (int k = 0; k < 10; ++k) {
      const auto s = traj->state((f * 10 + k + 0.5) * dt);
      Eigen::Vector3d gyro, acc;
      tools::true_imu(s, 9.81, gyro, acc);
      if (motion == core::EkfMotionModel::kVelocity) acc = s.q_WB.conjugate() * s.v_WB;  // the body velocity
      inputs.push_back({gyro, acc});
    }
    auto& of = obs[static_cast<size_t>(f)];
    test::observe(world, test::pose_of(traj->state((f + 1) * 10 * dt)), 0.5, rng, of, 200);
    // Every fourth observation of every other frame without depth: the
    // chunks then mix 3-row and 2-row observations.
    if (f % 2 == 1)
      for (size_t i = 1; i < of.size(); i += 4) of[i] = core::pixel_only(of[i].id, of[i].uL, of[i].vL);
  }
  unsigned long new_count = 0, malloc_count = 0;
  int max_active = 0, frozen_total = 0, init_total = 0, pose_updates = 0, without_depth_total = 0;
  for (int f = 0; f < frames; ++f) {
    const bool measure = f >= 20;  // warm-up: first frames fill the active set
    rt::AllocCountScope scope;
    const unsigned long m0 = mallocs_now();
    for (int k = 0; k < 10; ++k) {
      const auto& in = inputs[static_cast<size_t>(f * 10 + k)];
      if (motion == core::EkfMotionModel::kImu)
        ekf.propagate_imu(in[0], in[1], dt);
      else
        ekf.predict_velocity(in[1], in[0], dt);
    }
    const auto& o = obs[static_cast<size_t>(f)];
    const core::EkfUpdateStats st = ekf.update(o.data(), static_cast<int>(o.size()));
    if (f % 3 == 0) {
      // The map pose measurement (EkfEstimator, docs/ekf.md) on every third frame, at the truth.
      core::ekf::Mat6 R = core::ekf::Mat6::Identity() * 4e-4;
      pose_updates += ekf.update_pose(test::pose_of(traj->state((f + 1) * 10 * dt)), R, 1e9) ? 1 : 0;
    }
    frozen_total += ekf.frozen_count();
    init_total += st.initialised;
    without_depth_total += st.used_without_depth;
    ekf.clear_frozen();
    if (measure) {
      new_count += scope.count();
      malloc_count += mallocs_now() - m0;
    }
    max_active = std::max(max_active, ekf.num_active());
  }
  EXPECT_EQ(new_count, 0u) << "operator new calls after warm-up";
  EXPECT_EQ(malloc_count, 0u) << "malloc calls after warm-up";
  // The run must have exercised what it claims to.
  EXPECT_EQ(max_active, capacity);
  EXPECT_GT(frozen_total, 50);
  EXPECT_GT(init_total, 50);
  EXPECT_GT(pose_updates, 30);
  EXPECT_GT(without_depth_total, 200);
}

TEST(EkfAlloc, ImuModeStepsAllocateNothing) { run_and_count(core::EkfMotionModel::kImu, 96); }
TEST(EkfAlloc, VelocityModeLargeCapacityAllocatesNothing) {
  run_and_count(core::EkfMotionModel::kVelocity, 120);
}

}  // namespace
