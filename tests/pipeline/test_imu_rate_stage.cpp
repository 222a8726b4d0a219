// The IMU-rate pose stage that `kestrel replay` (realtime pace) and `kestrel
// run` share (tools/kestrel/imu_rate_stage.hpp): every sample is forwarded to
// the estimator in order, a pose is published for each sample once an anchor
// exists, a newer anchor re-propagates over the samples after it, and the
// steady state allocates nothing.
#include <gtest/gtest.h>

#include <memory>

#include "kestrel/core/estimator.hpp"
#include "kestrel/imu_rate_stage.hpp"
#include "kestrel/rt/alloc_counter.hpp"
#include "kestrel/rt/clock.hpp"

namespace kestrel::cli {
namespace {

Rig test_rig() {
  Rig r;
  r.imu_rate_hz = 400;
  return r;
}

ImuSample still_sample(int64_t t_ns) {
  ImuSample s{};
  s.t_ns = t_ns;
  s.t_recv_ns = rt::now_ns();
  s.acc_mps2[2] = 9.81;  // level, at rest: the specific force is +g along z
  return s;
}

TEST(ImuRateStage, ForwardsEverySampleAndPublishesFromTheAnchor) {
  auto in = std::make_unique<ImuRing>();
  auto fwd = std::make_unique<ImuRing>();
  auto anchor = std::make_unique<rt::Mailbox<Anchor>>();
  auto pose = std::make_unique<rt::Mailbox<core::PoseSample>>();
  const Rig rig = test_rig();
  ImuRateStage stage(*in, *fwd, *anchor, rig, 0, *pose);
  const int64_t dt = 2'500'000;
  // No anchor yet: samples are forwarded, no pose is published.
  for (int i = 0; i < 10; ++i) ASSERT_TRUE(in->try_push(still_sample(i * dt)));
  EXPECT_TRUE(stage.step());
  EXPECT_FALSE(stage.step()) << "the ring is drained";
  EXPECT_EQ(fwd->size(), 10u);
  EXPECT_EQ(pose->version(), 0u);
  // An anchor at sample 5, moving at 1 m/s along x: the pose at the next sample
  // is re-propagated from it over samples 5..10 (the history), 5 periods later.
  core::EstimatorOutput o;
  o.state.t_ns = 5 * dt;
  o.state.p_WB = Eigen::Vector3d(1, 2, 3);
  o.state.v_WB = Eigen::Vector3d(1, 0, 0);
  o.quality = core::TrackingQuality::kTracking;
  o.reset_counter = 4;
  anchor->publish(to_anchor(o));
  ASSERT_TRUE(in->try_push(still_sample(10 * dt)));
  const uint64_t a0 = rt::alloc_count_this_thread();
  EXPECT_TRUE(stage.step());
  EXPECT_EQ(rt::alloc_count_this_thread(), a0) << "step() allocated";
  core::PoseSample p;
  ASSERT_TRUE(pose->read(p));
  EXPECT_EQ(p.t_ns, 10 * dt);
  EXPECT_NEAR(p.p_WB_m[0], 1 + 5 * 2.5e-3, 1e-6);
  EXPECT_NEAR(p.p_WB_m[1], 2, 1e-9);
  EXPECT_NEAR(p.p_WB_m[2], 3, 1e-6);
  EXPECT_EQ(p.quality, core::TrackingQuality::kTracking);
  EXPECT_EQ(p.reset_counter, 4u);
  // Forwarded in order, none lost.
  ImuSample s;
  for (int i = 0; i <= 10; ++i) {
    ASSERT_TRUE(fwd->try_pop(s));
    EXPECT_EQ(s.t_ns, i * dt);
  }
  stage.finish();
  EXPECT_EQ(stage.stats().forward_drops, 0u);
  EXPECT_EQ(stage.stats().poses, 1u);
  EXPECT_EQ(stage.stats().imu_to_output.count(), 1u);
}

TEST(ImuRateStage, AFullForwardRingIsCountedNotBlocking) {
  auto in = std::make_unique<ImuRing>();
  auto fwd = std::make_unique<ImuRing>();
  auto anchor = std::make_unique<rt::Mailbox<Anchor>>();
  auto pose = std::make_unique<rt::Mailbox<core::PoseSample>>();
  ImuRateStage stage(*in, *fwd, *anchor, test_rig(), 0, *pose);
  while (fwd->try_push(still_sample(0))) {
  }
  for (int i = 0; i < 3; ++i) ASSERT_TRUE(in->try_push(still_sample(i)));
  EXPECT_TRUE(stage.step());
  EXPECT_EQ(stage.stats().forward_drops, 3u);
}

}  // namespace
}  // namespace kestrel::cli
