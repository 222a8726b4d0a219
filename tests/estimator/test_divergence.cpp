// The divergence monitor's decisions on hand-made state sequences: every
// cause fires at its bound and not before, a fix clears the lost flag, and
// the time accounting (coast, lost) adds up.
#include <gtest/gtest.h>

#include "kestrel/core/divergence.hpp"

namespace kestrel::core {
namespace {

constexpr int64_t kMs = 1'000'000;

NavState state_at(int64_t t_ns) {
  NavState x;
  x.t_ns = t_ns;
  return x;
}

// Feeds IMU-rate checks (every 5 ms) from t0 to t1 and returns the first cause.
DivergenceCause run(DivergenceMonitor& m, int64_t t0, int64_t t1, NavState x = NavState{}) {
  for (int64_t t = t0; t <= t1; t += 5 * kMs) {
    x.t_ns = t;
    const DivergenceCause c = m.check(x, nullptr);
    if (c != DivergenceCause::kNone) return c;
  }
  return DivergenceCause::kNone;
}

TEST(Divergence, TrackingEveryFrameNeverFires) {
  DivergenceMonitor m;
  for (int64_t t = 0; t < 20'000 * kMs; t += 5 * kMs) {
    if (t % (33 * kMs) < 5 * kMs) m.on_frame(t, true, false);
    ASSERT_EQ(m.check(state_at(t), nullptr), DivergenceCause::kNone) << t;
  }
  EXPECT_FALSE(m.lost());
  EXPECT_EQ(m.counts().divergences, 0u);
  EXPECT_EQ(m.counts().coast_timeouts, 0u);
  EXPECT_EQ(m.counts().coast_ns, 0);
}

TEST(Divergence, CoastTimeoutFlagsLostKeepsStateThenRestartsAfterMaxLost) {
  DivergenceOptions o;
  o.max_coast_s = 1.0;
  o.max_lost_s = 5.0;
  DivergenceMonitor m(o);
  m.on_frame(0, true, false);
  // Up to the bound: coasting, not lost.
  EXPECT_EQ(run(m, 0, 1000 * kMs), DivergenceCause::kNone);
  EXPECT_FALSE(m.lost());
  EXPECT_TRUE(m.coasting(1000 * kMs));
  // Past it: lost, but no restart asked for (the state is kept).
  EXPECT_EQ(run(m, 1005 * kMs, 1010 * kMs), DivergenceCause::kNone);
  EXPECT_TRUE(m.lost());
  EXPECT_EQ(m.counts().coast_timeouts, 1u);
  EXPECT_EQ(m.counts().divergences, 0u);
  // max_lost_s later: restart, counted as one divergence.
  EXPECT_EQ(run(m, 1015 * kMs, 6000 * kMs), DivergenceCause::kNone);
  const DivergenceCause c = run(m, 6005 * kMs, 6100 * kMs);
  ASSERT_EQ(c, DivergenceCause::kCoastTimeout);
  m.on_reinitialised(6010 * kMs, c);
  EXPECT_EQ(m.counts().divergences, 1u);
  EXPECT_EQ(m.counts().by_cause[static_cast<size_t>(DivergenceCause::kCoastTimeout)], 1u);
  // Still no fix: the next restart is one of the same outage, not a new divergence.
  const DivergenceCause c2 = run(m, 6015 * kMs, 12000 * kMs);
  ASSERT_EQ(c2, DivergenceCause::kCoastTimeout);
  m.on_reinitialised(11015 * kMs, c2);
  EXPECT_EQ(m.counts().divergences, 1u);
  EXPECT_EQ(m.counts().restarts_while_lost, 1u);
  // A fix ends the outage.
  m.on_frame(11100 * kMs, true, false);
  EXPECT_FALSE(m.lost());
  // Coast time: from the grace (0.1 s) to the timeout (1 s); lost from there to the fix.
  EXPECT_NEAR(1e-9 * static_cast<double>(m.counts().coast_ns), 0.9, 0.01);
  EXPECT_NEAR(1e-9 * static_cast<double>(m.counts().lost_ns), 11.1 - 1.0, 0.02);
}

TEST(Divergence, NoFixEverIsAnOutageFromTheFirstState) {
  DivergenceMonitor m;
  EXPECT_EQ(run(m, 500 * kMs, 1500 * kMs), DivergenceCause::kNone);
  EXPECT_FALSE(m.lost());
  EXPECT_EQ(run(m, 1505 * kMs, 1600 * kMs), DivergenceCause::kNone);
  EXPECT_TRUE(m.lost()) << "a camera that never gives a fix must not leave the pose trusted";
}

TEST(Divergence, SanityBoundsFireAtTheirLimits) {
  DivergenceOptions o;
  {
    DivergenceMonitor m(o);
    m.on_frame(0, true, false);
    NavState x = state_at(5 * kMs);
    x.v_WB = Eigen::Vector3d(0.99 * o.max_speed_mps, 0, 0);
    EXPECT_EQ(m.check(x, nullptr), DivergenceCause::kNone);
    x.v_WB = Eigen::Vector3d(1.01 * o.max_speed_mps, 0, 0);
    EXPECT_EQ(m.check(x, nullptr), DivergenceCause::kSpeed);
  }
  {
    DivergenceMonitor m(o);
    m.on_frame(0, true, false);
    NavState x = state_at(5 * kMs);
    x.ba_mps2 = Eigen::Vector3d(0, 0.99 * o.max_acc_bias_mps2, 0);
    EXPECT_EQ(m.check(x, nullptr), DivergenceCause::kNone);
    x.ba_mps2 = Eigen::Vector3d(0, 1.01 * o.max_acc_bias_mps2, 0);
    EXPECT_EQ(m.check(x, nullptr), DivergenceCause::kAccBias);
  }
  {
    DivergenceMonitor m(o);
    m.on_frame(0, true, false);
    NavState x = state_at(5 * kMs);
    x.bg_rps = Eigen::Vector3d(0, 0, 1.01 * o.max_gyro_bias_rps);
    EXPECT_EQ(m.check(x, nullptr), DivergenceCause::kGyroBias);
  }
  {
    DivergenceMonitor m(o);
    m.on_frame(0, true, false);
    PoseCovariance cov;
    cov.valid = true;
    cov.cov.setIdentity();
    const double s = o.max_position_sigma_m;
    cov.cov(2, 2) = 0.98 * s * s;
    EXPECT_EQ(m.check(state_at(5 * kMs), &cov), DivergenceCause::kNone);
    cov.cov(2, 2) = 1.02 * s * s;
    EXPECT_EQ(m.check(state_at(5 * kMs), &cov), DivergenceCause::kCovariance);
    cov.valid = false;  // a covariance the backend does not vouch for is not judged
    EXPECT_EQ(m.check(state_at(5 * kMs), &cov), DivergenceCause::kNone);
  }
  {
    DivergenceMonitor m(o);
    NavState x = state_at(5 * kMs);
    x.p_WB.x() = std::numeric_limits<double>::quiet_NaN();
    EXPECT_EQ(m.check(x, nullptr), DivergenceCause::kNonFinite);
  }
}

TEST(Divergence, PersistentDisagreementBetweenVisionAndImu) {
  DivergenceOptions o;
  o.max_rejected_fixes = 4;
  DivergenceMonitor m(o);
  m.on_frame(0, true, false);
  int64_t t = 0;
  // A healthy flight: the odd refusal among fixes never adds up.
  for (int k = 0; k < 100; ++k) {
    m.on_frame(t += 33 * kMs, false, k % 3 == 0);
    m.on_frame(t += 33 * kMs, true, false);
  }
  EXPECT_EQ(m.check(state_at(t), nullptr), DivergenceCause::kNone);
  // Refusals broken by frames with no pose (new keyframes) and a rare fix
  // still add up: 3 refusals and a keyframe per cycle, a fix every other cycle.
  int cycles = 0;
  while (m.check(state_at(t), nullptr) == DivergenceCause::kNone && cycles < 10) {
    for (int k = 0; k < 3; ++k) m.on_frame(t += 33 * kMs, false, true);
    m.on_frame(t += 33 * kMs, false, false);
    if (cycles % 2 == 1) m.on_frame(t += 33 * kMs, true, false);
    ++cycles;
  }
  EXPECT_LE(cycles, 3);
  EXPECT_EQ(m.check(state_at(t), nullptr), DivergenceCause::kVisualImuDisagreement);
  m.on_reinitialised(t, DivergenceCause::kVisualImuDisagreement);
  EXPECT_TRUE(m.lost());
  EXPECT_EQ(m.check(state_at(t + kMs), nullptr), DivergenceCause::kNone) << "the count starts over";
  EXPECT_EQ(m.counts().by_cause[static_cast<size_t>(DivergenceCause::kVisualImuDisagreement)], 1u);
}

TEST(Divergence, OptionsValidateNamesTheKey) {
  DivergenceOptions o;
  EXPECT_EQ(o.validate(), "");
  o.max_coast_s = 0;
  o.max_rejected_fixes = -1;
  const std::string e = o.validate();
  EXPECT_NE(e.find("max_coast_s"), std::string::npos) << e;
  EXPECT_NE(e.find("max_rejected_fixes"), std::string::npos) << e;
}

}  // namespace
}  // namespace kestrel::core
